"""Training Action2Motion (Guo et al. 2020, eq. 9) on the shared loop: Adam with weight decay,
teacher forcing drawn per sequence. An epoch visits every training clip once, in random order,
at a random T-frame crop. On several processes each rank draws a step's crops, coins and noise
for the whole batch and computes its share (training/distributed.py).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from odmo_cli.data.dataset import MotionDataset, crops_from_start
from odmo_cli.data.readers import ClipSet
from odmo_cli.device import generator
from odmo_cli.errors import UserError
from odmo_cli.geometry.lie import bone_lengths_from_pose
from odmo_cli.models.a2m import A2M, A2MConfig, a2m_terms, paper_lambda_kl
from odmo_cli.parallel import thread_count
from odmo_cli.training.configs import A2MTrainConfig
from odmo_cli.training.distributed import training_group
from odmo_cli.training.loop import Progress, Trainer, TrainResult, dataset_shapes


def a2m_config_for(clips: ClipSet, representation: str = "lie", overrides: dict | None = None) -> A2MConfig:
    return A2MConfig.from_dict({**dataset_shapes(clips, A2MConfig), "representation": representation, **(overrides or {})})


def bone_bank(clips: ClipSet, idx: np.ndarray, k: int, seed: int) -> torch.Tensor:
    """(k, J) bone lengths of k training clips (each averaged over its frames), chosen by seed."""
    rng = np.random.default_rng(seed)
    pick = np.sort(rng.choice(idx, size=k, replace=len(idx) < k))
    sk = clips.manifest.skeleton
    return torch.stack([bone_lengths_from_pose(torch.from_numpy(clips.motions[i]), sk).mean(0) for i in pick])


class A2MTrainer(Trainer):
    kind = "a2m"
    config_class = A2MConfig
    model_class = A2M
    min_train_clips = 1

    def __init__(self, clips: ClipSet, cfg: A2MConfig, tc: A2MTrainConfig, out: Path, group=None):
        if tc.lambda_kl < 0:  # resolved here so the checkpoint's train config shows the value used
            tc = replace(tc, lambda_kl=paper_lambda_kl(clips.manifest.name))
        self.lambda_kl = tc.lambda_kl
        super().__init__(clips, cfg, tc, out, group)

    def build_optimizers(self) -> dict:
        return {"optimizer": torch.optim.Adam(self.model.parameters(), lr=self.tc.lr,
                                              weight_decay=self.tc.weight_decay)}

    def setup(self) -> None:
        self.model.bone_bank.copy_(bone_bank(self.clips, self.train_idx, self.cfg.bank_size, self.tc.seed))
        self.data = MotionDataset(self.clips, self.cfg.length, rng=self.np_rng)

    def train_epoch(self) -> dict[str, float]:
        tc, model, opt, dev, gen = self.tc, self.model, self.optimizers["optimizer"], self.device, self.torch_gen
        model.train()
        order = self.train_idx[self.np_rng.permutation(len(self.train_idx))]
        sums: dict[str, float] = {}
        for b in range(0, len(order), tc.batch_size):
            index = order[b:b + tc.batch_size]
            n = len(index)
            rows, weight = self.group.share(n)
            mine = np.arange(n)[rows] if self.group.distributed else None
            motion, labels = self.data.batch(index, mine)  # (B, T, J, 3), (B,): all, or this rank's
            motion, labels = motion.to(dev), labels.to(dev)
            # the whole batch's coins and noise (in the order the model would draw them), then our rows
            teacher = torch.rand(n, generator=gen, device=dev) < tc.teacher_rate  # (B,) per sequence
            noise = torch.stack([torch.randn((n, self.cfg.z_dim), generator=gen, device=dev)
                                 for _ in range(self.cfg.length)])  # (T, B, Z)
            if mine is not None:
                teacher, noise = teacher[rows], noise[:, rows]
            terms = a2m_terms(model, motion, labels, teacher, self.lambda_kl, noise=noise, net=self.net)
            self.check_finite(terms["loss"])
            opt.zero_grad(set_to_none=True)
            (terms["loss"] if weight == 1 else terms["loss"] * weight).backward()
            if tc.grad_clip > 0:
                torch.nn.utils.clip_grad_norm_(model.parameters(), tc.grad_clip)
            opt.step()
            own = len(labels) if weight else 0
            for k, v in terms.items():
                sums[k] = sums.get(k, 0.0) + float(v.detach()) * own
        sums = self.group.sum(sums)
        return {"clips": len(order), "teacher": tc.teacher_rate, **{k: v / len(order) for k, v in sums.items()}}

    @torch.no_grad()
    def validate(self, batch: int = 256) -> dict[str, float]:
        """Eq. (9)'s terms on held-out clips (first T frames), teacher-forced, fixed noise."""
        self.model.eval()
        idx = self.val_idx if len(self.val_idx) else self.train_idx
        gen = generator(self.device, self.tc.seed)  # its own stream: training's is untouched
        sums = {"mse": 0.0, "kl": 0.0}
        for b in range(0, len(idx), batch):
            motion, labels = crops_from_start(self.clips, idx[b:b + batch], self.cfg.length)
            motion, labels = motion.to(self.device), labels.to(self.device)
            terms = a2m_terms(self.model, motion, labels, torch.ones(len(labels), dtype=torch.bool, device=self.device),
                              self.lambda_kl, gen)
            for k in sums:
                sums[k] += float(terms[k]) * len(labels)
        return {k: v / len(idx) for k, v in sums.items()}


def train_a2m(clips: ClipSet, tc: A2MTrainConfig, out: str | Path, *, representation: str | None = None,
              overrides: dict | None = None, resume: Path | None = None, progress: Progress | None = None,
              device: str = "cpu") -> TrainResult:
    """Train Action2Motion on clips (or resume a checkpoint); the final checkpoint holds a report.

    representation: "xyz" or "lie" (None: "lie", or the resumed checkpoint's). `device`: as train_odmo's.
    """
    with thread_count(tc.threads), training_group(device) as group:
        if resume is not None:
            trainer = A2MTrainer.resumed(resume, clips, tc, out, group)
            if representation not in (None, trainer.cfg.representation):
                raise UserError(f"cannot resume: {resume} is an a2m-{trainer.cfg.representation} model, "
                                f"not {representation}")
        else:
            trainer = A2MTrainer(clips, a2m_config_for(clips, representation or "lie", overrides), tc, out, group)
        history = trainer.run(progress)
        held = trainer.val_idx if len(trainer.val_idx) else trainer.train_idx
        report = {"held_out_clips": int(len(held)), **{f"held_out_{k}": v for k, v in trainer.validate().items()},
                  "lambda_kl": trainer.lambda_kl, "representation": trainer.cfg.representation,
                  "bone_bank": int(len(trainer.model.bone_bank))}
        trainer.save({"report": report})
        return TrainResult(Path(out), trainer.epoch, history, report)
