"""ODMO: LMP encoder, trajectory generator and motion generator (main paper §3.2, supplement
Table S2). Class conditioning is the outer product of the one-hot class and the code, flattened.

Shapes: B batch, T frames, J joints, D latent size, C classes; a pose is flattened to J*3.
"""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from odmo_cli.geometry.lie import rigid_bones, torso_branches
from odmo_cli.geometry.skeletons import SKELETONS
from odmo_cli.models.odmo_config import (BONES, CONS, POSE_FRAMES, POSE_LOSSES, PRESETS, ROOTS,  # noqa: F401
                                         ODMOConfig, preset_values)


def condition(onehot: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    """outer(c, z) flattened: (B, C), (B, D) -> (B, C*D)."""
    return (onehot[:, :, None] * z[:, None, :]).flatten(1)


class LMPEncoder(nn.Module):
    """LSTM over the LMP, FC-BN-PReLU x2, FC to (mu, logvar)."""

    def __init__(self, cfg: ODMOConfig):
        super().__init__()
        self.rnn = nn.LSTM(cfg.n_joints * 3, cfg.encoder_hidden, batch_first=True)
        h = cfg.encoder_fc
        self.fc = nn.Sequential(
            nn.Linear(cfg.encoder_hidden, h), nn.BatchNorm1d(h), nn.PReLU(),
            nn.Linear(h, h), nn.BatchNorm1d(h), nn.PReLU(),
            nn.Linear(h, 2 * cfg.latent_dim),
        )

    def forward(self, lmp: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        _, (h, _) = self.rnn(lmp.flatten(2))  # lmp (B, T, J, 3); h (1, B, H)
        mu, logvar = self.fc(h[-1]).chunk(2, dim=-1)  # (B, D) each
        return mu, logvar


class TrajectoryGenerator(nn.Module):
    """[outer(c, z), r_e] -> per-step root velocities (B, T, 3), without a Python loop over time."""

    def __init__(self, cfg: ODMOConfig):
        super().__init__()
        self.cfg = cfg
        d_in = cfg.n_classes * cfg.latent_dim + 3
        h = cfg.traj_hidden
        self.expand = nn.Linear(d_in, d_in * cfg.length)
        self.act_in = nn.PReLU()
        self.embed = nn.Linear(d_in, h)
        self.rnn = nn.LSTM(h, h, num_layers=2, batch_first=True)
        self.features = nn.Sequential(nn.Linear(h, h), nn.PReLU(), nn.Linear(h, h), nn.PReLU(),
                                      nn.Linear(h, h), nn.PReLU())
        self.out = nn.Linear(h, 3)

    def forward(self, cond: torch.Tensor, end_point: torch.Tensor) -> torch.Tensor:
        if not self.cfg.use_end_point:
            end_point = torch.zeros_like(end_point)
        x = torch.cat([cond, end_point], dim=-1)  # (B, C*D + 3)
        x = self.act_in(self.expand(x)).view(len(x), self.cfg.length, -1)  # (B, T, C*D + 3)
        y, _ = self.rnn(self.embed(x))  # (B, T, H)
        return self.out(self.features(y))  # (B, T, 3) velocities


class MotionGenerator(nn.Module):
    """Seq2seq: a trajectory encoder whose final state starts an autoregressive pose decoder.

    Each decoder step sees [previous pose, outer(c, z), t/T]. The parts of its input embedding
    that do not depend on the previous pose are computed once for all steps, and so are the
    teacher-forced inputs; both are unbound into per-step views once, because indexing a (B, T, H)
    tensor inside the loop makes every step's backward fill and add a full (B, T, H) gradient.
    The decoder is two LSTMCells: a 2-layer LSTM stepped one frame at a time.
    """

    def __init__(self, cfg: ODMOConfig):
        super().__init__()
        self.cfg = cfg
        h, p = cfg.motion_hidden, cfg.n_joints * 3
        self.traj_embed = nn.Linear(3, h)
        self.traj_act = nn.PReLU()
        self.traj_rnn = nn.LSTM(h, h, num_layers=2, batch_first=True)
        self.embed = nn.Linear(p + cfg.n_classes * cfg.latent_dim + 1, h)
        self.act = nn.PReLU()
        self.cell0 = nn.LSTMCell(h, h)
        self.cell1 = nn.LSTMCell(h, h)
        self.out = nn.Linear(h, p)

    def forward(self, trajectory: torch.Tensor, cond: torch.Tensor, target: torch.Tensor | None = None,
                teacher: torch.Tensor | None = None, keep: torch.Tensor | None = None) -> torch.Tensor:
        """trajectory (B, T, 3), cond (B, C*D) -> poses (B, T, J*3).

        teacher (T,) bool: at steps where it is True the previous pose fed in is target's (B, T, J*3);
        (B, T) bool: the same choice made for each clip and step.
        keep (2, B, H): multipliers of the two cells' outputs, the same at every step (variational
        dropout: 0 for a dropped unit, 1 / (1 - p) for a kept one); None keeps every unit as it is.
        """
        return self.unroll(self.prepare(trajectory, cond), target, teacher, keep)

    def prepare(self, trajectory: torch.Tensor, cond: torch.Tensor) -> tuple:
        """What every unroll of one (trajectory, cond) shares: the trajectory encoder's final state
        and the per-step inputs that do not depend on the previous pose. Computing it once for a
        teacher-forced and a free-running unroll saves most of the second decode (the sequence
        LSTMs cost more than the 2-cell step loop)."""
        return self.encode_path(trajectory), self.step_inputs(cond, trajectory.shape[1])

    def encode_path(self, trajectory: torch.Tensor) -> tuple:
        """trajectory (B, T, 3) -> the trajectory encoder's final state, ((h, c) of cell 0, (h, c) of cell 1),
        (B, H) each: the state the pose decoder starts from."""
        _, (h, c) = self.traj_rnn(self.traj_act(self.traj_embed(trajectory)))  # (2, B, H) each
        return (h[0], c[0]), (h[1], c[1])

    def step_inputs(self, cond: torch.Tensor, T: int) -> tuple:
        """The parts of the decoder's T step inputs that do not depend on the previous pose: cond (B, C*D)
        and step t's share t/T of the window -> T x (B, H)."""
        w_rest = self.embed.weight[:, self.cfg.n_joints * 3:]
        t_frac = torch.arange(1, T + 1, dtype=cond.dtype, device=cond.device) / T  # (T,)
        fixed = F.linear(cond, w_rest[:, :-1], self.embed.bias)  # (B, H)
        return (fixed[:, None, :] + t_frac[None, :, None] * w_rest[:, -1]).unbind(1)  # T x (B, H)

    def unroll(self, prepared: tuple, target: torch.Tensor | None = None,
               teacher: torch.Tensor | None = None, keep: torch.Tensor | None = None) -> torch.Tensor:
        """The autoregressive pose decoder from `prepare`'s output -> poses (B, T, J*3); teacher and
        keep as in forward."""
        (s0, s1), fixed = prepared
        state = [s0, s1]
        B, T, p = len(fixed[0]), len(fixed), self.cfg.n_joints * 3
        w_prev = self.embed.weight[:, :p]
        if target is not None and teacher is not None and bool(teacher.any()):
            prev_real = torch.cat([torch.zeros_like(target[:, :1]), target[:, :-1]], dim=1)  # (B, T, P)
            real_part = F.linear(prev_real, w_prev).unbind(1)  # T x (B, H): all teacher-forced inputs
        else:
            teacher = None
        prev = fixed[0].new_zeros(B, p)
        outputs = []
        for t in range(T):
            if teacher is not None and teacher.dim() == 2:
                x = torch.where(teacher[:, t, None], real_part[t], F.linear(prev, w_prev)) + fixed[t]
            elif teacher is not None and teacher[t]:
                x = real_part[t] + fixed[t]
            else:
                x = F.linear(prev, w_prev) + fixed[t]
            state[0] = self.cell0(self.act(x), state[0])
            # dropout masks what each cell passes on, not its own recurrent state
            state[1] = self.cell1(state[0][0] if keep is None else state[0][0] * keep[0], state[1])
            prev = self.out(state[1][0] if keep is None else state[1][0] * keep[1])  # (B, P)
            outputs.append(prev)
        return torch.stack(outputs, dim=1)  # (B, T, P)


def read_out(motion: torch.Tensor, trajectory: torch.Tensor, cfg: ODMOConfig) -> torch.Tensor:
    """The pose decoder's motion (B, T, J, 3) as a model outputs it: its root as cfg.root says (on the
    trajectory (B, T, 3), or on its path at the decoder's own height), its bones as cfg.bones says."""
    if cfg.root != "decoder":
        root = trajectory[:, :, None]  # (B, T, 1, 3)
        if cfg.root == "ground":  # the decoder's own height over the path on the ground plane
            up = cfg.up_axis
            root = torch.cat([root[..., :up], motion[:, :, :1, up:up + 1], root[..., up + 1:]], dim=-1)
        motion = motion - motion[:, :, :1] + root  # the same body about its root, on T-hat
    if cfg.bones == "rigid" and cfg.skeleton:
        skeleton = SKELETONS[cfg.skeleton]
        motion = rigid_bones(motion, skeleton.parents, branches=torso_branches(skeleton))
    return motion


class ODMO(nn.Module):
    def __init__(self, cfg: ODMOConfig):
        super().__init__()
        self.cfg = cfg
        self.encoder = LMPEncoder(cfg)
        self.trajectory = TrajectoryGenerator(cfg)
        self.motion = MotionGenerator(cfg)

    def encode(self, motion: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Motion (B, T, J, 3) -> (mu, logvar) of its LMP, (B, D) each."""
        lmp = motion - motion[:, :, :1]
        return self.encoder(lmp)

    def decode(self, z: torch.Tensor, labels: torch.Tensor, end_point: torch.Tensor,
               target: torch.Tensor | None = None, teacher: torch.Tensor | None = None
               ) -> tuple[torch.Tensor, torch.Tensor]:
        """Code (B, D), labels (B,), end point (B, 3) -> (trajectory (B, T, 3), motion (B, T, J, 3)),
        the motion's root as cfg.root says, its bones as cfg.bones says."""
        trajectory, prepared = self._plan(z, labels, end_point)
        return trajectory, read_out(self.poses(prepared, trajectory, target, teacher), trajectory, self.cfg)

    def _plan(self, z: torch.Tensor, labels: torch.Tensor, end_point: torch.Tensor) -> tuple[torch.Tensor, tuple]:
        """The trajectory (B, T, 3) and what the pose decoder's unrolls of it share."""
        onehot = F.one_hot(labels, self.cfg.n_classes).to(z.dtype)
        cond = condition(onehot, z)
        trajectory = torch.cumsum(self.trajectory(cond, end_point), dim=1)  # r_t = sum of v, r_0 = 0
        return trajectory, self.motion.prepare(trajectory, cond)

    def poses(self, prepared: tuple, trajectory: torch.Tensor, target: torch.Tensor | None = None,
               teacher: torch.Tensor | None = None, keep: torch.Tensor | None = None) -> torch.Tensor:
        """The pose decoder's motion (B, T, J, 3) in the dataset's frame; teacher-forced from target,
        its units dropped as `keep` says (MotionGenerator.forward)."""
        origin = trajectory[:, :, None] if self.cfg.pose_frame == "path" else None  # (B, T, 1, 3)
        if target is not None and origin is not None:
            # the previous pose as the decoder would have drawn it; the path is not detached, here or
            # in the output, so the pose losses reach the trajectory generator through both
            target = target - origin
        flat_target = target.flatten(2) if target is not None else None
        motion = self.motion.unroll(prepared, flat_target, teacher, keep)
        motion = motion.view(*motion.shape[:2], self.cfg.n_joints, 3)
        return motion if origin is None else motion + origin

    def forward(self, motion: torch.Tensor, labels: torch.Tensor, generator: torch.Generator | None = None,
                teacher: torch.Tensor | None = None, eps: torch.Tensor | None = None,
                free: bool = False, keep: torch.Tensor | None = None,
                mix: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Reconstruct a batch: encode its LMP, sample z (noise `eps` (B, D), else drawn from
        `generator`), decode with the real end point; with `free`, also without teacher forcing
        ("free_motion"). keep (2, B, H): the pose decoder's dropout (MotionGenerator.forward), the
        same units in both decodes. mix (B/2,): for the pairs of rows k and B/2 + k of one action,
        also the free-running decode of mix z_k + (1 - mix) z_{B/2+k} ("mix_motion" on its path
        "mix_trajectory", those pairs' rows "mix_rows", "mix_lam": mix), the end points mixed alike, without dropout."""
        mu, logvar = self.encode(motion)
        if eps is None:
            eps = torch.randn(mu.shape, generator=generator, dtype=mu.dtype, device=mu.device)
        z = mu + eps * torch.exp(0.5 * logvar)
        trajectory, prepared = self._plan(z, labels, motion[:, -1, 0])
        out = {"mu": mu, "logvar": logvar, "z": z, "trajectory": trajectory,
               "motion": self.poses(prepared, trajectory, motion, teacher, keep)}
        if free:  # the same trajectory, decoded again without teacher forcing
            forced = teacher is not None and bool(teacher.any())
            # with no step forced the first decode is already the free-running one: the same
            # values and gradients, at half the cost of decoding it twice
            out["free_motion"] = self.poses(prepared, trajectory, keep=keep) if forced else out["motion"]
        if mix is not None:
            half = len(motion) // 2
            rows = torch.nonzero(labels[:half] == labels[half:2 * half]).flatten()
            if len(rows) == 0:  # no pair of one action in this batch: nothing to mix
                return out
            w = mix[rows, None]  # (M, 1)
            zm = w * z[rows] + (1 - w) * z[half + rows]
            end = w * motion[rows, -1, 0] + (1 - w) * motion[half + rows, -1, 0]
            mix_traj, mix_prepared = self._plan(zm, labels[rows], end)
            out.update(mix_motion=self.poses(mix_prepared, mix_traj), mix_trajectory=mix_traj, mix_rows=rows, mix_lam=mix)
        return out


def widen_pose_decoder(state: dict[str, torch.Tensor], fresh: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """`state` (an ODMO state dict) in a model whose pose decoder has more hidden units, the same
    function: `fresh` is the wider model's own (initialised) state dict.

    The old units keep their weights; the new ones keep `fresh`'s incoming weights and biases, and
    every weight from a new unit into an old unit or into the output starts at zero, so the wider
    decoder draws exactly what the narrow one drew and training grows the new units from there
    (their outgoing weights have gradients at once). Applies to `motion.*` (MotionGenerator: its
    trajectory LSTM and its two LSTM cells, whose rows are the i, f, g, o gates of H units each).
    """
    h = state["motion.out.weight"].shape[1]
    h2 = fresh["motion.out.weight"].shape[1]
    if h2 < h:
        raise ValueError(f"the pose decoder can only be widened: {h} hidden units, asked {h2}")
    out = {}
    for k, new in fresh.items():
        old = state[k]
        if not k.startswith("motion.") or old.shape == new.shape:
            out[k] = old
            continue
        w = new.clone()
        if k == "motion.out.weight":  # (P, H): zero from the new units
            w[:, :h], w[:, h:] = old, 0
        elif k.startswith(("motion.embed.", "motion.traj_embed.")):  # rows are units
            w[:h] = old
        else:  # LSTM weights (4 H2, H2 or input) and biases (4 H2): the old units' gate rows
            for g in range(4):
                rows = slice(g * h2, g * h2 + h)
                if w.dim() == 2:
                    w[rows] = 0
                    w[rows, :old.shape[1]] = old[g * h:(g + 1) * h]
                else:
                    w[rows] = old[g * h:(g + 1) * h]
        out[k] = w
    return out
