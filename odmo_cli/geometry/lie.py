"""Lie-algebra pose representation of Action2Motion (A2M §3.1, eqs. 1-4).

A pose is split into a root translation, one so(3) vector per joint, and bone lengths. The
functions are pure torch, differentiable, batched over any leading dimensions (as in
pytorch3d's `transforms`) and work in float32 and float64. Shapes use `...` for batch dims.

Conventions (all chosen here; the paper leaves them open)
---------------------------------------------------------
* **Rest pose.** Every bone c (the bone from `parents[c]` to joint c; bones are indexed by
  their child joint) has a unit rest direction `u_c` expressed in the *body frame*. With all
  rotations equal to the identity the skeleton stands in that rest pose. `rest_directions`
  gives a canonical T-pose for the named skeletons, written in the dataset's own axes (up as
  in `Skeleton.up_axis`, the subject's left along +x, forward = left x up): legs straight
  down, spine/neck/head straight up, arms straight out sideways, feet/toes forward, and the
  girdle bones slanted as in real bodies (hips out and down, collars out and up).
  `rest_offsets(reference_pose, skeleton)` instead takes the rest pose from a (J, 3)
  reference pose: with identity rotations every frame equals the root frame, so the offsets
  of the bones in their parent frames are simply `x_c - x_parent` of that pose.
  Either can be passed as `rest_dirs` (they are normalised internally).
  A2M attaches a frame to every bone with the bone along its x-axis (d = (b, 0, 0)); that
  is the same as ours up to a constant per-bone rotation taking x to `u_c`.
* **Rotations.** `lie_params[..., 0, :]` is the root (global body) orientation G_0 and, for
  c > 0, `lie_params[..., c, :]` is the rotation of bone c *relative to its parent's frame*:
      G_0 = exp(w_0),  G_c = G_parent(c) exp(w_c),  x_c = x_parent(c) + b_c G_c u_c,
  which is A2M eq. (4) with one rotation per bone (so branching joints such as spine3 or
  the thorax, with several children, are unambiguous). `lie_params[..., 1:, :]` is the
  (J-1)*3-vector A2M generates (69 numbers for HumanAct12).
* **Root frame.** Positions alone fix the body frame from the hips and the spine: x along
  the unit direction(left hip) - unit direction(right hip), y along the first spine bone
  made orthogonal to x, z = x cross y. G_0 maps this frame of the rest pose onto the frame
  of the pose, so the rest pose itself has G_0 = I.
* **Twist.** Positions do not determine the rotation of a bone about its own axis.
  `inverse_kinematics` uses the minimal (swing-only) rotation taking `u_c` to the bone's
  direction in its parent's frame: w_c is perpendicular to both, |w_c| = angle between them.
  Twist is therefore never stored in a bone; what the data implies about it (e.g. spine
  twist) shows up in the child bones' rotations instead.
* **Bone lengths** are per joint, shape (..., J), 0 for the root (`bone_lengths_from_pose`).
"""

from __future__ import annotations

import functools
from typing import Mapping, Sequence

import numpy as np
import torch

from odmo_cli.errors import UserError
from odmo_cli.geometry.kinematics import bone_lengths, check_motion
from odmo_cli.geometry.skeletons import Skeleton, get_skeleton

__all__ = [
    "hat", "vee", "so3_exp", "so3_log", "rotation_between",
    "rest_directions", "rest_offsets", "root_frame_joints", "bone_lengths_from_pose", "joint_side", "body_frame",
    "inverse_kinematics", "forward_kinematics", "bone_groups", "scale_bones", "retarget",
]

# Below this |theta| (resp. |sin theta|) the closed forms are replaced by Taylor series.
_SMALL = 1e-2
# so3_log switches to the symmetric-part formula when cos(theta) < this (theta > 120 deg).
_NEAR_PI_COS = -0.5


# ----------------------------------------------------------------------------- helpers


def _as_float_tensor(x: torch.Tensor | np.ndarray | Sequence) -> torch.Tensor:
    t = torch.as_tensor(x)
    if not t.is_floating_point():
        t = t.to(torch.get_default_dtype())
    return t


def _check_vec3(v: torch.Tensor, name: str) -> None:
    if v.dim() < 1 or v.shape[-1] != 3:
        raise UserError(f"{name} must have shape (..., 3), got {tuple(v.shape)}")


