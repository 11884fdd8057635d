"""Tests of odmo_cli.geometry.lie: so(3) maps, rest poses, inverse/forward kinematics, bone scaling.

Real-data tests read clips below $ODMO_DATA_DIR (humanact12/HumanAct12/*.npy and
cmu_a2m/mocap_3djoints/*.npy) and are skipped when it is unset.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from odmo_cli.geometry import lie
from odmo_cli.errors import UserError
from odmo_cli.geometry.skeletons import SKELETONS, get_skeleton

DATA_DIR = os.environ.get("ODMO_DATA_DIR")
needs_data = pytest.mark.skipif(
    not DATA_DIR, reason="ODMO_DATA_DIR is not set (point it at the folder holding humanact12/ and cmu_a2m/)"
)

DTYPES = [torch.float32, torch.float64]
EDGE_ANGLES = [0.0, 1e-8, math.pi / 2, math.pi - 1e-6, math.pi]


def _axes(dtype=torch.float64) -> torch.Tensor:
    """Coordinate axes, a diagonal and a few random unit axes: (7, 3)."""
    g = torch.Generator().manual_seed(0)
    rand = torch.randn(3, 3, generator=g, dtype=torch.float64)
    axes = torch.cat([torch.eye(3, dtype=torch.float64), torch.ones(1, 3, dtype=torch.float64), rand])
    return (axes / axes.norm(dim=-1, keepdim=True)).to(dtype)


def _random_omega(n: int, max_angle: float = math.pi, seed: int = 0, dtype=torch.float64) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    axis = torch.randn(n, 3, generator=g, dtype=torch.float64)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    angle = torch.rand(n, 1, generator=g, dtype=torch.float64) * max_angle
    return (axis * angle).to(dtype)


def _unit(v: torch.Tensor) -> torch.Tensor:
    return v / v.norm(dim=-1, keepdim=True)


def _assert_rotation(r: torch.Tensor, atol: float) -> None:
    eye = torch.eye(3, dtype=r.dtype).expand_as(r)
    torch.testing.assert_close(r.transpose(-1, -2) @ r, eye, atol=atol, rtol=0)
    torch.testing.assert_close(torch.linalg.det(r), torch.ones(r.shape[:-2], dtype=r.dtype), atol=atol, rtol=0)


# ----------------------------------------------------------------------------- hat / vee


def test_hat_is_cross_product_and_vee_inverts_it():
    v, x = torch.randn(2, 5, 3, dtype=torch.float64)
    k = lie.hat(v)
    assert k.shape == (5, 3, 3)
    torch.testing.assert_close((k @ x[..., None]).squeeze(-1), torch.linalg.cross(v, x))
    torch.testing.assert_close(k, -k.transpose(-1, -2))
    torch.testing.assert_close(lie.vee(k), v)


# ----------------------------------------------------------------------------- exp


def test_exp_known_values():
    rz = lie.so3_exp(torch.tensor([0.0, 0.0, math.pi / 2], dtype=torch.float64))
    expected = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    torch.testing.assert_close(rz, expected, atol=1e-15, rtol=0)
    torch.testing.assert_close(lie.so3_exp(torch.zeros(3)), torch.eye(3))
    rx = lie.so3_exp(torch.tensor([math.pi, 0.0, 0.0], dtype=torch.float64))
    torch.testing.assert_close(rx, torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64)), atol=1e-15, rtol=0)


def test_exp_matches_scipy():
    omega = torch.cat([_random_omega(200, 2 * math.pi), _random_omega(50, 0.02, seed=1)])
    expected = torch.as_tensor(Rotation.from_rotvec(omega.numpy()).as_matrix())
    torch.testing.assert_close(lie.so3_exp(omega), expected, atol=1e-14, rtol=0)


@pytest.mark.parametrize("dtype", DTYPES)
def test_exp_outputs_are_rotations(dtype):
    omega = torch.cat([_random_omega(300, 3 * math.pi, dtype=dtype)] + [_axes(dtype) * a for a in EDGE_ANGLES])
    r = lie.so3_exp(omega.reshape(-1, 5, 3))  # extra batch dim
    assert r.shape == (omega.shape[0] // 5, 5, 3, 3) and r.dtype == dtype
    _assert_rotation(r, atol=1e-6 if dtype == torch.float32 else 1e-14)


# ----------------------------------------------------------------------------- log


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("angle", EDGE_ANGLES)
def test_exp_log_round_trip_edge_angles(angle, dtype):
    omega = _axes(dtype) * angle
    r = lie.so3_exp(omega)
    w = lie.so3_log(r)
    assert torch.isfinite(w).all()
    atol = 1e-5 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(lie.so3_exp(w), r, atol=atol, rtol=0)
    torch.testing.assert_close(w.norm(dim=-1), omega.norm(dim=-1), atol=atol, rtol=0)
    if dtype == torch.float64:
        if angle < math.pi:
            torch.testing.assert_close(w, omega, atol=1e-12, rtol=0)
        else:  # at pi, omega and -omega are the same rotation
            sign = torch.sign((w * omega).sum(-1, keepdim=True))
            torch.testing.assert_close(w * sign, omega, atol=1e-12, rtol=0)


def test_log_exp_identity_below_pi():
    omega = torch.cat([
        _random_omega(500, math.pi - 1e-3),
        _random_omega(100, 0.03, seed=1),  # around the Taylor threshold
        _random_omega(100, 1e-6, seed=2),
        _unit(_random_omega(100, 1.0, seed=3)) * (math.pi - 1e-4 * torch.rand(100, 1, dtype=torch.float64)),
    ])
    omega = omega[omega.norm(dim=-1) < math.pi]
    torch.testing.assert_close(lie.so3_log(lie.so3_exp(omega)), omega, atol=1e-11, rtol=0)


def test_log_near_pi_all_axes():
    # every branch of the symmetric-part formula (largest diagonal on x, y or z)
    axes = _unit(_random_omega(300, 1.0, seed=4))
    for angle in (2.2, 3.0, math.pi - 1e-7):
        omega = axes * angle
        torch.testing.assert_close(lie.so3_log(lie.so3_exp(omega)), omega, atol=1e-9, rtol=0)


def test_log_of_random_rotation_matrices():
    r = torch.as_tensor(Rotation.random(500, random_state=0).as_matrix())
    w = lie.so3_log(r)
    assert (w.norm(dim=-1) <= math.pi + 1e-12).all()
    torch.testing.assert_close(lie.so3_exp(w), r, atol=1e-13, rtol=0)
    expected = torch.as_tensor(Rotation.from_matrix(r.numpy()).as_rotvec())
    torch.testing.assert_close(w, expected, atol=1e-12, rtol=0)


# ----------------------------------------------------------------------------- gradients


@pytest.mark.parametrize("scale", [0.0, 1e-12, 1e-8, 1e-4])
def test_exp_gradient_finite_near_zero(scale):
    omega = (torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64) * scale).requires_grad_(True)
    jac = torch.autograd.functional.jacobian(lie.so3_exp, omega)  # (3, 3, 3)
    assert torch.isfinite(jac).all()
    # d exp / d omega_i at 0 is hat(e_i)
    expected = torch.stack([lie.hat(e) for e in torch.eye(3, dtype=torch.float64)], -1)
    torch.testing.assert_close(jac, expected, atol=1e-3 if scale else 1e-15, rtol=0)


@pytest.mark.parametrize("scale", [0.0, 1e-12, 1e-8, 1e-4])
def test_log_gradient_finite_near_identity(scale):
    r = lie.so3_exp(torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64) * scale).requires_grad_(True)
    jac = torch.autograd.functional.jacobian(lie.so3_log, r)  # (3, 3, 3)
    assert torch.isfinite(jac).all()
    # log(exp(omega)) = omega: the chain through both maps is the identity
    omega = (torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64) * scale).requires_grad_(True)
    jac2 = torch.autograd.functional.jacobian(lambda w: lie.so3_log(lie.so3_exp(w)), omega)
    torch.testing.assert_close(jac2, torch.eye(3, dtype=torch.float64), atol=1e-8, rtol=0)


def test_gradcheck_exp_and_log():
    omega = torch.cat([
        _random_omega(6, 3.0, seed=5),
        _random_omega(3, 1e-2, seed=6) * torch.tensor([[0.9], [1.0], [1.1]], dtype=torch.float64),
        _random_omega(2, 1e-5, seed=7),
    ]).requires_grad_(True)
    assert torch.autograd.gradcheck(lie.so3_exp, (omega,))
    assert torch.autograd.gradcheck(lambda w: lie.so3_log(lie.so3_exp(w)), (omega,))
    u = torch.randn(5, 3, dtype=torch.float64, requires_grad=True)
    v = torch.randn(5, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lie.rotation_between, (u, v))


def test_gradient_of_kinematics_is_finite_at_rest():
    sk = get_skeleton("humanact12")
    lie_params = torch.zeros(2, sk.n_joints, 3, dtype=torch.float64, requires_grad=True)
    lengths = torch.full((sk.n_joints,), 0.2, dtype=torch.float64)
    pos = lie.forward_kinematics(torch.zeros(2, 3, dtype=torch.float64), lie_params, lengths, sk)
    pos.square().sum().backward()
    assert torch.isfinite(lie_params.grad).all()
    x = pos.detach().requires_grad_(True)
    _, w = lie.inverse_kinematics(x, sk)
    w.sum().backward()
    assert torch.isfinite(x.grad).all()


# ----------------------------------------------------------------------------- minimal rotation


def test_rotation_between_is_minimal_and_exact():
    g = torch.Generator().manual_seed(8)
    u = torch.randn(200, 3, generator=g, dtype=torch.float64)
    u = u / u.norm(dim=-1, keepdim=True)
    v_rand = torch.randn(200, 3, generator=g, dtype=torch.float64)
    perp = torch.linalg.cross(u, v_rand)
    perp = perp / perp.norm(dim=-1, keepdim=True)
    cases = [v_rand / v_rand.norm(dim=-1, keepdim=True), u, -u]
    for eps in (1e-3, 1e-9, 1e-14):
        near = u + eps * perp
        cases += [near / near.norm(dim=-1, keepdim=True), -near / near.norm(dim=-1, keepdim=True)]
    for v in cases:
        w = lie.rotation_between(u, v)
        assert torch.isfinite(w).all()
        torch.testing.assert_close((lie.so3_exp(w) @ u[..., None]).squeeze(-1), v, atol=1e-13, rtol=0)
        angle = torch.arccos((u * v).sum(-1).clamp(-1, 1))
        torch.testing.assert_close(w.norm(dim=-1), angle, atol=1e-7, rtol=0)
        # no twist: the rotation axis is perpendicular to u (and hence to v)
        assert (w * u).sum(-1).abs().max() < 1e-12


# ----------------------------------------------------------------------------- rest pose


@pytest.mark.parametrize("name", list(SKELETONS))
def test_rest_directions_and_rest_pose_has_zero_rotations(name):
    sk = get_skeleton(name)
    rest = lie.rest_directions(sk)
    assert rest.shape == (sk.n_joints, 3)
    assert (rest[0] == 0).all()
    torch.testing.assert_close(rest[1:].norm(dim=-1), torch.ones(sk.n_joints - 1, dtype=torch.float64))
    # the rest pose built from the rest directions: all Lie parameters zero
    lengths = torch.linspace(0.05, 0.4, sk.n_joints, dtype=torch.float64)
    lengths[0] = 0
    zero = torch.zeros(1, sk.n_joints, 3, dtype=torch.float64)
    pose = lie.forward_kinematics(torch.zeros(1, 3, dtype=torch.float64), zero, lengths, sk)
    offsets = lie.rest_offsets(pose[0], sk)
    torch.testing.assert_close(offsets, rest * lengths[:, None])
    root, w = lie.inverse_kinematics(pose, name)  # by name too
    torch.testing.assert_close(w, zero, atol=1e-12, rtol=0)
    torch.testing.assert_close(lie.bone_lengths_from_pose(pose[0], sk), lengths)


def test_rest_offsets_from_reference_pose():
    sk = get_skeleton("humanact12")
    reference = _synthetic_motion(sk, batch=(), frames=1, seed=9)[0][0]  # (J, 3)
    offsets = lie.rest_offsets(reference, sk)
    _, w = lie.inverse_kinematics(reference[None], sk, rest_dirs=offsets)
    torch.testing.assert_close(w, torch.zeros_like(w), atol=1e-12, rtol=0)
    lengths = lie.bone_lengths_from_pose(reference, sk)
    back = lie.forward_kinematics(reference[None, 0], w, lengths, sk, rest_dirs=offsets)
    torch.testing.assert_close(back[0], reference, atol=1e-12, rtol=0)


# ----------------------------------------------------------------------------- IK / FK


def _synthetic_motion(sk, batch=(2,), frames=6, seed=0, dtype=torch.float64):
    """A rigid motion by FK: random rotations (< 1 rad), fixed bone lengths, random root."""
    g = torch.Generator().manual_seed(seed)
    lie_params = (torch.rand(*batch, frames, sk.n_joints, 3, generator=g, dtype=torch.float64) - 0.5) * 1.2
    lengths = 0.05 + 0.4 * torch.rand(*batch, sk.n_joints, generator=g, dtype=torch.float64)
    lengths[..., 0] = 0
    root = torch.randn(*batch, frames, 3, generator=g, dtype=torch.float64)
    pos = lie.forward_kinematics(root, lie_params, lengths, sk)
    return pos.to(dtype), lengths.to(dtype)


@pytest.mark.parametrize("name", list(SKELETONS))
def test_synthetic_rigid_round_trip(name):
    sk = get_skeleton(name)
    pos, lengths = _synthetic_motion(sk, batch=(2, 3))
    assert pos.shape == (2, 3, 6, sk.n_joints, 3)
    # bone lengths constant after FK with fixed lengths
    per_frame = lie.bone_lengths_from_pose(pos, sk)
    torch.testing.assert_close(per_frame, lengths[..., None, :].expand_as(per_frame), atol=1e-13, rtol=0)
    root, w = lie.inverse_kinematics(pos, sk)
    assert root.shape == (2, 3, 6, 3) and w.shape == (2, 3, 6, sk.n_joints, 3)
    assert (w.norm(dim=-1) <= math.pi + 1e-9).all()
    back = lie.forward_kinematics(root, w, lengths, sk)  # per-clip lengths (..., J)
    assert (back - pos).abs().max() < 1e-12


def test_synthetic_round_trip_float32():
    sk = get_skeleton("humanact12")
    pos, lengths = _synthetic_motion(sk, dtype=torch.float32)
    root, w = lie.inverse_kinematics(pos, sk)
    assert w.dtype == torch.float32
    back = lie.forward_kinematics(root, w, lengths, sk)
    assert back.dtype == torch.float32
    assert (back - pos).abs().max() < 1e-5


def test_global_rotation_only_changes_root_rotation():
    sk = get_skeleton("cmu20")
    pos, _ = _synthetic_motion(sk, seed=3)
    q = torch.as_tensor(Rotation.random(random_state=1).as_matrix())
    root, w = lie.inverse_kinematics(pos, sk)
    root_q, w_q = lie.inverse_kinematics(pos @ q.T, sk)
    torch.testing.assert_close(root_q, root @ q.T)
    torch.testing.assert_close(w_q[..., 1:, :], w[..., 1:, :], atol=1e-10, rtol=0)
    torch.testing.assert_close(lie.so3_exp(w_q[..., 0, :]), q @ lie.so3_exp(w[..., 0, :]), atol=1e-10, rtol=0)


def test_scale_bones():
    sk = get_skeleton("humanact12")
    pos, lengths = _synthetic_motion(sk, batch=(), frames=4, seed=4)
    groups = lie.bone_groups(sk)
    names = {g: {sk.joint_names[j] for j in js} for g, js in groups.items()}
    assert {"left_knee", "right_ankle", "left_foot"} <= names["legs"]
    assert {"left_elbow", "right_wrist", "left_hand"} <= names["arms"]
    assert {"spine1", "neck", "head"} <= names["spine"]
    scaled = lie.scale_bones(lengths, sk, legs=1.5, arms=0.5, all=2.0)
    factor = scaled / lengths.clamp_min(1e-12)
    for j in range(1, sk.n_joints):
        expected = 2.0 * (1.5 if j in groups["legs"] else 0.5 if j in groups["arms"] else 1.0)
        assert factor[j].item() == pytest.approx(expected)
    assert scaled[0] == 0
    # replay the motion on the new body: new lengths, same Lie parameters
    root, w = lie.inverse_kinematics(pos, sk)
    new = lie.forward_kinematics(root, w, scaled, sk)
    torch.testing.assert_close(lie.bone_lengths_from_pose(new, sk), scaled.expand(4, -1))
    with pytest.raises(UserError):
        lie.scale_bones(lengths, sk, legs=-1.0)


def test_retarget_to_another_body():
    sk = get_skeleton("humanact12")
    pos, lengths = _synthetic_motion(sk, batch=(), frames=4, seed=4)
    other = lie.bone_lengths_from_pose(_synthetic_motion(sk, batch=(), frames=2, seed=9)[0], sk).mean(-2)
    assert not torch.allclose(other, lengths)
    moved = lie.retarget(pos, other, sk)
    torch.testing.assert_close(lie.bone_lengths_from_pose(moved, sk), other.expand(4, -1))
    root, w = lie.inverse_kinematics(pos, sk)
    root_m, w_m = lie.inverse_kinematics(moved, sk)
    torch.testing.assert_close(root_m, root)
    torch.testing.assert_close(w_m, w, atol=1e-9, rtol=0)  # same rotations: the same movement
    torch.testing.assert_close(lie.retarget(pos, lengths, sk), pos)
    longer = lie.retarget(pos, lie.scale_bones(lengths, sk, legs=1.2), sk)
    knee = sk.joint_names.index("left_knee")
    ratio = lie.bone_lengths_from_pose(longer, sk)[:, knee] / lengths[knee]
    torch.testing.assert_close(ratio, torch.full_like(ratio, 1.2))
    with pytest.raises(UserError, match="bone_lengths must have shape"):
        lie.retarget(pos, lengths[:20], sk)


# ----------------------------------------------------------------------------- real data


def _clips(sub: str, n: int) -> list[Path]:
    folder = Path(DATA_DIR) / sub  # type: ignore[arg-type]
    files = sorted(folder.glob("*.npy"))
    if not files:
        pytest.skip(f"no .npy clips in {folder}")
    return [files[i] for i in np.linspace(0, len(files) - 1, n).astype(int)]


@needs_data
@pytest.mark.parametrize(
    "name,sub,scale",
    [("humanact12", "humanact12/HumanAct12", 1.0), ("cmu20", "cmu_a2m/mocap_3djoints", 20.0)],
)
def test_real_clips_round_trip(name, sub, scale):
    """xyz -> Lie -> xyz with the clip's own per-frame bone lengths (real lengths vary a little)."""
    sk = get_skeleton(name)
    worst = 0.0
    for path in _clips(sub, 4):
        pos = torch.as_tensor(np.load(path)) / scale
        assert pos.dtype == torch.float64 and pos.shape[1:] == (sk.n_joints, 3)
        root, w = lie.inverse_kinematics(pos, sk)
        lengths = lie.bone_lengths_from_pose(pos, sk)  # (T, J): per frame
        back = lie.forward_kinematics(root, w, lengths, sk)
        worst = max(worst, (back - pos).abs().max().item())
        # float32 too
        root32, w32 = lie.inverse_kinematics(pos.float(), sk)
        back32 = lie.forward_kinematics(root32, w32, lengths.float(), sk)
        assert (back32 - pos.float()).abs().max() < 1e-5
        # rigid body: the clip's mean lengths give constant bone lengths
        mean = lengths.mean(0)
        rigid = lie.forward_kinematics(root, w, mean, sk)
        torch.testing.assert_close(lie.bone_lengths_from_pose(rigid, sk), mean.expand_as(lengths))
    assert worst < 1e-6, f"round-trip error {worst:.3g} m"


