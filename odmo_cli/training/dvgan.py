"""Training DVGAN with WGAN-GP (paper eq. 3 and §5.2) on the shared loop: n_critic discriminator
steps per generator step, Adam for both, shifted discriminator inputs.

An epoch is one pass of the discriminator over the training clips (random crops, shuffled); the
generator steps after every n_critic discriminator steps, counted across epochs (`d_steps`, kept
in the checkpoint).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from odmo_cli.data.dataset import MotionDataset, crops_from_start
from odmo_cli.data.readers import ClipSet
from odmo_cli.errors import UserError
from odmo_cli.models.dvgan import DVGAN, DVGANConfig, gradient_penalty, temporal_shift
from odmo_cli.parallel import thread_count
from odmo_cli.training.loop import LoopConfig, Progress, Trainer, TrainResult, dataset_shapes


@dataclass
class DVGANTrainConfig(LoopConfig):
    # the paper runs 20,000 generator iterations with n_critic 10; at batch 64 on HumanAct12
    # (1191 clips, 19 critic steps an epoch) that is about 10,500 epochs
    epochs: int = 10500
    batch_size: int = 64  # not given in the paper
    lr: float = 1e-4  # Adam, §5.2; constant (lr_final 0)
    val_fraction: float = 0.0  # a GAN has no validation loss; a `split` column still holds out val/test
    val_every: int = 0
    betas: tuple[float, float] = (0.0, 0.9)  # not given; WGAN-GP's own choice (DVGAN builds on it)
    n_critic: int = 10  # discriminator steps per generator step (§5.2)
    gp_lambda: float = 10.0  # eq. 3

    def __post_init__(self):
        self.betas = tuple(self.betas)
        if self.epochs <= 0 or self.batch_size <= 0 or self.n_critic <= 0:
            raise UserError(f"epochs, batch size and n_critic must be positive, got {self.epochs}, "
                            f"{self.batch_size} and {self.n_critic}")
        if self.lr <= 0:
            raise UserError(f"the learning rate must be positive, got {self.lr}")
        super().__post_init__()


def model_config_for(clips: ClipSet, generator: str = "cnn", overrides: dict | None = None) -> DVGANConfig:
    return DVGANConfig.from_dict({**dataset_shapes(clips), "generator": generator, **(overrides or {})})


class DVGANTrainer(Trainer):
    kind = "dvgan"
    config_class = DVGANConfig
    model_class = DVGAN

    def build_optimizers(self) -> dict:
        tc = self.tc
        return {"optimizer_g": torch.optim.Adam(self.model.generator_parameters(), lr=tc.lr, betas=tc.betas),
                "optimizer_d": torch.optim.Adam(self.model.discriminator_parameters(), lr=tc.lr, betas=tc.betas)}

    def setup(self) -> None:
        motions, _ = crops_from_start(self.clips, self.train_idx, self.cfg.length)  # (N, T, J, 3)
        self.model.set_stats(motions)
        self.data = MotionDataset(self.clips, self.cfg.length, rng=self.np_rng)
        self.d_steps = 0

    def extra_state(self) -> dict:
        return {"d_steps": self.d_steps}

    def load_extra_state(self, ckpt: dict) -> None:
        self.d_steps = int(ckpt["d_steps"])

    def _augment(self, x: torch.Tensor) -> torch.Tensor:
        return temporal_shift(x, self.torch_gen) if self.cfg.shift_augment else x

    def critic_step(self, real: torch.Tensor, labels: torch.Tensor) -> dict[str, float]:
        """One discriminator step on normalised real poses (B, T, F): minimise D(fake) - D(real) + GP."""
        model, gen, opt = self.model, self.torch_gen, self.optimizers["optimizer_d"]
        with torch.no_grad():
            fake = model.fake(labels, gen)
        real, fake = self._augment(real), self._augment(fake)
        wasserstein = model.critic(real, labels).mean() - model.critic(fake, labels).mean()
        gp = gradient_penalty(lambda x: model.critic(x, labels), real, fake, gen, self.tc.gp_lambda)
        loss = -wasserstein + gp
        self.check_finite(loss)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        return {"d_loss": float(loss.detach()), "wasserstein": float(wasserstein.detach()), "gp": float(gp.detach())}

    def generator_step(self, labels: torch.Tensor) -> float:
        """One generator step: minimise -D(G(z, S)) for the batch's actions."""
        opt = self.optimizers["optimizer_g"]
        fake = self._augment(self.model.fake(labels, self.torch_gen))
        loss = -self.model.critic(fake, labels).mean()
        self.check_finite(loss)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        return float(loss.detach())

    def train_epoch(self) -> dict[str, float]:
        self.model.train()
        order = self.np_rng.permutation(self.train_idx)
        sums = {"d_loss": 0.0, "wasserstein": 0.0, "gp": 0.0}
        g_losses: list[float] = []
        n_batches = 0
        for b in range(0, len(order), self.tc.batch_size):
            motion, labels = self.data.batch(order[b:b + self.tc.batch_size])  # (B, T, J, 3), (B,)
            for k, v in self.critic_step(self.model.normalize(motion), labels).items():
                sums[k] += v
            n_batches += 1
            self.d_steps += 1
            if self.d_steps % self.tc.n_critic == 0:
                g_losses.append(self.generator_step(labels))
        log = {"clips": len(order), **{k: v / n_batches for k, v in sums.items()}, "generator_steps": len(g_losses)}
        if g_losses:
            log["g_loss"] = float(np.mean(g_losses))
        return log


def train_dvgan(clips: ClipSet, tc: DVGANTrainConfig, out: Path, generator: str = "cnn",
                overrides: dict | None = None, resume: Path | None = None,
                progress: Progress | None = None) -> TrainResult:
    """Train DVGAN on clips (or resume a checkpoint, keeping its model and schedule)."""
    with thread_count(tc.threads):
        if resume is not None:
            trainer = DVGANTrainer.resumed(resume, clips, tc, out)
        else:
            trainer = DVGANTrainer(clips, model_config_for(clips, generator, overrides), tc, out)
        first = trainer.epoch
        history = trainer.run(progress)
        if trainer.epoch == first:
            trainer.save()  # resumed at or past the asked length: nothing ran, but `out` is still written
    last = history[-1] if history else {}
    report = {"generator": trainer.cfg.generator, "epochs": trainer.epoch,
              "generator_steps": trainer.d_steps // trainer.tc.n_critic,
              **{k: last[k] for k in ("d_loss", "wasserstein", "gp", "g_loss") if k in last}}
    return TrainResult(Path(out), trainer.epoch, history, report)