def _check_mat3(m: torch.Tensor, name: str) -> None:
    if m.dim() < 2 or tuple(m.shape[-2:]) != (3, 3):
        raise UserError(f"{name} must have shape (..., 3, 3), got {tuple(m.shape)}")


def _skeleton(skeleton: Skeleton | str) -> Skeleton:
    return get_skeleton(skeleton) if isinstance(skeleton, str) else skeleton


def _topological_order(parents: Sequence[int]) -> list[int]:
    """Non-root joints ordered so that every parent comes before its children."""
    order: list[int] = []
    placed = {0}
    pending = [j for j in range(len(parents)) if j != 0]
    while pending:
        rest = [j for j in pending if parents[j] not in placed]
        ready = [j for j in pending if parents[j] in placed]
        if not ready:
            raise UserError(f"skeleton joints {rest} are not connected to the root")
        order += ready
        placed.update(ready)
        pending = rest
    return order


def _normalize(v: torch.Tensor, eps: float | None = None) -> torch.Tensor:
    """v / |v| along the last dim; zero stays zero, with a finite gradient (no norm of 0)."""
    min_sq = torch.finfo(v.dtype).tiny if eps is None else eps * eps
    return v / torch.sqrt((v * v).sum(-1, keepdim=True).clamp_min(min_sq))


# ----------------------------------------------------------------------------- so(3)


def hat(v: torch.Tensor) -> torch.Tensor:
    """Skew-symmetric matrix of a vector (A2M eq. 2): (..., 3) -> (..., 3, 3), hat(v) @ x = v x x."""
    v = _as_float_tensor(v)
    _check_vec3(v, "v")
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack(
        [torch.stack([o, -z, y], -1), torch.stack([z, o, -x], -1), torch.stack([-y, x, o], -1)], -2
    )


