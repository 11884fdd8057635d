"""BVH files: read them (forward kinematics to joint positions) and write motions as BVH.

Parsing, writing and the Euler-angle maths are pybvh's (MIT, needs only numpy and matplotlib,
which odmo has anyway): it handles any rotation channel order, End Sites, and rejects a file
whose MOTION block is truncated or whose value count disagrees with its CHANNELS. It does not
model position channels on non-root joints; such files are reported as unreadable.

Writing (positions -> rotations) is lossy, so the convention is fixed here:
* The file is y-up, in metres, at the motion's fps; the subject's left is +x at rest. Every
  joint's rest offset is its bone's canonical rest direction (`lie.rest_directions`: a T-pose)
  times the bone's mean length in the motion.
* The root and every branching joint (pelvis, chest) take the *body frame* of their children:
  x along left child - right child, y along the middle child (`lie.body_frame`). The facing and
  the torso's twist therefore come from the hip and shoulder lines, never from one bone, so a
  character facing away from the camera is not flipped.
* Every other joint takes the *minimal swing* from its parent's frame that turns its bone's rest
  direction into the bone's direction (as `lie.inverse_kinematics`): bones carry no twist about
  their own axis.
* A branching joint's children hang from zero-length joints named `<parent>_to_<child>`, which
  carry the swing of each child bone: one rotation cannot aim three bones whose angles to each
  other change, and these joints make the positions exact.
* Rotation channels are `Zrotation Yrotation Xrotation` (as the CMU and Character Creator BVH
  files), each frame on the Euler branch nearest the previous frame: curves have no 180- or
  360-degree jumps when the character turns round.
With constant bone lengths the re-imported positions equal the motion's to the file's 6
decimals; a generated motion whose bones stretch differs by that stretch (reported).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pybvh
import torch
from pybvh.bvhnode import BvhEndSite, BvhJoint, BvhRoot
from pybvh.rotations import rotmat_to_euler

from odmo_cli.errors import UserError
from odmo_cli.io import atomic_path
from odmo_cli.kinematics import check_motion
from odmo_cli.lie import body_frame, joint_side, rest_directions, rotation_between, so3_exp
from odmo_cli.skeletons import Skeleton

EULER_ORDER = "ZYX"


@dataclass
class BvhClip:
    """A BVH file after forward kinematics: joints (End Sites excluded) in file order."""

    names: tuple[str, ...]
    parents: tuple[int, ...]  # -1 for the root
    positions: np.ndarray  # (F, J, 3) float64, in the file's units and axes
    fps: float


def read_bvh(path: str | Path) -> BvhClip:
    """Parse a BVH file and run its forward kinematics. UserError (naming the file) when unusable."""
    path = Path(path)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # pybvh warns about guessed up axes; we don't use them
            bvh = pybvh.read_bvh_file(path, world_up="+y")
            positions = bvh.joint_positions()  # (F, J, 3)
    except (ValueError, IndexError, OSError, KeyError) as exc:
        raise UserError(f"{path.name}: {_reason(exc, path)}") from None
    joints = [n for n in bvh.nodes if not n.is_end_site()]
    index = {id(n): i for i, n in enumerate(joints)}
    parents = tuple(-1 if n.parent is None else index[id(n.parent)] for n in joints)
    if not np.isfinite(positions).all():
        raise UserError(f"{path.name}: non-finite values in the MOTION block")
    return BvhClip(tuple(n.name for n in joints), parents, positions, float(bvh.fps))


def _reason(exc: Exception, path: Path) -> str:
    """pybvh's / numpy's message, in the words of the BVH format where they are cryptic."""
    msg = str(exc).replace(f" in file {path}", "").replace(str(path), path.name).strip()
    msg = msg.splitlines()[0] if msg else type(exc).__name__
    if "number of columns changed" in msg:  # numpy.loadtxt on a ragged MOTION block
        return "MOTION block is truncated or has a frame with a wrong number of values (" + msg.split(";")[0] + ")"
    if "could not convert" in msg:
        return f"MOTION block has a value that is not a number ({msg})"
    return msg


# ----------------------------------------------------------------------------- export


@dataclass(frozen=True)
class _Node:
    name: str
    parent: int  # index into the node list, -1 for the root
    site: int  # skeleton joint the node sits on
    child: int  # skeleton joint whose bone it aims (-1: a leaf, or a branching joint)
    branch: tuple[int, int, int] | None  # (left, right, middle) children of a branching joint
    offset_bone: int  # skeleton joint whose bone is the node's OFFSET (-1: zero offset)


def _hierarchy(sk: Skeleton) -> list[_Node]:
    """BVH nodes in depth-first order (parents first), with the `<parent>_to_<child>` joints."""
    children = {j: [c for c, p in enumerate(sk.parents) if p == j] for j in range(sk.n_joints)}
    nodes: list[_Node] = []

    def add(joint: int, parent: int, offset_bone: int) -> None:
        kids = children[joint]
        branch = _branch(sk, joint, kids) if len(kids) > 1 else None
        me = len(nodes)
        nodes.append(_Node(sk.joint_names[joint], parent, joint, kids[0] if len(kids) == 1 else -1,
                           branch, offset_bone))
        if len(kids) == 1:
            add(kids[0], me, kids[0])
            return
        for c in kids:
            link = len(nodes)
            nodes.append(_Node(f"{sk.joint_names[joint]}_to_{sk.joint_names[c]}", me, joint, c, None, -1))
            add(c, link, c)

    add(0, -1, -1)
    return nodes


def _branch(sk: Skeleton, joint: int, kids: list[int]) -> tuple[int, int, int]:
    def side(c: int) -> float:
        try:
            return joint_side(sk.joint_names[c])
        except UserError:
            return 0.0

    left = [c for c in kids if side(c) > 0]
    right = [c for c in kids if side(c) < 0]
    middle = [c for c in kids if side(c) == 0]
    if len(kids) != 3 or len(left) != 1 or len(right) != 1:
        raise UserError(f"skeleton {sk.name!r}: joint {sk.joint_names[joint]!r} needs a left, a right "
                        "and a middle child for BVH export")
    return left[0], right[0], middle[0]


def _up_rotation(sk: Skeleton) -> np.ndarray:
    """(3, 3) proper rotation taking the dataset's axes to y-up with the subject's left kept at +x."""
    if sk.up_index != 1:
        raise UserError(f"skeleton {sk.name!r} is {sk.up_axis}-up; BVH export supports y-up datasets only")
    return np.diag([1.0, sk.up_sign, sk.up_sign])  # -y up: half a turn about x


def motion_to_bvh(motion: np.ndarray, skeleton: Skeleton, fps: float) -> pybvh.Bvh:
    """One motion (T, J, 3) in the dataset's frame -> a pybvh.Bvh (y-up, metres), see module doc."""
    check_motion(np.asarray(motion), n_joints=skeleton.n_joints)
    if not np.isfinite(motion).all():
        raise UserError("motion has non-finite values; cannot export it to BVH")
    up = _up_rotation(skeleton)
    pos = torch.as_tensor(np.asarray(motion, dtype=np.float64) @ up.T)  # (T, J, 3) y-up
    rest = rest_directions(skeleton).numpy() @ up.T  # (J, 3) unit, y-up
    rest_t = torch.as_tensor(rest)
    parents = list(skeleton.parents)
    parents[0] = 0
    bones = pos - pos[:, parents]  # (T, J, 3)
    lengths = torch.linalg.vector_norm(bones, dim=-1)  # (T, J)
    nodes = _hierarchy(skeleton)
    frames = _global_frames(pos, bones, lengths, nodes, rest_t)  # (T, K, 3, 3)
    parent_frames = torch.stack([frames[:, n.parent] if n.parent >= 0 else torch.eye(3, dtype=pos.dtype)
                                 .expand_as(frames[:, 0]) for n in nodes], 1)
    local = parent_frames.transpose(-1, -2) @ frames  # (T, K, 3, 3)
    angles = continuous_euler(rotmat_to_euler(local.numpy(), EULER_ORDER))  # (T, K, 3) radians

    mean_len = lengths.mean(0).numpy()  # (J,)
    bvh_nodes: list = []  # pybvh's node list, End Sites included
    made: list[BvhJoint] = []  # our node k -> its pybvh joint
    for n in nodes:
        offset = rest[n.offset_bone] * mean_len[n.offset_bone] if n.offset_bone >= 0 else np.zeros(3)
        channels = list(EULER_ORDER)
        if n.parent < 0:
            node = BvhRoot(n.name, offset, ["X", "Y", "Z"], channels, [], None)
        else:
            node = BvhJoint(n.name, offset, channels, [], made[n.parent])
            made[n.parent].children = made[n.parent].children + [node]
        bvh_nodes.append(node)
        made.append(node)
        if n.child < 0 and n.branch is None:  # a leaf: End Site half a bone further, for drawing
            tip = BvhEndSite(f"End{n.name}", rest[n.site] * 0.5 * mean_len[n.site], node)
            node.children = node.children + [tip]
            bvh_nodes.append(tip)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return pybvh.Bvh(nodes=bvh_nodes, root_pos=pos[:, 0].numpy(), joint_angles=angles,
                         frame_time=1.0 / float(fps), world_up="+y")


