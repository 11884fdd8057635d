"""Training Action2Motion: Adam with weight decay, teacher forcing drawn per sequence, eq. (9).

The checkpoint format, the run loop (validation and checkpoints at intervals, Ctrl-C keeps the
last completed epoch) and exact resume are ODMO's `Trainer`; only the model, the optimizer and
one epoch differ. An epoch visits every training clip once, in random order, at a random crop.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from odmo_cli.data.dataset import MotionDataset, split_indices
from odmo_cli.data.readers import ClipSet
from odmo_cli.errors import TrainingError, UserError
from odmo_cli.io import load_checkpoint
from odmo_cli.lie import bone_lengths_from_pose
from odmo_cli.models.a2m import A2M, A2MConfig, a2m_terms, paper_lambda_kl
from odmo_cli.train import EpochLog, Trainer, TrainResult, crops_from_start, resumed_config, seeded_start


@dataclass
class A2MTrainConfig:
    epochs: int = 500  # the paper gives iterations, not epochs; ~9 steps per HumanAct12 epoch
    batch_size: int = 128  # A.2
    lr: float = 2e-4  # A.2, Adam with betas (0.9, 0.999)
    weight_decay: float = 1e-5  # A.2
    teacher_rate: float = 0.6  # p_tf (§3.2.3, A.2)
    lambda_kl: float = -1.0  # < 0: the paper's value for the dataset (0.01 HumanAct12, else 0.1)
    val_fraction: float = 0.1
    val_every: int = 10  # epochs between validation losses
    checkpoint_every: int = 25
    grad_clip: float = 0.0  # 0: no clipping (the paper does not clip)
    seed: int = 0
    threads: int = 0  # torch intra-op threads; 0 leaves torch's default

    def __post_init__(self):
        if self.epochs <= 0 or self.batch_size <= 0:
            raise UserError(f"epochs and batch size must be positive, got {self.epochs} and {self.batch_size}")
        if self.lr <= 0 or self.weight_decay < 0:
            raise UserError(f"learning rate must be positive and weight decay >= 0, got {self.lr}, {self.weight_decay}")
        if not 0 <= self.teacher_rate <= 1:
            raise UserError(f"teacher-forcing rate must be in [0, 1], got {self.teacher_rate}")

    @classmethod
    def from_dict(cls, d: dict) -> "A2MTrainConfig":
        known = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in known})


def a2m_config_for(clips: ClipSet, representation: str = "lie", overrides: dict | None = None) -> A2MConfig:
    m = clips.manifest
    base = dict(n_joints=m.skeleton.n_joints, n_classes=len(m.actions), length=m.clip_length,
                skeleton=m.skeleton_name, representation=representation)
    return A2MConfig.from_dict({**base, **(overrides or {})})


def bone_bank(clips: ClipSet, idx: np.ndarray, k: int, seed: int) -> torch.Tensor:
    """(k, J) bone lengths of k training clips (each averaged over its frames), chosen by seed."""
    rng = np.random.default_rng(seed)
    pick = np.sort(rng.choice(idx, size=k, replace=len(idx) < k))
    sk = clips.manifest.skeleton
    return torch.stack([bone_lengths_from_pose(torch.from_numpy(clips.motions[i]), sk).mean(0) for i in pick])


class A2MTrainer(Trainer):
    kind = "a2m"

    def __init__(self, clips: ClipSet, cfg: A2MConfig, tc: A2MTrainConfig, out: Path):
        # not Trainer.__init__, which builds ODMO; the attributes are the ones Trainer's methods use
        if tc.lambda_kl < 0:  # resolved here so the checkpoint's train config shows the value used
            tc = replace(tc, lambda_kl=paper_lambda_kl(clips.manifest.name))
        self.clips, self.cfg, self.tc, self.out = clips, cfg, tc, Path(out)
        self.np_rng, self.torch_gen = seeded_start(tc)
        self.model = A2M(cfg)
        self.opt = torch.optim.Adam(self.model.parameters(), lr=tc.lr, weight_decay=tc.weight_decay)
        self.train_idx, self.val_idx = split_indices(clips, tc.val_fraction, tc.seed)
        if len(self.train_idx) < 1:
            raise UserError("need at least 1 training clip")
        self.model.bone_bank.copy_(bone_bank(clips, self.train_idx, cfg.bank_size, tc.seed))
        self.data = MotionDataset(clips, cfg.length, rng=self.np_rng)
        self.lambda_kl = tc.lambda_kl
        self.epoch = 0
        self.history: list[dict] = []

    def train_epoch(self) -> EpochLog:
        tc, model = self.tc, self.model
        model.train()
        order = self.train_idx[self.np_rng.permutation(len(self.train_idx))]
        sums: dict[str, float] = {}
        start = time.perf_counter()
        for b in range(0, len(order), tc.batch_size):
            motion, labels = self.data.batch(order[b:b + tc.batch_size])  # (B, T, J, 3), (B,)
            teacher = torch.rand(len(labels), generator=self.torch_gen) < tc.teacher_rate  # (B,) per sequence
            terms = a2m_terms(model, motion, labels, teacher, self.lambda_kl, self.torch_gen)
            if not torch.isfinite(terms["loss"]):
                raise TrainingError(f"non-finite loss at epoch {self.epoch + 1}; "
                                    f"the last good checkpoint is kept at {self.out}")
            self.opt.zero_grad(set_to_none=True)
            terms["loss"].backward()
            if tc.grad_clip > 0:
                torch.nn.utils.clip_grad_norm_(model.parameters(), tc.grad_clip)
            self.opt.step()
            for k, v in terms.items():
                sums[k] = sums.get(k, 0.0) + float(v.detach()) * len(labels)
        seconds = time.perf_counter() - start
        self.epoch += 1
        return EpochLog(self.epoch, seconds, len(order) / seconds, tc.teacher_rate, tc.lr,
                        {k: v / len(order) for k, v in sums.items()})

    @torch.no_grad()
    def validate(self, batch: int = 256) -> dict[str, float]:
        """Eq. (9)'s terms on held-out clips (first T frames), teacher-forced, fixed noise."""
        self.model.eval()
        idx = self.val_idx if len(self.val_idx) else self.train_idx
        gen = torch.Generator().manual_seed(self.tc.seed)  # its own stream: training's is untouched
        sums = {"mse": 0.0, "kl": 0.0}
        for b in range(0, len(idx), batch):
            motion, labels = crops_from_start(self.clips, idx[b:b + batch], self.cfg.length)
            terms = a2m_terms(self.model, motion, labels, torch.ones(len(labels), dtype=torch.bool),
                              self.lambda_kl, gen)
            for k in sums:
                sums[k] += float(terms[k]) * len(labels)
        return {k: v / len(idx) for k, v in sums.items()}


