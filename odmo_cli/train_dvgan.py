"""Training DVGAN with WGAN-GP (paper eq. 3 and §5.2): n_critic discriminator steps per
generator step, Adam for both, shifted discriminator inputs, exact resume, Ctrl-C safety.

An epoch is one pass of the discriminator over the training clips (random crops, shuffled);
the generator steps after every n_critic discriminator steps, counted across epochs. Checkpoints
follow odmo_cli.train: plain values and tensors only, written atomically.
"""

from __future__ import annotations

import copy
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from odmo_cli.data.dataset import MotionDataset, split_indices
from odmo_cli.data.readers import ClipSet
from odmo_cli.errors import TrainingError, UserError
from odmo_cli.io import load_checkpoint, save_checkpoint
from odmo_cli.models.dvgan import DVGAN, DVGANConfig, gradient_penalty, temporal_shift
from odmo_cli.train import (FORMAT_VERSION, TrainResult, _np_state, _np_state_from, crops_from_start, dataset_description,
                            resumed_config, seeded_start)


@dataclass
class DVGANTrainConfig:
    # the paper runs 20,000 generator iterations with n_critic 10; at batch 64 on HumanAct12
    # (1191 clips, 19 critic steps an epoch) that is about 10,500 epochs
    epochs: int = 10500
    batch_size: int = 64  # not given in the paper
    lr: float = 1e-4  # Adam, §5.2
    betas: tuple[float, float] = (0.0, 0.9)  # not given; WGAN-GP's own choice (DVGAN builds on it)
    n_critic: int = 10  # discriminator steps per generator step (§5.2)
    gp_lambda: float = 10.0  # eq. 3
    val_fraction: float = 0.0  # a GAN has no validation loss; a `split` column still holds out val/test
    checkpoint_every: int = 25  # epochs between checkpoints (and one at the end)
    seed: int = 0
    threads: int = 0  # torch intra-op threads; 0 leaves torch's default

    def __post_init__(self):
        self.betas = tuple(self.betas)
        if self.epochs <= 0 or self.batch_size <= 0 or self.n_critic <= 0:
            raise UserError(f"epochs, batch size and n_critic must be positive, got {self.epochs}, "
                            f"{self.batch_size} and {self.n_critic}")
        if self.lr <= 0:
            raise UserError(f"the learning rate must be positive, got {self.lr}")

    @classmethod
    def from_dict(cls, d: dict) -> "DVGANTrainConfig":
        known = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in known})

    def to_dict(self) -> dict:
        d = asdict(self)
        d["betas"] = list(self.betas)
        return d


def model_config_for(clips: ClipSet, generator: str = "cnn", overrides: dict | None = None) -> DVGANConfig:
    m = clips.manifest
    base = dict(n_joints=m.skeleton.n_joints, length=m.clip_length, actions=list(m.action_names),
                generator=generator)
    base.update(overrides or {})
    return DVGANConfig.from_dict(base)