def _global_frames(pos: torch.Tensor, bones: torch.Tensor, lengths: torch.Tensor, nodes: list[_Node],
                   rest: torch.Tensor) -> torch.Tensor:
    """World rotation of every BVH node: (T, K, 3, 3)."""
    eye = torch.eye(3, dtype=pos.dtype).expand(pos.shape[0], 3, 3)
    tiny = torch.finfo(pos.dtype).eps
    dirs = bones / lengths.clamp_min(tiny)[..., None]  # (T, J, 3), zero for zero-length bones
    frames: list[torch.Tensor] = []
    for n in nodes:
        parent = frames[n.parent] if n.parent >= 0 else eye
        if n.branch is not None:
            l, r, m = n.branch
            frames.append(body_frame(dirs[:, l], dirs[:, r], dirs[:, m])
                          @ body_frame(rest[l], rest[r], rest[m]).T)
        elif n.child >= 0:
            local = (parent.transpose(-1, -2) @ dirs[:, n.child, :, None])[..., 0]  # (T, 3)
            u = rest[n.child].expand_as(local)
            local = torch.where(lengths[:, n.child, None] > tiny, local, u)  # no direction: no swing
            frames.append(parent @ so3_exp(rotation_between(u, local)))
        else:
            frames.append(parent)
    return torch.stack(frames, 1)


