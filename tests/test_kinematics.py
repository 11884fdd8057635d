"""`odmo_cli.geometry.kinematics` (LMP/trajectory split, root velocities, bone lengths) and the named
skeletons of `odmo_cli.geometry.skeletons` (parents derived from chains, tree structure)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from odmo_cli.errors import UserError
from odmo_cli.geometry.kinematics import bone_lengths, check_motion, join_lmp, root_velocities, split_lmp
from odmo_cli.geometry.skeletons import SKELETONS, get_skeleton

SMPL_PARENTS = (-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19, 20, 21)
# cmu20: thorax/neck/head on the root, arms on the thorax (1), legs on the root.
CMU20_PARENTS = (-1, 0, 1, 2, 1, 4, 5, 6, 1, 8, 9, 10, 0, 12, 13, 14, 0, 16, 17, 18)


def _motion(shape, seed=0):
    return np.random.default_rng(seed).normal(size=shape)


# ---------------------------------------------------------------- LMP / trajectory


@pytest.mark.parametrize("shape", [(5, 4, 3), (2, 5, 4, 3), (2, 3, 5, 24, 3)])
def test_split_join_round_trip_numpy(shape):
    motion = _motion(shape)
    lmp, traj = split_lmp(motion)
    assert lmp.shape == shape
    assert traj.shape == shape[:-2] + (3,)
    np.testing.assert_array_equal(traj, motion[..., 0, :])
    np.testing.assert_array_equal(lmp[..., 0, :], 0.0)  # root joint of the LMP is exactly zero
    np.testing.assert_allclose(lmp[..., 1:, :], motion[..., 1:, :] - motion[..., :1, :])
    np.testing.assert_allclose(join_lmp(lmp, traj), motion, atol=1e-12)


@pytest.mark.parametrize("shape", [(6, 20, 3), (3, 6, 20, 3), (2, 2, 6, 20, 3)])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_split_join_round_trip_torch(shape, dtype):
    motion = torch.from_numpy(_motion(shape, seed=1)).to(dtype)
    lmp, traj = split_lmp(motion)
    assert isinstance(lmp, torch.Tensor) and isinstance(traj, torch.Tensor)
    assert lmp.dtype == dtype and traj.dtype == dtype
    assert tuple(lmp.shape) == shape and tuple(traj.shape) == shape[:-2] + (3,)
    assert torch.equal(traj, motion[..., 0, :])
    assert torch.count_nonzero(lmp[..., 0, :]) == 0
    torch.testing.assert_close(join_lmp(lmp, traj), motion)


def test_split_agrees_between_numpy_and_torch():
    motion = _motion((2, 7, 5, 3), seed=2)
    lmp_np, traj_np = split_lmp(motion)
    lmp_t, traj_t = split_lmp(torch.from_numpy(motion))
    np.testing.assert_allclose(lmp_t.numpy(), lmp_np)
    np.testing.assert_allclose(traj_t.numpy(), traj_np)


def test_lmp_is_translation_invariant():
    motion = _motion((8, 5, 3), seed=3)
    shifted = motion + np.array([1.5, -2.0, 0.25])
    np.testing.assert_allclose(split_lmp(shifted)[0], split_lmp(motion)[0], atol=1e-12)


def test_lmp_known_values():
    motion = np.array([[[1.0, 2.0, 3.0], [2.0, 2.0, 3.0], [1.0, 5.0, 3.0]]])  # (T=1, J=3, 3)
    lmp, traj = split_lmp(motion)
    np.testing.assert_array_equal(traj, [[1.0, 2.0, 3.0]])
    np.testing.assert_array_equal(lmp, [[[0, 0, 0], [1, 0, 0], [0, 3, 0]]])


# ---------------------------------------------------------------- root velocities


def test_root_velocities_known_values_numpy():
    traj = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [3.0, 0.5, 0.0], [6.0, 0.5, -1.0]])
    v = root_velocities(traj)
    np.testing.assert_array_equal(v, [[0, 0, 0], [1, 0, 0], [2, 0.5, 0], [3, 0, -1]])
    np.testing.assert_array_equal(np.cumsum(v, axis=0), traj)  # integrating gives r back


def test_root_velocities_r0_zero_convention():
    # v_0 = r_0 - 0: the first step is measured from the origin (ODMO eq. 2)
    traj = np.array([[2.0, -1.0, 4.0], [2.5, -1.0, 4.0]])
    np.testing.assert_array_equal(root_velocities(traj), [[2.0, -1.0, 4.0], [0.5, 0.0, 0.0]])


def test_root_velocities_torch_batched_matches_numpy():
    traj = _motion((3, 2, 9, 3), seed=4)
    v_np = root_velocities(traj)
    v_t = root_velocities(torch.from_numpy(traj))
    assert isinstance(v_t, torch.Tensor) and tuple(v_t.shape) == traj.shape
    np.testing.assert_allclose(v_t.numpy(), v_np)
    np.testing.assert_allclose(v_np[..., 0, :], traj[..., 0, :])
    np.testing.assert_allclose(v_np[..., 1:, :], np.diff(traj, axis=-2))
    np.testing.assert_allclose(np.cumsum(v_np, axis=-2), traj, atol=1e-12)


# ---------------------------------------------------------------- bone lengths


def test_bone_lengths_known_values():
    parents = (-1, 0, 1, 0)
    frame = np.array([[0, 0, 0], [3, 4, 0], [3, 4, 2], [0, -1, 0]], dtype=float)  # bones 5, 2, 1
    motion = np.stack([frame, 2 * frame])  # (T=2, J=4, 3): second frame twice as big
    lengths = bone_lengths(motion, parents)
    assert lengths.shape == (2, 3)
    np.testing.assert_allclose(lengths, [[5, 2, 1], [10, 4, 2]])
    lengths_t = bone_lengths(torch.from_numpy(motion), parents)
    assert isinstance(lengths_t, torch.Tensor)
    np.testing.assert_allclose(lengths_t.numpy(), [[5, 2, 1], [10, 4, 2]])


def test_bone_lengths_batched_and_translation_invariant():
    sk = get_skeleton("humanact12")
    motion = _motion((2, 4, 24, 3), seed=5)
    lengths = bone_lengths(motion, sk.parents)
    assert lengths.shape == (2, 4, 23)
    expected = np.stack([np.linalg.norm(motion[..., j, :] - motion[..., p, :], axis=-1) for p, j in sk.bones],
                        axis=-1)
    np.testing.assert_allclose(lengths, expected)
    np.testing.assert_allclose(bone_lengths(motion + 3.0, sk.parents), lengths, atol=1e-12)


# ---------------------------------------------------------------- bad shapes


@pytest.mark.parametrize("shape", [(5, 3), (3,), (5, 4, 2), (5, 4, 4), (0, 4, 3), (2, 0, 4, 3)])
def test_bad_shapes_raise_user_error(shape):
    bad = np.zeros(shape)
    with pytest.raises(UserError, match=r"shape"):
        check_motion(bad)
    with pytest.raises(UserError):
        split_lmp(bad)
    with pytest.raises(UserError):
        split_lmp(torch.zeros(shape))


def test_join_rejects_mismatched_trajectory():
    lmp = np.zeros((2, 5, 4, 3))
    with pytest.raises(UserError, match="trajectory shape"):
        join_lmp(lmp, np.zeros((2, 6, 3)))  # wrong T
    with pytest.raises(UserError, match="trajectory shape"):
        join_lmp(lmp, np.zeros((5, 3)))  # missing batch dim
    with pytest.raises(UserError, match="LMP"):
        join_lmp(np.zeros((5, 4)), np.zeros((5, 3)))


def test_bone_lengths_rejects_wrong_joint_count():
    with pytest.raises(UserError, match="22 joints.*24"):
        bone_lengths(np.zeros((3, 22, 3)), SMPL_PARENTS)
    with pytest.raises(UserError, match="shape"):
        bone_lengths(np.zeros((3, 24)), SMPL_PARENTS)


# ---------------------------------------------------------------- skeletons


def test_humanact12_parents_are_smpl():
    sk = get_skeleton("humanact12")
    assert sk.n_joints == 24
    assert sk.parents == SMPL_PARENTS
    assert sk.joint_names[0] == "pelvis" and sk.joint_names[15] == "head"
    assert sk.up_axis == "-y" and sk.up_index == 1 and sk.up_sign == -1.0
    assert sk.ground_axes == (0, 2)


def test_cmu20_parents():
    sk = get_skeleton("cmu20")
    assert sk.n_joints == 20
    assert sk.parents == CMU20_PARENTS
    assert sk.joint_names[3] == "head" and sk.joint_names[15] == "left_toe"
    assert sk.up_axis == "+y" and sk.up_index == 1 and sk.up_sign == 1.0


@pytest.mark.parametrize("name", sorted(SKELETONS))
def test_skeleton_is_a_tree(name):
    sk = get_skeleton(name)
    parents = sk.parents
    assert len(parents) == sk.n_joints == len(set(sk.joint_names))
    assert parents[0] == -1
    assert all(0 <= p < sk.n_joints for p in parents[1:]), f"{name}: joint without parent: {parents}"
    covered = {j for chain in sk.chains for j in chain}
    assert covered == set(range(sk.n_joints))
    # each chain starts at a joint already placed, and no joint is placed twice
    placed = {0}
    for chain in sk.chains:
        assert chain[0] in placed, f"{name}: chain {chain} starts at an unplaced joint"
        assert not placed & set(chain[1:]), f"{name}: chain {chain} re-parents a placed joint"
        placed |= set(chain)
    for j in range(sk.n_joints):  # walking up the parents reaches the root without a cycle
        seen, k = set(), j
        while k != 0:
            assert k not in seen
            seen.add(k)
            k = parents[k]
    assert len(sk.bones) == sk.n_joints - 1
    assert [j for _, j in sk.bones] == list(range(1, sk.n_joints))


def test_unknown_skeleton_is_user_error():
    with pytest.raises(UserError, match="unknown skeleton 'smplx'.*humanact12"):
        get_skeleton("smplx")


# -- rigid bones ------------------------------------------------------------------------------------------

def test_rigid_bones_keeps_a_rigid_motion_and_fixes_a_stretching_one():
    from odmo_cli.geometry.kinematics import bone_lengths
    from odmo_cli.geometry.lie import rigid_bones
    from odmo_cli.geometry.skeletons import get_skeleton

    parents = get_skeleton("humanact12").parents
    g = torch.Generator().manual_seed(0)
    rest = torch.randn(24, 3, generator=g) * 0.2
    rigid = rest.expand(2, 30, 24, 3).clone() + torch.linspace(0, 1, 30)[None, :, None, None]  # a body gliding
    assert torch.allclose(rigid_bones(rigid, parents), rigid, atol=1e-6)
    stretched = rigid.clone()
    stretched[:, :, 20] += torch.randn(2, 30, 3, generator=g) * 0.05  # a wrist that wanders
    fixed = rigid_bones(stretched, parents)
    lengths = bone_lengths(fixed, parents)  # (2, 30, 23)
    assert float((lengths.amax(1) - lengths.amin(1)).max()) < 1e-5
    assert torch.equal(fixed[..., 0, :], stretched[..., 0, :])  # the root stays
    # every bone keeps its direction
    child = [j for j, p in enumerate(parents) if p >= 0]
    d_in = stretched[..., child, :] - stretched[..., [parents[j] for j in child], :]
    d_out = fixed[..., child, :] - fixed[..., [parents[j] for j in child], :]
    assert torch.allclose(torch.nn.functional.cosine_similarity(d_in, d_out, dim=-1), torch.ones(2, 30, 23), atol=1e-5)


def test_rigid_bones_takes_given_lengths_and_has_finite_gradients():
    from odmo_cli.geometry.kinematics import bone_lengths
    from odmo_cli.geometry.lie import rigid_bones

    parents = (-1, 0, 1)
    motion = torch.tensor([[[0.0, 0, 0], [0, 2, 0], [0, 2, 3]]]).repeat(4, 1, 1).requires_grad_(True)  # (T, J, 3)
    out = rigid_bones(motion, parents, torch.tensor([0.0, 1.0, 0.5]))
    assert torch.allclose(out[0], torch.tensor([[0.0, 0, 0], [0, 1, 0], [0, 1, 0.5]]))
    out.sum().backward()
    assert torch.isfinite(motion.grad).all()
    assert torch.allclose(bone_lengths(out, parents), torch.tensor([1.0, 0.5]).expand(4, 2))


def test_rigid_bones_with_torso_branches_keeps_a_turning_rigid_body_and_stiffens_a_bending_torso():
    from odmo_cli.geometry.lie import rigid_bones, so3_exp, torso_branches
    from odmo_cli.geometry.skeletons import get_skeleton

    sk = get_skeleton("humanact12")
    branches = torso_branches(sk)
    assert branches == {0: (1, 2, 3), 9: (13, 14, 12)}
    g = torch.Generator().manual_seed(1)
    rest = torch.randn(24, 3, generator=g, dtype=torch.float64) * 0.2
    turn = so3_exp(torch.linspace(0, 2.0, 30, dtype=torch.float64)[:, None] * torch.tensor([0.0, 1.0, 0.3], dtype=torch.float64))
    turning = (turn[:, None] @ rest[None, :, :, None])[..., 0]  # (30, 24, 3): a rigid body turning
    assert torch.allclose(rigid_bones(turning, sk.parents, branches=branches), turning, atol=1e-9)
    bending = turning.clone()
    bending[:, 3] += torch.randn(30, 3, generator=g, dtype=torch.float64) * 0.03  # the spine wanders off the hips
    fixed = rigid_bones(bending, sk.parents, branches=branches)
    for a, b in ((1, 2), (1, 3), (2, 3), (12, 13), (13, 14)):  # distances inside each rigid piece stay fixed
        d = torch.linalg.vector_norm(fixed[:, a] - fixed[:, b], dim=-1)
        assert float(d.max() - d.min()) < 1e-9


def test_rigid_bones_takes_the_torso_pieces_of_another_motion_of_the_body():
    from odmo_cli.geometry.lie import rigid_bones, rigid_pieces, torso_branches
    from odmo_cli.geometry.skeletons import get_skeleton

    sk = get_skeleton("humanact12")
    branches = torso_branches(sk)
    g = torch.Generator().manual_seed(2)
    motion = torch.randn(2, 20, 24, 3, generator=g, dtype=torch.float64)  # (B, T, J, 3)
    pieces = rigid_pieces(motion, branches)
    assert set(pieces) == set(branches) and pieces[0].shape == (2, 1, 3, 3)
    own = rigid_bones(motion, sk.parents, branches=branches)
    assert torch.allclose(rigid_bones(motion, sk.parents, branches=branches, pieces=pieces), own, atol=1e-12)
    # another motion given these pieces: its pelvis piece is the first one's, wherever the body turns
    other = torch.randn(2, 20, 24, 3, generator=g, dtype=torch.float64)
    moved = rigid_bones(other, sk.parents, branches=branches, pieces=pieces)
    for a, b in ((1, 2), (1, 3), (2, 3)):
        assert torch.allclose(torch.linalg.vector_norm(moved[:, :, a] - moved[:, :, b], dim=-1),
                              torch.linalg.vector_norm(pieces[0][..., a - 1] - pieces[0][..., b - 1], dim=-1), atol=1e-9)
    assert not torch.allclose(moved, rigid_bones(other, sk.parents, branches=branches))
