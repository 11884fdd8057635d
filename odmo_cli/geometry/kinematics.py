"""Pure kinematics functions on joint positions.

ODMO (§3.1) splits a motion M (T, J, 3) into its trajectory r_t = m_t[0] (the root) and its
local movement profile (LMP) p_t = m_t - r_t. Functions accept numpy arrays or torch tensors
and any leading batch dimensions: (..., T, J, 3).
"""

from __future__ import annotations

from typing import Sequence, TypeVar

import numpy as np
import torch

from odmo_cli.errors import UserError

Array = TypeVar("Array", np.ndarray, torch.Tensor)


def check_motion(motion: Array, n_joints: int | None = None, name: str = "motion") -> None:
    """Raise UserError unless `motion` is (..., T, J, 3) with T >= 1 (and J == n_joints if given)."""
    shape = tuple(motion.shape)
    if len(shape) < 3 or shape[-1] != 3 or shape[-3] < 1:
        raise UserError(f"{name} must have shape (..., T, J, 3), got {shape}")
    if n_joints is not None and shape[-2] != n_joints:
        raise UserError(f"{name} has {shape[-2]} joints, the skeleton has {n_joints}")


def split_lmp(motion: Array) -> tuple[Array, Array]:
    """Motion (..., T, J, 3) -> (LMP (..., T, J, 3), trajectory (..., T, 3)).

    The LMP's root joint is zero by construction.
    """
    check_motion(motion)
    trajectory = motion[..., 0, :]  # (..., T, 3)
    lmp = motion - trajectory[..., None, :]
    return lmp, trajectory


def join_lmp(lmp: Array, trajectory: Array) -> Array:
    """Inverse of `split_lmp`: LMP (..., T, J, 3) + trajectory (..., T, 3) -> motion (..., T, J, 3)."""
    check_motion(lmp, name="LMP")
    if tuple(trajectory.shape) != tuple(lmp.shape[:-2]) + (3,):
        raise UserError(
            f"trajectory shape {tuple(trajectory.shape)} does not match LMP shape {tuple(lmp.shape)}"
        )
    return lmp + trajectory[..., None, :]


def root_velocities(trajectory: Array) -> Array:
    """Trajectory (..., T, 3) -> per-step velocities v_t = r_t - r_{t-1} with r_0 = 0 (ODMO eq. 2)."""
    if isinstance(trajectory, torch.Tensor):
        prev = torch.cat([torch.zeros_like(trajectory[..., :1, :]), trajectory[..., :-1, :]], dim=-2)
    else:
        prev = np.concatenate([np.zeros_like(trajectory[..., :1, :]), trajectory[..., :-1, :]], axis=-2)
    return trajectory - prev


def bone_lengths(motion: Array, parents: Sequence[int]) -> Array:
    """Per-frame bone lengths: (..., T, J, 3) -> (..., T, J-1), one per non-root joint in joint order."""
    check_motion(motion, n_joints=len(parents))
    children = [j for j, p in enumerate(parents) if p >= 0]
    parent_idx = [parents[j] for j in children]
    diff = motion[..., children, :] - motion[..., parent_idx, :]
    if isinstance(diff, torch.Tensor):
        return torch.linalg.vector_norm(diff, dim=-1)
    return np.linalg.norm(diff, axis=-1)

