"""BVH files: read them (forward kinematics to joint positions) and write motions as BVH.

Parsing, writing and the Euler-angle maths are pybvh's (MIT, needs only numpy and matplotlib,
which odmo has anyway): it handles any rotation channel order, End Sites, and rejects a file
whose MOTION block is truncated or whose value count disagrees with its CHANNELS. It does not
model position channels on non-root joints; such files are reported as unreadable.

Writing (positions -> rotations) is lossy, so the convention is fixed here (`BvhOptions`):
* The file is y-up, in centimetres (or metres), at the motion's fps; the subject's left is +x at
  rest. The motion is lifted so that its lowest foot over all frames touches y = 0: the
  character stands on the floor instead of half below it.
* One BVH joint per skeleton joint, under the usual BVH names where the skeleton has them
  (`Skeleton.bvh_names`: Hips, Spine, LeftUpLeg, LeftArm, ...), so retargeting tools map them.
* The root and every branching joint (pelvis, chest) take the *body frame* of their children:
  x along left child - right child, y along the middle child (`lie.body_frame`). The facing and
  the torso's twist therefore come from the hip and shoulder lines, never from one bone, so a
  character facing away from the camera is not flipped. A branching joint's children sit at their
  mean position in that frame: exact for a rigid torso; where the torso bends (the three children
  move against each other) the fit error is reported.
* Every other joint takes the *minimal swing* from its parent's frame that turns its bone's rest
  direction into the bone's direction (as `lie.inverse_kinematics`): bones carry no twist about
  their own axis. Its offset is its bone's canonical rest direction (`lie.rest_directions`: a
  T-pose) times the bone's mean length in the motion.
* With `helpers`, each child of a branching joint hangs from a zero-length joint named
  `<parent>_to_<child>` that aims the child's own bone, for tools that want one bone per child:
  positions are then exact however the torso bends.
* Rotation channels are `Zrotation Yrotation Xrotation` (as the CMU and Character Creator BVH
  files), each frame on the Euler branch nearest the previous frame: curves have no 180- or
  360-degree jumps when the character turns round.
With constant bone lengths (and a rigid torso, or helpers) the re-imported positions equal the
motion's to the file's 6 decimals; a generated motion whose bones stretch differs by that
stretch (reported).
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
from odmo_cli.geometry.kinematics import check_motion
from odmo_cli.geometry.lie import body_frame, joint_side, rest_directions, rotation_between, so3_exp
from odmo_cli.geometry.skeletons import Skeleton, get_skeleton
from odmo_cli.formats.samples import read_samples

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

UNITS = {"cm": 100.0, "m": 1.0}  # file units per metre


@dataclass(frozen=True)
class BvhOptions:
    """How `odmo export` writes a file. The defaults import cleanly into Blender, MotionBuilder,
    Maya and game engines: centimetres, the lowest foot on the floor, one joint per skeleton joint."""

    units: str = "cm"  # "cm" or "m"
    floor: bool = True  # lift the motion so that its lowest foot (over all frames) is at height 0
    helpers: bool = False  # a zero-length `<parent>_to_<child>` joint per child of a branching joint

    def __post_init__(self):
        if self.units not in UNITS:
            raise UserError(f"unknown units {self.units!r}; valid: {', '.join(UNITS)}")


@dataclass(frozen=True)
class FileFrame:
    """dataset positions (metres, the dataset's axes) -> file positions: (p @ R.T - floor * y) * scale."""

    rotation: np.ndarray  # (3, 3) to y-up
    floor: float  # height (metres, y-up) put at 0
    scale: float  # file units per metre

    def to_file(self, pos: np.ndarray) -> np.ndarray:
        return (pos @ self.rotation.T - np.array([0.0, self.floor, 0.0])) * self.scale

    def from_file(self, pos: np.ndarray) -> np.ndarray:
        return (pos / self.scale + np.array([0.0, self.floor, 0.0])) @ self.rotation


@dataclass(frozen=True)
class _Node:
    name: str
    parent: int  # index into the node list, -1 for the root
    site: int  # skeleton joint the node sits on (-1: a helper, which sits on its parent's joint)
    child: int  # skeleton joint whose bone it aims (-1: a leaf, or a branching joint)
    branch: tuple[int, int, int] | None  # (left, right, middle) children of a branching joint


def _hierarchy(sk: Skeleton, helpers: bool) -> list[_Node]:
    """BVH nodes in depth-first order (parents first). A node of a joint with one child aims that
    child's bone; a branching joint's node takes the body frame of its children (`lie.body_frame`);
    with `helpers`, each child of a branching joint hangs from a zero-length `<parent>_to_<child>`
    node that aims the child's own bone."""
    children = {j: [c for c, p in enumerate(sk.parents) if p == j] for j in range(sk.n_joints)}
    names = sk.bvh_names or sk.joint_names
    nodes: list[_Node] = []

    def add(joint: int, parent: int) -> None:
        kids = children[joint]
        branch = _branch(sk, joint, kids) if len(kids) > 1 else None
        me = len(nodes)
        nodes.append(_Node(names[joint], parent, joint, kids[0] if len(kids) == 1 else -1, branch))
        if len(kids) == 1:
            add(kids[0], me)
            return
        for c in kids:
            if helpers:
                nodes.append(_Node(f"{names[joint]}_to_{names[c]}", me, -1, c, None))
            add(c, len(nodes) - 1 if helpers else me)

    add(0, -1)
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
    return sk.y_up_rotation()


def _feet(sk: Skeleton) -> list[int]:
    """The joints a character stands on: ankles, feet and toes (all joints if none is named so)."""
    feet = [j for j, n in enumerate(sk.joint_names) if any(k in n for k in ("ankle", "foot", "toe"))]
    return feet or list(range(sk.n_joints))


def motion_to_bvh(motion: np.ndarray, skeleton: Skeleton, fps: float,
                  options: BvhOptions = BvhOptions()) -> pybvh.Bvh:
    """One motion (T, J, 3) in the dataset's frame -> a pybvh.Bvh (y-up, see module doc and BvhOptions)."""
    return export_bvh(motion, skeleton, fps, options)[0]


def export_bvh(motion: np.ndarray, skeleton: Skeleton, fps: float,
               options: BvhOptions = BvhOptions()) -> tuple[pybvh.Bvh, FileFrame]:
    """motion_to_bvh, and the FileFrame that maps the motion into the file. The floor is the lowest
    foot of the file's own skeleton (rigid bones at their mean lengths), not of the motion, whose
    bones may stretch: in the file the lowest foot touches y = 0 exactly."""
    bvh, frame = _to_bvh(motion, skeleton, fps, FileFrame(_up_rotation(skeleton), 0.0, UNITS[options.units]), options)
    if options.floor:
        names = list(bvh.joint_names)
        names_of = skeleton.bvh_names or skeleton.joint_names
        feet = [names.index(names_of[j]) for j in _feet(skeleton)]
        lowest = float(bvh.joint_positions()[:, feet, 1].min())  # file units
        frame = FileFrame(frame.rotation, lowest / frame.scale, frame.scale)
        root = bvh.root_pos.copy()
        root[:, 1] -= lowest
        bvh.root_pos = root
    return bvh, frame


def _to_bvh(motion: np.ndarray, skeleton: Skeleton, fps: float, frame: FileFrame,
            options: BvhOptions) -> tuple[pybvh.Bvh, FileFrame]:
    check_motion(np.asarray(motion), n_joints=skeleton.n_joints)
    if not np.isfinite(motion).all():
        raise UserError("motion has non-finite values; cannot export it to BVH")
    pos = torch.as_tensor(frame.to_file(np.asarray(motion, dtype=np.float64)))  # (T, J, 3) y-up, file units
    rest = torch.as_tensor(rest_directions(skeleton).numpy() @ frame.rotation.T)  # (J, 3) unit, y-up
    parents = list(skeleton.parents)
    parents[0] = 0
    bones = pos - pos[:, parents]  # (T, J, 3)
    lengths = torch.linalg.vector_norm(bones, dim=-1)  # (T, J)
    nodes = _hierarchy(skeleton, options.helpers)
    frames = _global_frames(pos, bones, lengths, nodes, rest)  # (T, K, 3, 3)
    parent_frames = torch.stack([frames[:, n.parent] if n.parent >= 0 else torch.eye(3, dtype=pos.dtype)
                                 .expand_as(frames[:, 0]) for n in nodes], 1)
    local = parent_frames.transpose(-1, -2) @ frames  # (T, K, 3, 3)
    angles = continuous_euler(rotmat_to_euler(local.numpy(), EULER_ORDER))  # (T, K, 3) radians

    mean_len = lengths.mean(0).numpy()  # (J,)
    bvh_nodes: list = []  # pybvh's node list, End Sites included
    made: list[BvhJoint] = []  # our node k -> its pybvh joint
    for k, n in enumerate(nodes):
        offset = _offset(n, nodes, pos, frames, rest, mean_len, skeleton)
        channels = list(EULER_ORDER)
        if n.parent < 0:
            node = BvhRoot(n.name, offset, ["X", "Y", "Z"], channels, [], None)
        else:
            node = BvhJoint(n.name, offset, channels, [], made[n.parent])
            made[n.parent].children = made[n.parent].children + [node]
        bvh_nodes.append(node)
        made.append(node)
        if n.site >= 0 and n.child < 0 and n.branch is None:  # a leaf: End Site half a bone further, for drawing
            tip = BvhEndSite(f"End{n.name}", rest[n.site].numpy() * 0.5 * mean_len[n.site], node)
            node.children = node.children + [tip]
            bvh_nodes.append(tip)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return pybvh.Bvh(nodes=bvh_nodes, root_pos=pos[:, 0].numpy(), joint_angles=angles,
                         frame_time=1.0 / float(fps), world_up="+y"), frame


def _offset(n: _Node, nodes: list[_Node], pos: torch.Tensor, frames: torch.Tensor, rest: torch.Tensor,
            mean_len: np.ndarray, sk: Skeleton) -> np.ndarray:
    """A node's OFFSET from its parent node. Helpers sit on their parent (zero). A joint whose parent
    node aims its bone lies along the rest direction at the bone's mean length (exact while the bone
    keeps its length). A child of a branching joint lies where it lies on average in that joint's
    body frame (exact for a rigid torso, otherwise the fit error reported by export_motions)."""
    if n.site < 0 or n.parent < 0:
        return np.zeros(3)
    parent = nodes[n.parent]
    if parent.branch is None:  # the parent node (or helper) aims this joint's bone
        return rest[n.site].numpy() * mean_len[n.site]
    anchor = sk.parents[n.site]
    local = frames[:, n.parent].transpose(-1, -2) @ (pos[:, n.site] - pos[:, anchor])[..., None]  # (T, 3, 1)
    return local[..., 0].mean(0).numpy()


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


def bvh_positions(bvh: pybvh.Bvh, skeleton: Skeleton, frame: FileFrame) -> np.ndarray:
    """FK of an exported Bvh back to the skeleton's joints in the dataset's frame: (T, J, 3)."""
    names = list(bvh.joint_names)
    wanted = skeleton.bvh_names or skeleton.joint_names
    missing = [n for n in wanted if n not in names]
    if missing:
        raise UserError(f"BVH has no joint {missing[0]!r} of skeleton {skeleton.name!r}")
    return frame.from_file(bvh.joint_positions()[:, [names.index(n) for n in wanted]])


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
    units: str = "cm"
    joints: int = 0  # BVH joints per file (End Sites excluded)


def export_motions(motions: np.ndarray, actions, skeleton: Skeleton, fps: float, out_dir: str | Path,
                   options: BvhOptions = BvhOptions()) -> ExportReport:
    """One BVH per motion (N, T, J, 3) into out_dir (created if needed), named <index>_<action>.bvh."""
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise UserError(f"--bvh {out_dir} exists and is not a folder")
    if not out_dir.parent.is_dir():
        raise UserError(f"cannot create {out_dir}: folder {out_dir.parent} does not exist")
    if not np.isfinite(fps) or fps <= 0:
        raise UserError(f"fps must be a positive number, got {fps}")
    motions = np.asarray(motions)
    try:
        out_dir.mkdir(exist_ok=True)
    except OSError as exc:
        raise UserError(f"cannot create {out_dir}: {exc.strerror or exc}") from None
    width = max(3, len(str(len(motions) - 1)))
    files, err, total, stretch, joints = [], 0.0, 0.0, 0.0, 0
    for i, motion in enumerate(motions):
        bvh, frame = export_bvh(motion, skeleton, fps, options)
        back = bvh_positions(bvh, skeleton, frame)
        dist = np.linalg.norm(back - motion, axis=-1)  # (T, J) metres
        err, total = max(err, float(dist.max())), total + float(dist.mean())
        lengths = np.linalg.norm(motion[:, 1:] - motion[:, list(skeleton.parents[1:])], axis=-1)  # (T, J-1)
        stretch = max(stretch, float(np.abs(lengths - lengths.mean(0)).max()))
        joints = len(bvh.joint_names)
        action = "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in str(actions[i]))
        files.append(write_bvh(out_dir / f"{i:0{width}d}_{action}.bvh", bvh))
    return ExportReport(files, 1000 * err, 1000 * total / max(len(motions), 1), 1000 * stretch,
                        options.units, joints)


def export_samples(samples: str | Path, out_dir: str | Path, options: BvhOptions = BvhOptions()) -> ExportReport:
    """`odmo export samples.npz --bvh DIR`: every motion of a samples file as BVH."""
    f = read_samples(samples)
    return export_motions(f["motions"], f["actions"], get_skeleton(f["skeleton"]), f["fps"], out_dir, options)
