"""Action2Motion (Guo et al., ACM MM 2020, §3.2 and appendix A): a conditional temporal VAE.

At every frame t a posterior network q(z_t | p_1:t, a, c_t) and a learned prior
p(z_t | p_1:t-1, a, c_t) (one GRU cell each) give Gaussians over a 30-d noise z_t; a two-layer
GRU generator turns (p_t-1, a, c_t, z_t) into the next pose. a is the one-hot action and
c_t = t / T the time counter (eqs. 7-8). Training minimises eq. (9): the squared error between
generated and real joint positions plus lambda times KL(posterior || prior), both summed over t.
Sampling draws z_t from the prior and feeds each generated pose back in.

The pose vector p_t has D = 3J numbers in both representations (Table 3: 72 for HumanAct12):
  * xyz: the J joint positions ("ours w/o Lie").
  * lie: root translation (3) and the so(3) parameters of the J-1 bones (`odmo_cli.geometry.lie`). The
    body orientation is folded into the bones leaving the root, so the root frame is the
    identity, as in the paper's 3 + 69 numbers. Positions come from forward kinematics (eq. 4)
    with the clip's own bone lengths when training and, when sampling, one of a small bank of
    real bone-length sets kept in the model (`bone_bank`), so sampling never needs the data.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F

from odmo_cli.config import Config, ConfigError
from odmo_cli.errors import UserError
from odmo_cli.geometry.lie import (bone_lengths_from_pose, forward_kinematics, inverse_kinematics, rest_directions,
                          so3_exp, so3_log)
from odmo_cli.geometry.skeletons import get_skeleton

REPRESENTATIONS = ("xyz", "lie")
PAPER_LAMBDA_KL = {"humanact12": 0.01}  # A.2; CMU MoCap and NTU use 0.1


def paper_lambda_kl(dataset: str) -> float:
    return PAPER_LAMBDA_KL.get(dataset, 0.1)


@dataclass
class A2MConfig(Config):
    n_joints: int = 24
    n_classes: int = 12
    length: int = 60  # T (A.2: 60 HumanAct12 and NTU, 100 CMU)
    skeleton: str = "humanact12"
    representation: str = "lie"
    hidden: int = 128  # every encoder output and GRU (A.2)
    z_dim: int = 30
    gen_layers: int = 2  # the generator's GRU; posterior and prior have one layer
    bank_size: int = 16  # real bone-length sets kept for sampling

    def __post_init__(self):
        if self.representation not in REPRESENTATIONS:
            raise ConfigError("representation", f"must be one of {', '.join(REPRESENTATIONS)}, got {self.representation!r}")
        if min(self.n_joints, self.n_classes, self.length, self.hidden, self.z_dim, self.gen_layers,
               self.bank_size) <= 0:
            raise UserError("A2M config sizes must be positive")

    @property
    def pose_dim(self) -> int:
        return 3 * self.n_joints




class GaussianGRU(nn.Module):
    """Posterior or prior network (Table 3): linear encoder, one GRU cell, mean and log-variance."""

    def __init__(self, n_in: int, cfg: A2MConfig):
        super().__init__()
        self.encoder = nn.Linear(n_in, cfg.hidden)
        self.gru = nn.ModuleList([nn.GRUCell(cfg.hidden, cfg.hidden)])
        self.mu_net = nn.Linear(cfg.hidden, cfg.z_dim)
        self.logvar_net = nn.Linear(cfg.hidden, cfg.z_dim)

    def forward(self, x: torch.Tensor, h: torch.Tensor):
        h = self.gru[0](self.encoder(x), h)  # (B, H)
        return self.mu_net(h), self.logvar_net(h), h


class Generator(nn.Module):
    """Linear encoder, stacked GRU cells, linear decoder to the pose vector (Table 3).

    With Lie output the bone parameters pass through one more linear layer (`Lie_output`).
    """

    def __init__(self, n_in: int, cfg: A2MConfig):
        super().__init__()
        self.encoder = nn.Linear(n_in, cfg.hidden)
        self.gru = nn.ModuleList([nn.GRUCell(cfg.hidden, cfg.hidden) for _ in range(cfg.gen_layers)])
        self.decoder = nn.Linear(cfg.hidden, cfg.pose_dim)
        lie = cfg.representation == "lie"
        self.lie_output = nn.Linear(cfg.pose_dim - 3, cfg.pose_dim - 3) if lie else None

    def forward(self, x: torch.Tensor, hs: list[torch.Tensor]):
        h, new = self.encoder(x), []
        for cell, h_prev in zip(self.gru, hs):
            h = cell(h, h_prev)
            new.append(h)
        out = self.decoder(h)  # (B, D)
        if self.lie_output is not None:
            out = torch.cat([out[:, :3], self.lie_output(out[:, 3:])], 1)
        return out, new


def gaussian_kl(mu_q, logvar_q, mu_p, logvar_p) -> torch.Tensor:
    """KL(N(mu_q, var_q) || N(mu_p, var_p)) per dimension."""
    return 0.5 * (logvar_p - logvar_q + (logvar_q.exp() + (mu_q - mu_p) ** 2) / logvar_p.exp() - 1)


class A2M(nn.Module):
    def __init__(self, cfg: A2MConfig):
        super().__init__()
        self.cfg = cfg
        self.sk = get_skeleton(cfg.skeleton)
        if self.sk.n_joints != cfg.n_joints:
            raise UserError(f"skeleton {cfg.skeleton!r} has {self.sk.n_joints} joints, the config {cfg.n_joints}")
        n_cond = cfg.n_classes + 1  # one-hot action and time counter
        self.posterior = GaussianGRU(cfg.pose_dim + n_cond, cfg)
        self.prior = GaussianGRU(cfg.pose_dim + n_cond, cfg)
        self.generator = Generator(cfg.pose_dim + n_cond + cfg.z_dim, cfg)
        self.register_buffer("bone_bank", torch.zeros(cfg.bank_size, cfg.n_joints))  # (K, J) real bone lengths
        self.register_buffer("rest_dirs", rest_directions(self.sk, dtype=torch.float32), persistent=False)

    # -- representations -------------------------------------------------------------------
    def pose_vectors(self, motion: torch.Tensor) -> torch.Tensor:
        """Joint positions (B, T, J, 3) -> pose vectors (B, T, D)."""
        B, T = motion.shape[:2]
        if self.cfg.representation == "xyz":
            return motion.reshape(B, T, -1)
        root, lie = inverse_kinematics(motion, self.sk, self.rest_dirs)  # (B, T, 3), (B, T, J, 3)
        lie = fold_root(lie, self.sk.parents)
        return torch.cat([root, lie[:, :, 1:].reshape(B, T, -1)], -1)

    def positions(self, poses: torch.Tensor, bone_lengths: torch.Tensor) -> torch.Tensor:
        """Pose vectors (B, T, D) -> joint positions (B, T, J, 3); lengths (B, J) or (B, T, J), lie only."""
        B, T = poses.shape[:2]
        if self.cfg.representation == "xyz":
            return poses.reshape(B, T, self.cfg.n_joints, 3)
        lie = torch.cat([poses.new_zeros(B, T, 1, 3), poses[..., 3:].reshape(B, T, -1, 3)], 2)  # root frame = I
        return forward_kinematics(poses[..., :3], lie, bone_lengths, self.sk, self.rest_dirs)

    # -- the recurrence --------------------------------------------------------------------
    def _condition(self, labels: torch.Tensor, t: int) -> torch.Tensor:
        onehot = F.one_hot(labels, self.cfg.n_classes).float()  # (B, C)
        counter = onehot.new_full((len(labels), 1), (t + 1) / self.cfg.length)  # c_t = t / T, t = 1..T
        return torch.cat([onehot, counter], 1)

    def _start(self, n: int, device: torch.device):
        zeros = torch.zeros(n, self.cfg.hidden, device=device)
        # p_0 is a zero vector (§3.2.3)
        return torch.zeros(n, self.cfg.pose_dim, device=device), zeros, zeros, [zeros] * self.cfg.gen_layers

    def forward(self, poses: torch.Tensor, labels: torch.Tensor, teacher: torch.Tensor,
                generator: torch.Generator | None = None, noise: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Training pass, eq. (7)-(8): poses (B, T, D), labels (B,), teacher (B,) bool; the
        posterior's noise is `noise` (T, B, Z) if given, else drawn from `generator` step by step.

        A teacher-forced sequence feeds the real p_t-1 to prior and generator, the others their
        own previous output (the paper's choice per sequence, not per frame).
        """
        B, T, _ = poses.shape
        prev, h_q, h_p, h_g = self._start(B, poses.device)
        preds, kls = [], []
        for t in range(T):
            cond = self._condition(labels, t)
            mu_q, logvar_q, h_q = self.posterior(torch.cat([poses[:, t], cond], 1), h_q)
            mu_p, logvar_p, h_p = self.prior(torch.cat([prev, cond], 1), h_p)
            eps = noise[t] if noise is not None else torch.randn(mu_q.shape, generator=generator, device=mu_q.device)
            z = mu_q + (0.5 * logvar_q).exp() * eps
            pred, h_g = self.generator(torch.cat([prev, cond, z], 1), h_g)  # (B, D)
            prev = torch.where(teacher[:, None], poses[:, t], pred)
            preds.append(pred)
            kls.append(gaussian_kl(mu_q, logvar_q, mu_p, logvar_p).sum(-1))  # (B,)
        return {"poses": torch.stack(preds, 1), "kl": torch.stack(kls, 1)}  # (B, T, D), (B, T)

    @torch.no_grad()
    def generate(self, labels: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """Labels (N,) -> motions (N, T, J, 3), z_t from the learned prior, first root at the origin."""
        n, dev = len(labels), labels.device
        bones = self.bone_bank[torch.randint(len(self.bone_bank), (n,), generator=generator, device=dev)]  # (N, J)
        prev, _, h_p, h_g = self._start(n, dev)
        preds = []
        for t in range(self.cfg.length):
            cond = self._condition(labels, t)
            mu_p, logvar_p, h_p = self.prior(torch.cat([prev, cond], 1), h_p)
            z = mu_p + (0.5 * logvar_p).exp() * torch.randn(mu_p.shape, generator=generator, device=dev)
            prev, h_g = self.generator(torch.cat([prev, cond, z], 1), h_g)
            preds.append(prev)
        motion = self.positions(torch.stack(preds, 1), bones)  # (N, T, J, 3)
        return motion - motion[:, :1, :1]


def fold_root(lie: torch.Tensor, parents) -> torch.Tensor:
    """Lie parameters (..., J, 3) with the root rotation moved into the bones below the root.

    G_c = exp(w_0) exp(w_c) for a child c of the root, so w_c' = log(exp(w_0) exp(w_c)) and
    w_0' = 0 give the same forward kinematics.
    """
    root = so3_exp(lie[..., 0, :])  # (..., 3, 3)
    out = lie.clone()
    for c, p in enumerate(parents):
        if c > 0 and p == 0:
            out[..., c, :] = so3_log(root @ so3_exp(lie[..., c, :]))
    out[..., 0, :] = 0
    return out


def a2m_terms(model: A2M, motion: torch.Tensor, labels: torch.Tensor, teacher: torch.Tensor,
              lambda_kl: float, generator: torch.Generator | None = None, noise: torch.Tensor | None = None,
              net: torch.nn.Module | None = None) -> dict[str, torch.Tensor]:
    """Eq. (9) on a batch of real motions (B, T, J, 3); the forward pass runs through `net` (the
    model wrapped for several processes) when given, with the noise of A2M.forward.

    mse: squared joint-position error per coordinate, kl: KL per clip; both per frame. loss
    sums them over the T frames as the paper does: T * (mse + lambda * kl).
    """
    out = (net or model)(model.pose_vectors(motion), labels, teacher, generator, noise)
    lengths = bone_lengths_from_pose(motion, model.sk)  # (B, T, J): FK then reproduces the real bones
    recon = model.positions(out["poses"], lengths)
    mse = ((recon - motion) ** 2).mean()
    kl = out["kl"].mean()
    return {"mse": mse, "kl": kl, "loss": motion.shape[1] * (mse + lambda_kl * kl)}


def model_from_checkpoint(ckpt: dict) -> A2M:
    """The generator interface of `odmo_cli.generate` (BASELINES)."""
    if ckpt.get("kind") != "a2m":
        raise UserError(f"not an Action2Motion checkpoint (kind {ckpt.get('kind')!r})")
    model = A2M(A2MConfig.from_saved(ckpt["config"]))
    model.load_state_dict(ckpt["state_dict"])
    return model