def train_a2m(clips: ClipSet, tc: A2MTrainConfig, out: Path, representation: str | None = None,
              resume: Path | None = None, progress: Callable[[EpochLog], None] | None = None,
              overrides: dict | None = None) -> TrainResult:
    """Train Action2Motion on clips (or resume a checkpoint); the final checkpoint holds a report.

    representation: "xyz" or "lie" (None: "lie", or the resumed checkpoint's).
    """
    if resume is not None:
        ckpt = load_checkpoint(resume)
        if ckpt.get("kind") != "a2m":
            raise UserError(f"cannot resume: {resume} holds a {ckpt.get('kind')!r} model, not a2m")
        cfg = A2MConfig.from_dict(ckpt["config"])
        if representation not in (None, cfg.representation):
            raise UserError(f"cannot resume: {resume} is an a2m-{cfg.representation} model, "
                            f"not {representation}")
        tc = resumed_config(ckpt["train_config"], tc)
        trainer = A2MTrainer(clips, cfg, tc, out)
        trainer.load_state(ckpt)
    else:
        trainer = A2MTrainer(clips, a2m_config_for(clips, representation or "lie", overrides), tc, out)
    history = trainer.run(progress)
    held = trainer.val_idx if len(trainer.val_idx) else trainer.train_idx
    report = {"held_out_clips": int(len(held)), **{f"held_out_{k}": v for k, v in trainer.validate().items()},
              "lambda_kl": trainer.lambda_kl, "representation": trainer.cfg.representation,
              "bone_bank": int(len(trainer.model.bone_bank))}
    trainer.save({"report": report})
    return TrainResult(Path(out), trainer.epoch, history, report)