class DVGANTrainer:
    """Holds the GAN, both optimizers, the RNGs and the data; `run` trains and checkpoints."""

    def __init__(self, clips: ClipSet, cfg: DVGANConfig, tc: DVGANTrainConfig, out: Path):
        self.clips, self.cfg, self.tc, self.out = clips, cfg, tc, Path(out)
        self.np_rng, self.torch_gen = seeded_start(tc)
        self.model = DVGAN(cfg)
        self.opt_g = torch.optim.Adam(self.model.generator_parameters(), lr=tc.lr, betas=tc.betas)
        self.opt_d = torch.optim.Adam(self.model.discriminator_parameters(), lr=tc.lr, betas=tc.betas)
        self.train_idx, _ = split_indices(clips, tc.val_fraction, tc.seed)
        if len(self.train_idx) < 2:
            raise UserError(f"need at least 2 training clips, have {len(self.train_idx)}")
        motions, _ = crops_from_start(clips, self.train_idx, cfg.length)  # (N, T, J, 3)
        self.model.set_stats(motions)
        self.data = MotionDataset(clips, cfg.length, rng=self.np_rng)
        self.epoch = 0
        self.d_steps = 0
        self.history: list[dict] = []
        self._snapshot: dict | None = None  # the state after the last completed epoch

    # -- checkpoints -------------------------------------------------------------------------
    def state(self) -> dict:
        return {
            "format_version": FORMAT_VERSION, "kind": "dvgan", "config": self.cfg.to_dict(),
            "train_config": self.tc.to_dict(), "dataset": dataset_description(self.clips),
            "state_dict": self.model.state_dict(), "optimizer_g": self.opt_g.state_dict(),
            "optimizer_d": self.opt_d.state_dict(), "epoch": self.epoch, "d_steps": self.d_steps,
            "history": self.history,
            "rng": {"numpy": _np_state(self.np_rng), "torch": self.torch_gen.get_state()},
            "split": {"train": torch.from_numpy(self.train_idx)},
        }

    def load_state(self, ckpt: dict) -> None:
        if ckpt.get("kind") != "dvgan":
            raise UserError(f"cannot resume: checkpoint is a {ckpt.get('kind')!r} model, not dvgan")
        if ckpt["dataset"] != dataset_description(self.clips):
            raise UserError(f"cannot resume: checkpoint was trained on {ckpt['dataset']['name']}, "
                            f"not {self.clips.manifest.name}")
        self.model.load_state_dict(ckpt["state_dict"])
        self.opt_g.load_state_dict(ckpt["optimizer_g"])
        self.opt_d.load_state_dict(ckpt["optimizer_d"])
        self.epoch, self.d_steps = int(ckpt["epoch"]), int(ckpt["d_steps"])
        self.history = list(ckpt["history"])
        self.np_rng.bit_generator.state = _np_state_from(ckpt["rng"]["numpy"])
        self.torch_gen.set_state(ckpt["rng"]["torch"])

    def save(self, state: dict | None = None) -> None:
        save_checkpoint(self.out, state or self.state())

    # -- the steps ---------------------------------------------------------------------------
    def _augment(self, x: torch.Tensor) -> torch.Tensor:
        return temporal_shift(x, self.torch_gen) if self.cfg.shift_augment else x

    def critic_step(self, real: torch.Tensor, labels: torch.Tensor) -> dict[str, float]:
        """One discriminator step on normalised real poses (B, T, F): minimise D(fake) - D(real) + GP."""
        model, gen = self.model, self.torch_gen
        with torch.no_grad():
            fake = model.fake(labels, gen)
        real, fake = self._augment(real), self._augment(fake)
        wasserstein = model.critic(real, labels).mean() - model.critic(fake, labels).mean()
        gp = gradient_penalty(lambda x: model.critic(x, labels), real, fake, gen, self.tc.gp_lambda)
        loss = -wasserstein + gp
        self._check(loss)
        self.opt_d.zero_grad(set_to_none=True)
        loss.backward()
        self.opt_d.step()
        return {"d_loss": float(loss.detach()), "wasserstein": float(wasserstein.detach()), "gp": float(gp.detach())}

    def generator_step(self, labels: torch.Tensor) -> float:
        """One generator step: minimise -D(G(z, S)) for the batch's actions."""
        fake = self._augment(self.model.fake(labels, self.torch_gen))
        loss = -self.model.critic(fake, labels).mean()
        self._check(loss)
        self.opt_g.zero_grad(set_to_none=True)
        loss.backward()
        self.opt_g.step()
        return float(loss.detach())

    def _check(self, loss: torch.Tensor) -> None:
        if not torch.isfinite(loss):
            raise TrainingError(f"non-finite loss at epoch {self.epoch + 1}; "
                                f"the last good checkpoint is kept at {self.out}")

    def train_epoch(self) -> dict:
        self.model.train()
        order = self.np_rng.permutation(self.train_idx)
        sums = {"d_loss": 0.0, "wasserstein": 0.0, "gp": 0.0}
        g_losses: list[float] = []
        start = time.perf_counter()
        n_batches = 0
        for b in range(0, len(order), self.tc.batch_size):
            motion, labels = self.data.batch(order[b:b + self.tc.batch_size])  # (B, T, J, 3), (B,)
            for k, v in self.critic_step(self.model.normalize(motion), labels).items():
                sums[k] += v
            n_batches += 1
            self.d_steps += 1
            if self.d_steps % self.tc.n_critic == 0:
                g_losses.append(self.generator_step(labels))
        self.epoch += 1
        seconds = time.perf_counter() - start
        log = {"epoch": self.epoch, "seconds": seconds, "clips_per_s": len(order) / seconds,
               **{k: v / n_batches for k, v in sums.items()}, "generator_steps": len(g_losses)}
        if g_losses:
            log["g_loss"] = float(np.mean(g_losses))
        return log

    def run(self, progress: Callable[[dict], None] | None = None) -> list[dict]:
        """Train up to tc.epochs. On Ctrl-C the last completed epoch is checkpointed, then re-raised."""
        try:
            while self.epoch < self.tc.epochs:
                log = self.train_epoch()
                self.history.append(log)
                # kept in memory so an interrupt mid-epoch saves a state that resumes exactly
                self._snapshot = copy.deepcopy(self.state())
                if (self.tc.checkpoint_every and log["epoch"] % self.tc.checkpoint_every == 0) \
                        or log["epoch"] == self.tc.epochs:
                    self.save(self._snapshot)
                if progress:
                    progress(log)
        except KeyboardInterrupt:
            if self._snapshot is not None:
                self.save(self._snapshot)
            raise
        return self.history


def train_dvgan(clips: ClipSet, tc: DVGANTrainConfig, out: Path, generator: str = "cnn",
                overrides: dict | None = None, resume: Path | None = None,
                progress: Callable[[dict], None] | None = None) -> TrainResult:
    """Train DVGAN on clips (or resume a checkpoint, keeping its model and schedule)."""
    if resume is not None:
        ckpt = load_checkpoint(resume)
        if ckpt.get("kind") != "dvgan":
            raise UserError(f"cannot resume: {resume} holds a {ckpt.get('kind')!r} model, not dvgan")
        cfg = DVGANConfig.from_dict(ckpt["config"])
        tc = resumed_config(ckpt["train_config"], tc)
        trainer = DVGANTrainer(clips, cfg, tc, out)
        trainer.load_state(ckpt)
    else:
        trainer = DVGANTrainer(clips, model_config_for(clips, generator, overrides), tc, out)
    first = trainer.epoch
    history = trainer.run(progress)
    if trainer.epoch == first:
        trainer.save()  # resumed at or past the asked length: nothing ran, but `out` is still written
    last = history[-1] if history else {}
    report = {"generator": trainer.cfg.generator, "epochs": trainer.epoch, "generator_steps": trainer.d_steps // tc.n_critic,
              **{k: last[k] for k in ("d_loss", "wasserstein", "gp", "g_loss") if k in last}}
    return TrainResult(Path(out), trainer.epoch, history, report)
