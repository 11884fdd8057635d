"""The geometry of joining two windows of motion (`odmo compose`, generation/compose.py).

Pure tensor functions. Motions are (..., J, 3) in the dataset's frame; `up` is the index of its
vertical axis and (a, b) its two ground axes, in increasing order. A turn about the up axis by yaw
takes the ground-plane vector (cos t, sin t) in the (a, b) plane to (cos(t + yaw), sin(t + yaw)); it
is a proper rotation whichever axis is up, so the subject's left stays left.
"""

from __future__ import annotations

import math

import torch

from odmo_cli.geometry.lie import root_frame_joints
from odmo_cli.geometry.skeletons import Skeleton, ground_axes


def leg_length(poses: torch.Tensor, leg: tuple[int, ...]) -> torch.Tensor:
    """|hip - knee| + |knee - ankle| of poses (..., J, 3) for a leg (hip, knee, ankle, ...) -> (...)."""
    hip, knee, ankle = leg[:3]
    return (torch.linalg.vector_norm(poses[..., hip, :] - poses[..., knee, :], dim=-1)
            + torch.linalg.vector_norm(poses[..., knee, :] - poses[..., ankle, :], dim=-1))


def across_joints(skeleton: Skeleton) -> tuple[list[int], list[int]]:
    """The body's left and right joints whose differences give its facing: the hips and, where the
    skeleton names them, the shoulders (two lines average a pelvis's swing in a stride)."""
    left, right, _ = root_frame_joints(skeleton)
    lefts, rights = [left], [right]
    names = skeleton.joint_names
    if "left_shoulder" in names and "right_shoulder" in names:
        lefts.append(names.index("left_shoulder"))
        rights.append(names.index("right_shoulder"))
    return lefts, rights


def heading(poses: torch.Tensor, skeleton: Skeleton) -> torch.Tensor:
    """The direction of the body's right-to-left line on the ground plane, as an angle: poses
    (..., J, 3) -> (...,) radians. Its difference between two poses is the turn between them."""
    lefts, rights = across_joints(skeleton)
    across = (poses[..., lefts, :] - poses[..., rights, :]).sum(-2)  # (..., 3)
    a, b = skeleton.ground_axes
    return torch.atan2(across[..., b], across[..., a])


def turn(yaw: torch.Tensor, up: int) -> torch.Tensor:
    """Rotations about the up axis: yaw (K,) radians -> (K, 3, 3); R @ x turns x by yaw."""
    a, b = ground_axes(up)
    c, s = torch.cos(yaw), torch.sin(yaw)
    rot = torch.zeros(*yaw.shape, 3, 3, dtype=yaw.dtype, device=yaw.device)
    rot[..., up, up] = 1
    rot[..., a, a], rot[..., a, b], rot[..., b, a], rot[..., b, b] = c, -s, s, c
    return rot


def ramp(n: int, length: int | torch.Tensor, dtype=torch.float32) -> torch.Tensor:
    """(n,) weights of the new motion over the old at the n frames after a seam: a smooth step from 0
    to 1 over `length` frames (0 < w < 1 there), 1 after them; frame i (0-based) has
    smoothstep((i + 1) / (length + 1)). A length per sequence (K,) gives (K, n)."""
    i = torch.arange(1, n + 1, dtype=dtype)
    if isinstance(length, torch.Tensor):
        i = i.to(length.device)[None]
        length = length.to(dtype)[:, None]
    x = (i / (length + 1)).clamp(max=1.0)
    return x * x * (3 - 2 * x)


def splice_path(path: torch.Tensor, primer_root: torch.Tensor, height: torch.Tensor, blend: int,
                up: int) -> torch.Tensor:
    """A window's root path in the model's frame, its first k steps the primer's.

    path (K, T, 3): the trajectory generator's path for the window; primer_root (K, k, 3): the root of
    the k primed frames; height (K,): the up coordinate the path's own start stands for (the
    composition's reference height, expressed in this frame). After the primer, the ground-plane
    velocity fades from the primer's last step to the path's own over `blend` frames, and the height
    is the path's own above the reference, the primer's last height's difference from it fading
    over the same frames. Returns (K, T, 3).
    """
    k = primer_root.shape[1]
    T = path.shape[1]
    g = list(ground_axes(up))
    w = ramp(T - k, blend, path.dtype).to(path.device)[None, :, None]  # (1, T-k, 1)
    step = path[:, k:, g] - path[:, k - 1:-1, g]  # (K, T-k, 2) the path's own ground velocity
    last = primer_root[:, -1, g] - primer_root[:, -2, g] if k >= 2 else torch.zeros_like(primer_root[:, -1, g])
    ground = primer_root[:, -1:, g] + torch.cumsum(w * step + (1 - w) * last[:, None], dim=1)  # (K, T-k, 2)
    own = path[:, :, up] - path[:, :1, up] + height[:, None]  # (K, T) heights over the reference
    gap = primer_root[:, -1, up] - own[:, k - 1]  # (K,)
    rise = own[:, k:] + gap[:, None] * (1 - w[..., 0])  # (K, T-k)
    tail = torch.empty(len(path), T - k, 3, dtype=path.dtype, device=path.device)
    tail[..., g], tail[..., up] = ground, rise
    return torch.cat([primer_root, tail], dim=1)


