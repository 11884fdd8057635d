"""Training DVGAN with WGAN-GP (paper eq. 3 and §5.2) on the shared loop: n_critic discriminator
steps per generator step, Adam for both, shifted discriminator inputs.

An epoch is one pass of the discriminator over the training clips (random crops, shuffled); the
generator steps after every n_critic discriminator steps, counted across epochs (`d_steps`, kept
in the checkpoint).

On several processes the ranks share each step's real clips as the other trainers do, and average
their gradients with one all_reduce after each backward pass (Group.average_gradients), not
through DistributedDataParallel: the two networks step in turn with their own optimizers, outside
forward(), and the gradient penalty differentiates through torch.autograd.grad, which DDP does not
support. The generator's noise is each rank's own (a stream seeded by seed, epoch and rank), so a
run on N processes is a valid DVGAN run but not the single-process run's numbers.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from odmo_cli.data.dataset import MotionDataset, crops_from_start
from odmo_cli.data.readers import ClipSet
from odmo_cli.device import generator as seeded_generator
from odmo_cli.models.dvgan import DVGAN, DVGANConfig, gradient_penalty, temporal_shift
from odmo_cli.parallel import thread_count
from odmo_cli.training.configs import DVGANTrainConfig
from odmo_cli.training.distributed import training_group
from odmo_cli.training.loop import Progress, Trainer, TrainResult, dataset_shapes


def model_config_for(clips: ClipSet, generator: str = "cnn", overrides: dict | None = None) -> DVGANConfig:
    return DVGANConfig.from_dict({**dataset_shapes(clips, DVGANConfig), "generator": generator, **(overrides or {})})


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
        self.model.set_stats(motions.to(self.device))
        self.data = MotionDataset(self.clips, self.cfg.length, rng=self.np_rng)
        self.d_steps = 0
        self.noise_gen = self.torch_gen  # one process: the trainer's stream; several: see train_epoch
        self.weight = 1.0  # this rank's share of the batch (Group.share)

    def extra_state(self) -> dict:
        return {"d_steps": self.d_steps}

    def load_extra_state(self, ckpt: dict) -> None:
        self.d_steps = int(ckpt["d_steps"])

    def _augment(self, x: torch.Tensor) -> torch.Tensor:
        return temporal_shift(x, self.noise_gen) if self.cfg.shift_augment else x

    def _step(self, loss: torch.Tensor, opt: torch.optim.Optimizer, params) -> None:
        opt.zero_grad(set_to_none=True)
        (loss if self.weight == 1 else loss * self.weight).backward()
        self.group.average_gradients(params)
        opt.step()

    def critic_step(self, real: torch.Tensor, labels: torch.Tensor) -> dict[str, float]:
        """One discriminator step on normalised real poses (B, T, F): minimise D(fake) - D(real) + GP."""
        model, gen, opt = self.model, self.noise_gen, self.optimizers["optimizer_d"]
        with torch.no_grad():
            fake = model.fake(labels, gen)
        real, fake = self._augment(real), self._augment(fake)
        wasserstein = model.critic(real, labels).mean() - model.critic(fake, labels).mean()
        gp = gradient_penalty(lambda x: model.critic(x, labels), real, fake, gen, self.tc.gp_lambda)
        loss = -wasserstein + gp
        self.check_finite(loss)
        self._step(loss, opt, model.discriminator_parameters())
        return {"d_loss": float(loss.detach()), "wasserstein": float(wasserstein.detach()), "gp": float(gp.detach())}

    def generator_step(self, labels: torch.Tensor) -> float:
        """One generator step: minimise -D(G(z, S)) for the batch's actions."""
        opt = self.optimizers["optimizer_g"]
        fake = self._augment(self.model.fake(labels, self.noise_gen))
        loss = -self.model.critic(fake, labels).mean()
        self.check_finite(loss)
        self._step(loss, opt, self.model.generator_parameters())
        return float(loss.detach())

    def train_epoch(self) -> dict[str, float]:
        self.model.train()
        group = self.group
        if group.distributed:  # each rank its own noise, the same on resume with any number of ranks
            seed = int(np.random.SeedSequence([self.tc.seed, self.epoch, group.rank]).generate_state(1)[0])
            self.noise_gen = seeded_generator(self.device, seed)
        order = self.np_rng.permutation(self.train_idx)
        sums = {"d_loss": 0.0, "wasserstein": 0.0, "gp": 0.0}
        g_losses: list[float] = []
        n_batches = 0
        for b in range(0, len(order), self.tc.batch_size):
            index = order[b:b + self.tc.batch_size]
            rows, self.weight = group.share(len(index))
            mine = np.arange(len(index))[rows] if group.distributed else None
            motion, labels = self.data.batch(index, mine)  # (B, T, J, 3), (B,): all, or this rank's
            motion, labels = motion.to(self.device), labels.to(self.device)
            for k, v in self.critic_step(self.model.normalize(motion), labels).items():
                sums[k] += v
            n_batches += 1
            self.d_steps += 1
            if self.d_steps % self.tc.n_critic == 0:
                g_losses.append(self.generator_step(labels))
        sums = {k: v / group.world_size for k, v in group.sum(sums).items()}  # the ranks' mean
        log = {"clips": len(order), **{k: v / n_batches for k, v in sums.items()}, "generator_steps": len(g_losses)}
        if g_losses:
            log["g_loss"] = float(np.mean(g_losses))
        return log


def train_dvgan(clips: ClipSet, tc: DVGANTrainConfig, out: str | Path, *, generator: str = "cnn",
                overrides: dict | None = None, resume: Path | None = None, progress: Progress | None = None,
                device: str = "cpu") -> TrainResult:
    """Train DVGAN on clips (or resume a checkpoint, keeping its model and schedule). `device`:
    as train_odmo's."""
    with thread_count(tc.threads), training_group(device) as group:
        if resume is not None:
            trainer = DVGANTrainer.resumed(resume, clips, tc, out, group)
        else:
            trainer = DVGANTrainer(clips, model_config_for(clips, generator, overrides), tc, out, group)
        first = trainer.epoch
        history = trainer.run(progress)
        if trainer.epoch == first:
            trainer.save()  # resumed at or past the asked length: nothing ran, but `out` is still written
    last = history[-1] if history else {}
    report = {"generator": trainer.cfg.generator, "epochs": trainer.epoch,
              "generator_steps": trainer.d_steps // trainer.tc.n_critic,
              **{k: last[k] for k in ("d_loss", "wasserstein", "gp", "g_loss") if k in last}}
    return TrainResult(Path(out), trainer.epoch, history, report)