def continuous_euler(angles: np.ndarray) -> np.ndarray:
    """Tait-Bryan angles (T, ..., 3) -> the same rotations with no jumps between frames.

    Each frame's triple (a, b, c) also equals (a + pi, pi - b, c + pi), and any angle + 2 pi k;
    per frame the candidate nearest the previous frame is kept, so a character turning round
    gets smooth curves instead of 180- and 360-degree flips.
    """
    out = np.array(angles, dtype=np.float64)
    flip = np.array([np.pi, np.pi, np.pi])
    for t in range(1, len(out)):
        prev = out[t - 1]
        best, best_cost = None, None
        for cand in (out[t], flip + out[t] * np.array([1.0, -1.0, 1.0])):
            cand = cand + 2 * np.pi * np.round((prev - cand) / (2 * np.pi))
            cost = np.abs(cand - prev).sum(-1, keepdims=True)
            best = cand if best is None else np.where(cost < best_cost, cand, best)
            best_cost = cost if best_cost is None else np.minimum(cost, best_cost)
        out[t] = best
    return out


def bvh_positions(bvh: pybvh.Bvh, skeleton: Skeleton) -> np.ndarray:
    """FK of an exported Bvh back to the skeleton's joints in the dataset's frame: (T, J, 3)."""
    names = list(bvh.joint_names)
    missing = [n for n in skeleton.joint_names if n not in names]
    if missing:
        raise UserError(f"BVH has no joint {missing[0]!r} of skeleton {skeleton.name!r}")
    pos = bvh.joint_positions()[:, [names.index(n) for n in skeleton.joint_names]]
    return pos @ _up_rotation(skeleton)  # the inverse (transpose) of the export rotation


def write_bvh(path: str | Path, bvh: pybvh.Bvh) -> Path:
    """Write atomically (temp file then rename)."""
    path = Path(path)
    if path.suffix.lower() != ".bvh":
        raise UserError(f"cannot write {path.name}: a BVH file must end in .bvh")
    with atomic_path(path, suffix=".bvh") as tmp:
        pybvh.write_bvh_file(bvh, tmp)
    return path


@dataclass
class ExportReport:
    files: list[Path]
    max_error_mm: float  # largest |FK(BVH) - motion| over joints and frames
    mean_error_mm: float
    max_stretch_mm: float  # largest deviation of a bone from its mean length: the BVH cannot keep it


def export_motions(motions: np.ndarray, actions, skeleton: Skeleton, fps: float, out_dir: str | Path) -> ExportReport:
    """One BVH per motion (N, T, J, 3) into out_dir (created if needed), named <index>_<action>.bvh."""
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise UserError(f"--bvh {out_dir} exists and is not a folder")
    if not out_dir.parent.is_dir():
        raise UserError(f"cannot create {out_dir}: folder {out_dir.parent} does not exist")
    if not np.isfinite(fps) or fps <= 0:
        raise UserError(f"fps must be a positive number, got {fps}")
    motions = np.asarray(motions)
    out_dir.mkdir(exist_ok=True)
    width = max(3, len(str(len(motions) - 1)))
    files, err, total, stretch = [], 0.0, 0.0, 0.0
    for i, motion in enumerate(motions):
        bvh = motion_to_bvh(motion, skeleton, fps)
        dist = np.linalg.norm(bvh_positions(bvh, skeleton) - motion, axis=-1)  # (T, J)
        err, total = max(err, float(dist.max())), total + float(dist.mean())
        lengths = np.linalg.norm(motion[:, 1:] - motion[:, list(skeleton.parents[1:])], axis=-1)  # (T, J-1)
        stretch = max(stretch, float(np.abs(lengths - lengths.mean(0)).max()))
        action = "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in str(actions[i]))
        files.append(write_bvh(out_dir / f"{i:0{width}d}_{action}.bvh", bvh))
    return ExportReport(files, 1000 * err, 1000 * total / max(len(motions), 1), 1000 * stretch)


def export_samples(samples: str | Path, out_dir: str | Path) -> ExportReport:
    """`odmo export samples.npz --bvh DIR`: every motion of a samples file as BVH."""
    from odmo_cli.skeletons import get_skeleton

    samples = Path(samples)
    if not samples.is_file():
        raise UserError(f"samples file not found: {samples}")
    try:
        with np.load(samples, allow_pickle=False) as f:
            motions, actions = f["motions"], f["actions"]
            skeleton, fps = str(f["skeleton"]), float(f["fps"])
    except KeyError as exc:
        raise UserError(f"{samples} is not an odmo samples file (no {exc.args[0]})") from None
    except (ValueError, OSError) as exc:
        raise UserError(f"cannot read {samples}: {exc}") from None
    return export_motions(motions, actions, get_skeleton(skeleton), fps, out_dir)