def fade(new: torch.Tensor, offset: torch.Tensor, blend: int | torch.Tensor) -> torch.Tensor:
    """new (K, m, J, 3) frames after a seam plus offset (K, J, 3), which fades out over `blend` frames
    (one number, or one per sequence (K,)): the first frame continues the old motion's last pose by the
    new motion's own step."""
    keep = 1 - ramp(new.shape[1], blend, new.dtype).to(new.device)  # (m,) or (K, m)
    keep = keep[None, :] if keep.dim() == 1 else keep
    return new + offset[:, None] * keep[:, :, None, None]


def fade_length(offset: torch.Tensor, shortest: int, longest: int, step: torch.Tensor) -> torch.Tensor:
    """Frames (K,) for a fade of offset (K, J, 3) whose joints move by at most `step` (K,) a frame on
    its account: smoothstep's steepest frame carries 1.5 / (length + 1) of the offset; between
    `shortest` and `longest`."""
    need = 1.5 * torch.linalg.vector_norm(offset, dim=-1).amax(-1) / step - 1  # (K,)
    return need.ceil().clamp(shortest, max(shortest, longest)).long()


def wrap(angle: torch.Tensor) -> torch.Tensor:
    """Angles into (-pi, pi]."""
    return torch.remainder(angle + math.pi, 2 * math.pi) - math.pi



def settle_feet(faded: torch.Tensor, new: torch.Tensor, offset: torch.Tensor, skeleton: Skeleton, fps: float,
                longest: int) -> torch.Tensor:
    """`fade`'s frames with feet that glide into place instead of skating: faded (K, m, J, 3) = new +
    offset * fading weights, new the decoder's own frames, offset (K, J, 3).

    The fade moves every joint by its share of the offset within the transition, so a foot on the floor
    slides by its whole offset there, faster than the skating threshold (plausibility.SLIDE_SPEED leg
    lengths a second) when the offset is large. Here each ankle's ground-plane offset fades at a
    constant speed of half that threshold instead (over at most `longest` frames), as far as the leg
    reaches (a straight leg drags its foot along with the hip); the toe moves with the ankle and the knee
    is placed by two-bone IK: thigh and shin keep their lengths, the knee bends the way it was drawn.
    """
    from odmo_cli.measures.plausibility import SLIDE_SPEED

    if not skeleton.legs:
        return faded
    out = faded.clone()
    g = list(skeleton.ground_axes)
    t = torch.arange(1, new.shape[1] + 1, dtype=new.dtype, device=new.device)  # (m,)
    for hip, knee, ankle, toe in skeleton.legs:
        leg = leg_length(new, (hip, knee, ankle)).median(dim=1).values  # (K,)
        shift = offset[:, ankle, g]  # (K, 2)
        step = 0.5 * SLIDE_SPEED * leg / fps  # (K,) the ankle's slide per frame
        frames = (torch.linalg.vector_norm(shift, dim=-1) / step).ceil().clamp(1, longest)  # (K,)
        keep = (1 - t[None] / (frames[:, None] + 1)).clamp_min(0)  # (K, m) linear: a constant speed
        target = out[:, :, ankle].clone()
        target[..., g] = new[:, :, ankle, g] + shift[:, None] * keep[..., None]
        for i in range(min(new.shape[1], longest)):
            _reach(out[:, i], hip, knee, ankle, toe, target[:, i])
    return out


def _reach(pose: torch.Tensor, hip: int, knee: int, ankle: int, toe: int, target: torch.Tensor) -> None:
    """Move pose's (K, J, 3) ankle to target (K, 3), in place: the toe moves with it, the knee is placed
    so thigh and shin keep their lengths, bent the way the pose had it (two-bone IK); a target out of
    reach is brought to the nearest reachable distance along the same line."""
    h, k, a = pose[:, hip], pose[:, knee], pose[:, ankle]
    l1 = torch.linalg.vector_norm(k - h, dim=-1)
    l2 = torch.linalg.vector_norm(a - k, dim=-1)
    d = target - h
    dist = torch.linalg.vector_norm(d, dim=-1).clamp_min(1e-9)
    u = d / dist[:, None]
    dist = torch.minimum(torch.maximum(dist, (l1 - l2).abs() + 1e-6), l1 + l2 - 1e-6)
    reach = h + u * dist[:, None]
    bend = (k - h) - ((k - h) * u).sum(-1, keepdim=True) * u
    bend = bend / torch.linalg.vector_norm(bend, dim=-1, keepdim=True).clamp_min(1e-9)
    along = (l1 ** 2 - l2 ** 2 + dist ** 2) / (2 * dist)
    across = (l1 ** 2 - along ** 2).clamp_min(0).sqrt()
    toe_now = pose[:, toe] - a + reach
    pose[:, knee] = h + u * along[:, None] + bend * across[:, None]
    pose[:, ankle] = reach
    pose[:, toe] = toe_now