# ----------------------------------------------------------------------------- bad input


def _one_line_error(fn, *args, **kwargs) -> str:
    with pytest.raises(UserError) as info:
        fn(*args, **kwargs)
    message = str(info.value)
    assert message and "\n" not in message
    return message


def test_bad_shapes_raise_user_error():
    sk = get_skeleton("humanact12")
    good = torch.zeros(5, sk.n_joints, 3, dtype=torch.float64)
    _one_line_error(lie.hat, torch.zeros(4))
    _one_line_error(lie.vee, torch.zeros(3, 4))
    _one_line_error(lie.so3_exp, torch.zeros(2, 2))
    _one_line_error(lie.so3_log, torch.zeros(3))
    _one_line_error(lie.rotation_between, torch.zeros(3), torch.zeros(2))
    assert "joints" in _one_line_error(lie.inverse_kinematics, torch.zeros(5, 23, 3), sk)
    _one_line_error(lie.inverse_kinematics, torch.zeros(5, sk.n_joints, 2), sk)
    _one_line_error(lie.inverse_kinematics, torch.zeros(sk.n_joints, 3), sk)  # no time axis
    _one_line_error(lie.inverse_kinematics, good, sk, rest_dirs=torch.zeros(20, 3))
    lengths = torch.ones(sk.n_joints, dtype=torch.float64)
    _one_line_error(lie.forward_kinematics, torch.zeros(4, 3), good, lengths, sk)
    _one_line_error(lie.forward_kinematics, torch.zeros(5, 3), good[:, :20], lengths, sk)
    _one_line_error(lie.forward_kinematics, torch.zeros(5, 3), good, lengths[:20], sk)
    _one_line_error(lie.forward_kinematics, torch.zeros(5, 3), good, torch.ones(4, 5, sk.n_joints), sk)
    _one_line_error(lie.bone_lengths_from_pose, torch.zeros(20, 3), sk)
    _one_line_error(lie.rest_offsets, torch.zeros(sk.n_joints, 4), sk)
    _one_line_error(lie.scale_bones, torch.ones(20), sk)
    _one_line_error(lie.rest_directions, "no_such_skeleton")