def vee(m: torch.Tensor) -> torch.Tensor:
    """Inverse of `hat`: (..., 3, 3) -> (..., 3), the vector of the skew-symmetric part of m."""
    m = _as_float_tensor(m)
    _check_mat3(m, "m")
    return 0.5 * torch.stack(
        [m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1
    )


def so3_exp(omega: torch.Tensor) -> torch.Tensor:
    """Exponential map so(3) -> SO(3) (Rodrigues): (..., 3) -> (..., 3, 3).

    R = I + A(theta) K + B(theta) K^2 with K = hat(omega), theta = |omega|,
    A = sin(theta)/theta and B = (1 - cos(theta))/theta^2 = (sin(theta/2)/(theta/2))^2 / 2.
    Below theta = 1e-2 both are replaced by their Taylor series (exact to double precision),
    so the map and its gradient are finite and accurate at and near omega = 0.
    """
    omega = _as_float_tensor(omega)
    _check_vec3(omega, "omega")
    t2 = (omega * omega).sum(-1)
    small = t2 < _SMALL**2
    t = torch.sqrt(torch.where(small, torch.ones_like(t2), t2))  # safe: never sqrt(0)
    half = 0.5 * t
    a = torch.where(small, 1 - t2 / 6 + t2 * t2 / 120, torch.sin(t) / t)
    b = torch.where(small, 0.5 - t2 / 24 + t2 * t2 / 720, 0.5 * (torch.sin(half) / half) ** 2)
    eye = torch.eye(3, dtype=omega.dtype, device=omega.device)
    k = hat(omega)
    k2 = omega[..., :, None] * omega[..., None, :] - t2[..., None, None] * eye  # = K @ K
    return eye + a[..., None, None] * k + b[..., None, None] * k2


def so3_log(r: torch.Tensor) -> torch.Tensor:
    """Logarithm map SO(3) -> so(3): (..., 3, 3) -> (..., 3) with |omega| = theta in [0, pi].

    A2M eq. (3), made stable at both ends:
    * theta near 0 (|sin theta| < 1e-2, cos theta > 0): omega = a * asin(s)/s by its Taylor
      series, where a = vee(R) = sin(theta) n and s = |a|; finite gradient at R = I.
    * generic: theta = atan2(|a|, cos theta), omega = theta a / |a|.
    * theta near pi (cos theta < -0.5): sin(theta) -> 0, so the axis comes from the
      symmetric part instead, (R + R^T)/2 - cos(theta) I = (1 - cos theta) n n^T, using
      the column with the largest diagonal entry; its sign is taken from a. At theta = pi
      exactly, omega and -omega are the same rotation and either may be returned.
    Input is assumed to be a rotation matrix (not re-orthogonalised).
    """
    r = _as_float_tensor(r)
    _check_mat3(r, "R")
    eps = torch.finfo(r.dtype).eps
    tr = r[..., 0, 0] + r[..., 1, 1] + r[..., 2, 2]
    c = ((tr - 1) / 2).clamp(-1.0, 1.0)
    a = vee(r)  # sin(theta) * axis
    s2 = (a * a).sum(-1)
    small = (s2 < _SMALL**2) & (c > 0)
    near_pi = c < _NEAR_PI_COS
    generic = ~small & ~near_pi

    # theta -> 0: asin(s)/s = 1 + s^2/6 + 3 s^4/40 + 5 s^6/112 + O(s^8)
    w_small = a * (1 + s2 / 6 + 3 * s2**2 / 40 + 5 * s2**3 / 112)[..., None]

    s_gen = torch.sqrt(torch.where(generic, s2, torch.ones_like(s2)))
    w_gen = a * (torch.atan2(s_gen, c) / s_gen)[..., None]

    # theta -> pi: n n^T = (S - c I) / (1 - c)
    eye = torch.eye(3, dtype=r.dtype, device=r.device)
    sym = 0.5 * (r + r.transpose(-1, -2))
    denom = torch.where(near_pi, 1 - c, torch.ones_like(c))
    nn = (sym - c[..., None, None] * eye) / denom[..., None, None]
    diag = torch.diagonal(nn, dim1=-2, dim2=-1)
    k = diag.argmax(-1, keepdim=True)  # (..., 1)
    col = torch.gather(nn, -1, k[..., None, :].expand(nn.shape[:-1] + (1,))).squeeze(-1)
    n = col / torch.sqrt(torch.gather(diag, -1, k).clamp_min(eps))
    n = _normalize(n, eps)
    n = torch.where(((n * a).sum(-1) < 0)[..., None], -n, n)
    theta_pi = torch.atan2(torch.sqrt(s2.clamp_min(eps * eps)), c)
    w_pi = theta_pi[..., None] * n

    return torch.where(small[..., None], w_small, torch.where(near_pi[..., None], w_pi, w_gen))


def rotation_between(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Minimal rotation taking direction u to direction v, as an so(3) vector: (..., 3) x2 -> (..., 3).

    omega = angle(u, v) * unit(u x v): perpendicular to u and v (no twist about either),
    |omega| in [0, pi]. Inputs need not be unit length (they are normalised). When v = -u the
    axis is undetermined; a fixed axis perpendicular to u is used. exp(omega) @ unit(u)
    reproduces unit(v) to machine precision for every angle, including near pi.
    """
    u = _as_float_tensor(u)
    v = _as_float_tensor(v)
    _check_vec3(u, "u")
    _check_vec3(v, "v")
    u, v = torch.broadcast_tensors(u, v)
    eps = torch.finfo(u.dtype).eps
    u = _normalize(u)
    v = _normalize(v)
    c = (u * v).sum(-1)
    cr = torch.linalg.cross(u, v)
    s2 = (cr * cr).sum(-1)
    small = (s2 < _SMALL**2) & (c > 0)

    # angle < 1e-2: omega = cr * asin(s)/s (Taylor), smooth through 0
    w_small = cr * (1 + s2 / 6 + 3 * s2**2 / 40 + 5 * s2**3 / 112)[..., None]

    # otherwise: axis = unit(cr made exactly perpendicular to u); near-antiparallel this keeps
    # exp(omega) u = v accurate although cr itself is tiny.
    n_raw = cr - (cr * u).sum(-1, keepdim=True) * u
    n2 = (n_raw * n_raw).sum(-1)
    degenerate = (n2 < eps * eps) & ~small
    idx = u.abs().argmin(-1)  # least-aligned coordinate axis
    e = torch.nn.functional.one_hot(idx, 3).to(u.dtype)
    perp = _normalize(torch.linalg.cross(u, e))
    n_len = torch.sqrt(torch.where(degenerate | small, torch.ones_like(n2), n2))  # never sqrt(0)
    axis = torch.where(degenerate[..., None], perp, n_raw / n_len[..., None])
    theta = torch.atan2(torch.sqrt(s2.clamp_min(eps * eps)), c)
    w_gen = theta[..., None] * axis
    return torch.where(small[..., None], w_small, w_gen)


# ----------------------------------------------------------------------------- rest pose

# Canonical rest pose, by the name of the bone's child joint: the bone's direction as
# (sideways, up, forward) in the body frame; "sideways" points to the joint's own side. A T-pose
# for the limbs and spine; the girdle bones (hips, collars, CMU/UESTC shoulders) and SMPL's
# feet get their typical anatomical slant (read off HumanAct12 and CMU clips) so that a
# standing pose has near-zero rotations in those bones.
_REST_BY_NAME: tuple[tuple[tuple[str, ...], tuple[float, float, float]], ...] = (
    (("spine", "thorax", "neck", "head"), (0.0, 1.0, 0.0)),
    (("knee", "ankle"), (0.0, -1.0, 0.0)),
    (("foot", "toe"), (0.0, 0.0, 1.0)),
    (("hip",), (0.6, -0.8, 0.0)),
    (("collar",), (0.6, 0.8, 0.0)),
    (("shoulder", "elbow", "wrist", "hand"), (1.0, 0.0, 0.0)),
)
_REST_OVERRIDES: Mapping[str, Mapping[str, tuple[float, float, float]]] = {
    "humanact12": {"foot": (0.0, -1.0, 1.0)},  # SMPL ankle -> foot joint points down and forward
    "cmu20": {"shoulder": (0.9, 0.4, 0.0)},  # thorax -> shoulder rises slightly
    "uestc18": {"shoulder": (0.9, 0.4, 0.0)},  # same topology as cmu20 (unverified)
}


def joint_side(name: str) -> float:
    """+1 for the subject's left, -1 for the right (uestc18: side a is taken as left, unverified)."""
    if name.startswith("left") or name.endswith("_a"):
        return 1.0
    if name.startswith("right") or name.endswith("_b"):
        return -1.0
    raise UserError(f"cannot tell the side of joint {name!r} for the rest pose")


def torso_branches(skeleton: Skeleton | str) -> dict[int, tuple[int, int, int]]:
    """The joints with exactly three children, one on each side and one in the middle (a pelvis with its
    hips and spine, a chest with its collars or shoulders and neck): {joint: (left, right, middle)}."""
    sk = _skeleton(skeleton)
    out = {}
    for j in range(sk.n_joints):
        kids = [c for c, p in enumerate(sk.parents) if p == j]
        sides = {}
        for c in kids:
            try:
                sides[c] = joint_side(sk.joint_names[c])
            except UserError:
                sides[c] = 0.0
        left = [c for c in kids if sides[c] > 0]
        right = [c for c in kids if sides[c] < 0]
        middle = [c for c in kids if sides[c] == 0]
        if len(kids) == 3 and len(left) == len(right) == len(middle) == 1:
            out[j] = (left[0], right[0], middle[0])
    return out


def _body_axes(sk: Skeleton) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(left, up, forward) unit vectors in the dataset's axes; left = +x, forward = left x up."""
    up = np.zeros(3)
    up[sk.up_index] = sk.up_sign
    left = np.array([1.0, 0.0, 0.0]) if sk.up_index != 0 else np.array([0.0, 0.0, 1.0])
    return left, up, np.cross(left, up)


def rest_directions(
    skeleton: Skeleton | str, dtype: torch.dtype = torch.float64, device: torch.device | str | None = None
) -> torch.Tensor:
    """Canonical rest direction (unit) of every bone, in the dataset's axes: (J, 3), row 0 = 0.

    Defined from the joint names (see `_REST_BY_NAME`): spine/neck/head up, knees and ankles
    down, feet and toes forward, arms straight out sideways (T-pose), hips sideways and down,
    collars sideways and up. The body axes are: up from `Skeleton.up_axis`, the subject's
    left along +x, forward = left x up (true of HumanAct12 and CMU data). Works for
    humanact12, cmu20 and uestc18 (whose a/b sides are assumed to be left/right).
    """
    sk = _skeleton(skeleton)
    left, up, fwd = _body_axes(sk)
    overrides = _REST_OVERRIDES.get(sk.name, {})
    dirs = np.zeros((sk.n_joints, 3))
    for j, name in enumerate(sk.joint_names):
        if j == 0:
            continue
        coef = next((c for k, c in overrides.items() if k in name), None)
        if coef is None:
            coef = next((c for keys, c in _REST_BY_NAME if any(k in name for k in keys)), None)
        if coef is None:
            raise UserError(f"no rest direction for joint {name!r} of skeleton {sk.name!r}")
        side = joint_side(name) if coef[0] else 0.0
        d = side * coef[0] * left + coef[1] * up + coef[2] * fwd
        dirs[j] = d / np.linalg.norm(d)
    return torch.as_tensor(dirs + 0.0, dtype=dtype, device=device)  # + 0.0: no -0 entries


def rest_offsets(reference_pose: torch.Tensor | np.ndarray, skeleton: Skeleton | str) -> torch.Tensor:
    """Rest pose from a reference pose: (..., J, 3) positions -> (..., J, 3) bone offsets.

    Row c is x_c - x_parent(c) of the reference pose (row 0 is zero). With every rotation
    equal to the identity all frames coincide with the root frame, so these are the bones'
    offsets in their parent frames; passing them (or their directions) as `rest_dirs` makes
    the reference pose the pose with zero Lie parameters.
    """
    sk = _skeleton(skeleton)
    pose = _as_float_tensor(reference_pose)
    _check_pose(pose, sk, "reference_pose")
    parents = list(sk.parents)
    parents[0] = 0
    return pose - pose[..., parents, :]


def root_frame_joints(skeleton: Skeleton | str) -> tuple[int, int, int]:
    """(left hip, right hip, first spine joint): the joints that fix the body frame."""
    sk = _skeleton(skeleton)
    children = [j for j, p in enumerate(sk.parents) if p == 0]
    hips = [j for j in children if "hip" in sk.joint_names[j]]
    spine = [j for j in children if any(k in sk.joint_names[j] for k in ("spine", "thorax"))]
    if len(hips) != 2 or len(spine) != 1:
        raise UserError(f"skeleton {sk.name!r} has no two hips and one spine joint below the root")
    left = [j for j in hips if joint_side(sk.joint_names[j]) > 0]
    right = [j for j in hips if joint_side(sk.joint_names[j]) < 0]
    if len(left) != 1 or len(right) != 1:
        raise UserError(f"skeleton {sk.name!r}: cannot tell its left hip from its right hip")
    return left[0], right[0], spine[0]


def _check_pose(pose: torch.Tensor, sk: Skeleton, name: str) -> None:
    shape = tuple(pose.shape)
    if len(shape) < 2 or shape[-1] != 3:
        raise UserError(f"{name} must have shape (..., J, 3), got {shape}")
    if shape[-2] != sk.n_joints:
        raise UserError(f"{name} has {shape[-2]} joints, skeleton {sk.name!r} has {sk.n_joints}")


def _prepare_rest(rest_dirs, sk: Skeleton, like: torch.Tensor) -> torch.Tensor:
    if rest_dirs is None:
        return rest_directions(sk, dtype=like.dtype, device=like.device)
    rest = torch.as_tensor(rest_dirs).to(dtype=like.dtype, device=like.device)
    if tuple(rest.shape) != (sk.n_joints, 3):
        raise UserError(f"rest_dirs must have shape ({sk.n_joints}, 3), got {tuple(rest.shape)}")
    return _normalize(rest)  # root row stays 0


def body_frame(left_dir: torch.Tensor, right_dir: torch.Tensor, up_dir: torch.Tensor) -> torch.Tensor:
    """Orthonormal body frame (columns x, y, z) from unit hip and spine directions."""
    eps = torch.finfo(left_dir.dtype).eps
    x = _normalize(left_dir - right_dir, eps)
    y = _normalize(up_dir - (up_dir * x).sum(-1, keepdim=True) * x, eps)
    z = torch.linalg.cross(x, y)
    return torch.stack([x, y, z], -1)


def bone_lengths_from_pose(pose: torch.Tensor | np.ndarray, skeleton: Skeleton | str) -> torch.Tensor:
    """Length of the bone ending at each joint: (..., J, 3) -> (..., J), 0 for the root.

    Works per frame on (..., T, J, 3) too; average over T (`.mean(-2)`) for a rigid body.
    """
    sk = _skeleton(skeleton)
    pose = _as_float_tensor(pose)
    _check_pose(pose, sk, "pose")
    return torch.linalg.vector_norm(rest_offsets(pose, sk), dim=-1)


# ----------------------------------------------------------------------------- kinematics


def inverse_kinematics(
    positions: torch.Tensor | np.ndarray,
    skeleton: Skeleton | str,
    rest_dirs: torch.Tensor | np.ndarray | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Joint positions (..., T, J, 3) -> (root_translation (..., T, 3), lie_params (..., T, J, 3)).

    root_translation is the root joint's position. lie_params[..., 0, :] is the body
    orientation (from hips and spine, see module docstring); lie_params[..., c, :] is the
    minimal (twist-free) rotation of bone c relative to its parent's frame. `rest_dirs`
    (J, 3) defaults to `rest_directions(skeleton)`. A zero-length bone gets a zero rotation.
    Together with `bone_lengths_from_pose(positions, skeleton)` the positions are recovered
    exactly (to rounding) by `forward_kinematics`.
    """
    sk = _skeleton(skeleton)
    x = _as_float_tensor(positions)
    check_motion(x, n_joints=sk.n_joints, name="positions")
    rest = _prepare_rest(rest_dirs, sk, x)
    parents = sk.parents
    lh, rh, sp = root_frame_joints(sk)

    offsets = rest_offsets(x, sk)  # (..., T, J, 3)
    length2 = (offsets * offsets).sum(-1, keepdim=True)
    zero = length2 <= torch.finfo(x.dtype).tiny
    dirs = offsets / torch.sqrt(torch.where(zero, torch.ones_like(length2), length2))

    frame = body_frame(dirs[..., lh, :], dirs[..., rh, :], dirs[..., sp, :])
    frame_rest = body_frame(rest[lh], rest[rh], rest[sp])
    w_root = so3_log(frame @ frame_rest.transpose(-1, -2))
    rots: list[torch.Tensor | None] = [None] * sk.n_joints
    rots[0] = so3_exp(w_root)  # use exp(log(.)) so IK and FK share the exact same frames
    lie: list[torch.Tensor] = [w_root] * sk.n_joints
    has_children = {p for p in parents if p >= 0}
    for c in _topological_order(parents):
        g_parent = rots[parents[c]]
        u = rest[c].expand_as(w_root)
        d_world = torch.where(zero[..., c, :], (g_parent @ rest[c][:, None]).squeeze(-1), dirs[..., c, :])
        d_local = (g_parent.transpose(-1, -2) @ d_world[..., None]).squeeze(-1)
        lie[c] = rotation_between(u, d_local)
        if c in has_children:
            rots[c] = g_parent @ so3_exp(lie[c])
    return x[..., 0, :], torch.stack(lie, -2)


def forward_kinematics(
    root_translation: torch.Tensor,
    lie_params: torch.Tensor,
    bone_lengths: torch.Tensor,
    skeleton: Skeleton | str,
    rest_dirs: torch.Tensor | np.ndarray | None = None,
) -> torch.Tensor:
    """A2M eq. (4): (root (..., T, 3), lie (..., T, J, 3), lengths) -> positions (..., T, J, 3).

    G_0 = exp(w_0), G_c = G_parent exp(w_c), x_0 = root, x_c = x_parent + b_c G_c u_c.
    `bone_lengths` is per clip, (..., J) (broadcast over T), or per frame, (..., T, J): a
    tensor with exactly one dimension fewer than `lie_params` is taken as per frame, any
    other as per clip. Entry 0 (the root) is ignored.
    """
    sk = _skeleton(skeleton)
    lie = _as_float_tensor(lie_params)
    check_motion(lie, n_joints=sk.n_joints, name="lie_params")
    root = torch.as_tensor(root_translation).to(dtype=lie.dtype, device=lie.device)
    if tuple(root.shape) != tuple(lie.shape[:-2]) + (3,):
        raise UserError(
            f"root_translation shape {tuple(root.shape)} does not match lie_params shape {tuple(lie.shape)}"
        )
    lengths = torch.as_tensor(bone_lengths).to(dtype=lie.dtype, device=lie.device)
    if lengths.dim() < 1 or lengths.shape[-1] != sk.n_joints:
        raise UserError(f"bone_lengths must have shape (..., {sk.n_joints}), got {tuple(lengths.shape)}")
    if lengths.dim() != lie.dim() - 1:
        lengths = lengths.unsqueeze(-2)  # per clip -> broadcast over T
    try:
        lengths = torch.broadcast_to(lengths, lie.shape[:-1])
    except RuntimeError:
        raise UserError(
            f"bone_lengths shape {tuple(torch.as_tensor(bone_lengths).shape)} does not broadcast "
            f"to lie_params shape {tuple(lie.shape)}"
        ) from None
    rest = _prepare_rest(rest_dirs, sk, lie)
    parents = sk.parents

    local = so3_exp(lie)  # (..., T, J, 3, 3)
    rots: list[torch.Tensor | None] = [None] * sk.n_joints
    pos: list[torch.Tensor | None] = [None] * sk.n_joints
    rots[0] = local[..., 0, :, :]
    pos[0] = root
    for c in _topological_order(parents):
        p = parents[c]
        rots[c] = rots[p] @ local[..., c, :, :]
        pos[c] = pos[p] + lengths[..., c, None] * (rots[c] @ rest[c])
    return torch.stack(pos, -2)  # type: ignore[arg-type]


# ----------------------------------------------------------------------------- body shape

# Groups by the name of the bone's child joint. Girdle bones (pelvis->hip, ->collar,
# ->shoulder) belong to no group and are scaled by `all` only.
_GROUP_KEYS: Mapping[str, tuple[str, ...]] = {
    "legs": ("knee", "ankle", "foot", "toe"),
    "arms": ("elbow", "wrist", "hand"),
    "spine": ("spine", "thorax", "neck", "head"),
}


def bone_groups(skeleton: Skeleton | str) -> dict[str, tuple[int, ...]]:
    """Joint indices of the bones in each group ("legs", "arms", "spine"), from joint names.

    legs: thigh, shin, foot (bones ending at knee/ankle/foot/toe); arms: upper arm, forearm,
    hand (ending at elbow/wrist/hand); spine: bones ending at spine*/thorax/neck/head.
    """
    sk = _skeleton(skeleton)
    return {
        group: tuple(j for j, n in enumerate(sk.joint_names) if j > 0 and any(k in n for k in keys))
        for group, keys in _GROUP_KEYS.items()
    }


def scale_bones(
    bone_lengths: torch.Tensor,
    skeleton: Skeleton | str,
    legs: float = 1.0,
    arms: float = 1.0,
    spine: float = 1.0,
    all: float = 1.0,  # noqa: A002 - mirrors the CLI option name
) -> torch.Tensor:
    """Scale bone lengths (..., J) by body part, to replay a motion on another body (A2M Fig. 6).

    Each bone is multiplied by its group's factor (see `bone_groups`) and by `all`. Returns a
    new tensor; feed it to `forward_kinematics` with the motion's Lie parameters.
    """
    sk = _skeleton(skeleton)
    lengths = _as_float_tensor(bone_lengths)
    if lengths.dim() < 1 or lengths.shape[-1] != sk.n_joints:
        raise UserError(f"bone_lengths must have shape (..., {sk.n_joints}), got {tuple(lengths.shape)}")
    factors = {"legs": legs, "arms": arms, "spine": spine, "all": all}
    for name, f in factors.items():
        if not (isinstance(f, (int, float)) and np.isfinite(f) and f > 0):
            raise UserError(f"scale factor {name}={f!r} must be a positive number")
    scale = torch.full((sk.n_joints,), float(all), dtype=lengths.dtype, device=lengths.device)
    for group, joints in bone_groups(sk).items():
        scale[list(joints)] *= factors[group]
    return lengths * scale


def retarget(
    positions: torch.Tensor | np.ndarray,
    bone_lengths: torch.Tensor | np.ndarray,
    skeleton: Skeleton | str,
) -> torch.Tensor:
    """The same motion (..., T, J, 3) on another body: its Lie parameters and root path, new lengths.

    `bone_lengths` is (..., J), e.g. another clip's `bone_lengths_from_pose(clip).mean(-2)` or
    `scale_bones(...)` of this one's (A2M Fig. 6); every frame gets exactly those lengths.
    """
    sk = _skeleton(skeleton)
    root, w = inverse_kinematics(positions, sk)
    lengths = _as_float_tensor(bone_lengths)
    if lengths.dim() < 1 or lengths.shape[-1] != sk.n_joints:
        raise UserError(f"bone_lengths must have shape (..., {sk.n_joints}), got {tuple(lengths.shape)}")
    return forward_kinematics(root, w, lengths.unsqueeze(-2), sk)


def rigid_bones(motion: torch.Tensor, parents: Sequence[int], lengths: torch.Tensor | None = None,
                branches: dict[int, tuple[int, int, int]] | None = None,
                pieces: dict[int, torch.Tensor] | None = None) -> torch.Tensor:
    """Motion (..., T, J, 3) with every bone at one length for all frames: each joint at its parent's new
    position plus its own direction from the parent times the bone's length. The root stays where it is
    and every bone keeps its direction, so only lengths change.

    lengths (..., J): each joint's bone (the root's entry unused); default: each bone's median length
    over the frames of its motion (the body the motion draws, made rigid). branches {joint: (left,
    right, middle)}: joints whose three children move as one rigid piece (a pelvis with its hips and
    spine, a chest with its collars and neck), as in a body model and in BVH export: the children sit at
    their mean offsets in the joint's body frame (body_frame of the three directions), so the angles
    between them stay fixed too, and at their mean offsets' lengths (`lengths` does not apply to them).
    pieces {joint: (..., 1, 3, 3)}: those offsets given (`rigid_pieces` of another motion of the same
    body) instead of this motion's means. Differentiable; a bone of zero length keeps its child on the
    parent."""
    check_motion(motion, n_joints=len(parents))
    child = torch.tensor([j for j, p in enumerate(parents) if p >= 0], device=motion.device)
    parent = torch.tensor([parents[j] for j in child.tolist()], device=motion.device)
    bones = motion.index_select(-2, child) - motion.index_select(-2, parent)  # (..., T, B, 3)
    norm = torch.linalg.vector_norm(bones, dim=-1, keepdim=True)  # (..., T, B, 1)
    size = norm[..., 0].median(dim=-2).values if lengths is None else lengths.index_select(-1, child)  # (..., B)
    # (..., T, J, 3): each joint from its new parent (the root from itself: 0)
    offsets = motion.new_zeros(motion.shape).index_copy(-2, child, bones / norm.clamp_min(1e-12) * size[..., None, :, None])
    for j, kids in (branches or {}).items():
        own, frame = _piece(motion, j, kids)
        local = pieces[j] if pieces is not None else _mean_piece(own, frame)
        offsets[..., list(kids), :] = (frame @ local).transpose(-1, -2)  # (..., T, 3 kids, 3)
    # every joint is the root plus the offsets along its path from the root: one product with the tree
    path = _paths(tuple(parents)).to(motion)  # (J, J)
    return motion[..., :1, :] + torch.einsum("jk,...kc->...jc", path, offsets)


def rigid_pieces(motion: torch.Tensor, branches: dict[int, tuple[int, int, int]]) -> dict[int, torch.Tensor]:
    """The rigid pieces `rigid_bones` gives motion (..., T, J, 3) at its branches: {joint: (..., 1, 3, 3)},
    the three children's mean offsets (columns) in the joint's body frame."""
    return {j: _mean_piece(*_piece(motion, j, kids)) for j, kids in branches.items()}


def _piece(motion: torch.Tensor, j: int, kids: tuple[int, int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """Joint j's three children's offsets (..., T, 3, 3) (columns) and the body frame they span (..., T, 3, 3)."""
    own = torch.stack([motion[..., c, :] - motion[..., j, :] for c in kids], dim=-1)
    return own, body_frame(_unit(own[..., 0]), _unit(own[..., 1]), _unit(own[..., 2]))


def _mean_piece(own: torch.Tensor, frame: torch.Tensor) -> torch.Tensor:
    """The rigid piece (..., 1, 3, 3): the children's offsets `own` in their body `frame`, averaged over the frames."""
    return (frame.transpose(-1, -2) @ own).mean(dim=-3, keepdim=True)


@functools.lru_cache(maxsize=None)
def _paths(parents: tuple[int, ...]) -> torch.Tensor:
    """(J, J): entry (j, k) is 1 when joint k lies on the path from the root to j (j itself included, the
    root not)."""
    out = torch.zeros(len(parents), len(parents))
    for j in range(len(parents)):
        k = j
        while parents[k] >= 0:
            out[j, k] = 1.0
            k = parents[k]
    return out


def _unit(d: torch.Tensor) -> torch.Tensor:
    return d / torch.linalg.vector_norm(d, dim=-1, keepdim=True).clamp_min(1e-12)
