"""Training the evaluation classifier (models/classifier.py) on real clips, on the shared loop.

Split: the loop's per-class seeded split (`val_fraction`, 20%). Each epoch takes one T-frame crop
per training clip (random start, or the first frames with crop="start"), augmented (mirroring,
playback speed, optionally rotation and noise), Adam and cross-entropy. Validation: the first T
frames of every held-out clip (the canonical crop), every epoch; the report adds one fixed seeded
random crop of each. The final weights are kept (no selection on the validation set).

The defaults are the shipped recipe: mirroring and length-proportional sampling, and no playback-speed
change, because a classifier taught that a slowed-down motion is still the same action lets damped
generated motion pass (docs/evaluation.md, "Classifiers that see damped motion"). What else was tried,
with its held-out accuracies: docs/lab/classifier.md.

On several processes every rank prepares the epoch's augmented crops (one numpy stream) and
computes its share of each batch (training/distributed.py).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
from torch import nn

from odmo_cli.data.dataset import crop_pad_shift, mirror_half, mirror_map, random_start
from odmo_cli.data.readers import ClipSet
from odmo_cli.errors import UserError
from odmo_cli.models.classifier import ClassifierConfig, MotionClassifier, config_for
from odmo_cli.parallel import thread_count
from odmo_cli.training.configs import ClassifierTrainConfig
from odmo_cli.training.distributed import training_group
from odmo_cli.training.loop import Progress, Trainer, TrainResult

def crop_batch(clips: ClipSet, idx: np.ndarray, length: int, rng: np.random.Generator | None = None,
               speed: float = 1.0) -> np.ndarray:
    """(len(idx), length, J, 3) float32: random crops when `rng` is given, else the first frames.

    speed > 1 (needs rng): each clip is replayed at a random speed in [1/speed, speed] (linear
    interpolation between frames) before its random crop.
    """
    out = np.empty((len(idx), length) + clips.motions[0].shape[1:], dtype=np.float32)
    for k, i in enumerate(idx):
        m = clips.motions[int(i)]
        if rng is not None and speed > 1.0:
            m = _resample(m, float(np.exp(rng.uniform(-np.log(speed), np.log(speed)))))
        start = random_start(len(m), length, rng) if rng is not None else 0
        out[k] = crop_pad_shift(m, length, start)
    return out


def _resample(motion: np.ndarray, rate: float) -> np.ndarray:
    """The clip played `rate` times as fast: frame t of the result is source time t * rate."""
    n = max(1, int((len(motion) - 1) / rate) + 1)
    t = np.minimum(np.arange(n) * rate, len(motion) - 1)
    i0 = np.floor(t).astype(np.int64)
    i1 = np.minimum(i0 + 1, len(motion) - 1)
    w = (t - i0).astype(np.float32)[:, None, None]
    return motion[i0] * (1 - w) + motion[i1] * w


def rotate_up(motions: np.ndarray, up_index: int, max_degrees: float, rng: np.random.Generator) -> np.ndarray:
    """Rotate each motion of (N, T, J, 3) about the up axis through the origin by a random angle."""
    if max_degrees <= 0:
        return motions
    angle = np.deg2rad(rng.uniform(-max_degrees, max_degrees, size=len(motions)))
    a, b = [i for i in range(3) if i != up_index]
    c, s = np.cos(angle)[:, None, None], np.sin(angle)[:, None, None]
    out = motions.copy()
    out[..., a] = c * motions[..., a] - s * motions[..., b]
    out[..., b] = s * motions[..., a] + c * motions[..., b]
    return out


def accuracy(model: MotionClassifier, motions: np.ndarray, labels: np.ndarray, batch: int = 1024) -> float:
    if len(labels) == 0:
        return float("nan")
    logits, _ = model.predict(motions, batch)
    return float((logits.argmax(1) == labels).mean())


class ClassifierTrainer(Trainer):
    kind = "classifier"
    config_class = ClassifierConfig

    def build_model(self) -> MotionClassifier:
        return MotionClassifier(self.cfg, dropout=self.tc.dropout)

    def build_optimizers(self) -> dict:
        return {"optimizer": torch.optim.Adam(self.model.parameters(), lr=self.tc.lr,
                                              weight_decay=self.tc.weight_decay)}

    def setup(self) -> None:
        clips, tc, length = self.clips, self.tc, self.clips.manifest.clip_length
        self.val_x = crop_batch(clips, self.val_idx, length)
        self.val_y = clips.labels[self.val_idx]
        self.val_x_rand = crop_batch(clips, self.val_idx, length, np.random.default_rng(tc.seed + 1))
        train_labels = clips.labels[self.train_idx]
        self.perm = mirror_map(clips.manifest.skeleton.joint_names)
        n_crops = [max(1, math.ceil(len(clips.motions[i]) / length)) for i in self.train_idx]
        self.repeats = np.repeat(self.train_idx, n_crops)
        self.by_class = [self.train_idx[train_labels == c] for c in np.unique(train_labels)]

    def train_epoch(self) -> dict[str, float]:
        tc, model, opt, rng = self.tc, self.model, self.optimizers["optimizer"], self.np_rng
        skeleton, labels = self.clips.manifest.skeleton, self.clips.labels
        model.train()
        if tc.sampling == "balanced":
            picks = rng.integers(0, len(self.by_class), size=len(self.train_idx))
            order = np.array([self.by_class[k][rng.integers(len(self.by_class[k]))] for k in picks], dtype=np.int64)
        elif tc.sampling == "length":
            order = self.repeats[rng.permutation(len(self.repeats))]
        else:
            order = self.train_idx[rng.permutation(len(self.train_idx))]
        x = crop_batch(self.clips, order, self.clips.manifest.clip_length, rng if tc.crop == "random" else None,
                       tc.speed)
        x = rotate_up(x, skeleton.up_index, tc.rotate, rng)
        if tc.mirror:
            x = mirror_half(x, self.perm, skeleton.ground_axes[0], rng)
        if tc.noise > 0:
            x = x + rng.normal(0.0, tc.noise, size=x.shape).astype(np.float32)
        x = torch.from_numpy(x)
        y = torch.from_numpy(labels[order])
        sums = {"loss": 0.0, "correct": 0.0}
        for b in range(0, len(order), tc.batch_size):
            xb, yb = x[b:b + tc.batch_size], y[b:b + tc.batch_size]
            rows, weight = self.group.share(len(yb))
            if self.group.distributed:
                xb, yb = xb[rows], yb[rows]
            xb, yb = xb.to(self.device), yb.to(self.device)
            logits = self.net(xb)
            loss = nn.functional.cross_entropy(logits, yb)
            self.check_finite(loss)
            opt.zero_grad(set_to_none=True)
            (loss if weight == 1 else loss * weight).backward()
            if tc.grad_clip > 0:
                nn.utils.clip_grad_norm_(model.parameters(), tc.grad_clip)
            opt.step()
            if weight:
                sums["loss"] += float(loss.detach()) * len(yb)
                sums["correct"] += int((logits.detach().argmax(1) == yb).sum())
        sums = self.group.sum(sums)
        return {"clips": len(order), "loss": sums["loss"] / len(order), "train_accuracy": sums["correct"] / len(order)}

    def validate(self) -> dict[str, float]:
        return {"accuracy": accuracy(self.model, self.val_x, self.val_y)}

    def report(self) -> dict:
        """Held-out accuracy (first-T crops, one random crop, per class, balanced) and training accuracy."""
        clips, length, val_y = self.clips, self.clips.manifest.clip_length, self.val_y
        train_acc = accuracy(self.model, crop_batch(clips, self.train_idx, length), clips.labels[self.train_idx])
        val_pred = self.model.predict(self.val_x)[0].argmax(1) if len(self.val_idx) else np.zeros(0, np.int64)
        per_class = {a: float((val_pred[val_y == k] == k).mean()) if (val_y == k).any() else float("nan")
                     for k, a in enumerate(clips.manifest.action_names)}
        return {
            "val_accuracy": float((val_pred == val_y).mean()) if len(self.val_idx) else float("nan"),
            "val_accuracy_random_crop": accuracy(self.model, self.val_x_rand, val_y),
            "val_balanced_accuracy": float(np.nanmean(list(per_class.values()))) if len(self.val_idx) else float("nan"),
            "val_per_class": per_class,
            "train_accuracy": train_acc,
            "epochs": self.epoch, "seconds": float(sum(h["seconds"] for h in self.history)),
            "train_clips": int(len(self.train_idx)), "val_clips": int(len(self.val_idx)),
        }


def train_classifier(clips: ClipSet, tc: ClassifierTrainConfig, out: str | Path, *,
                     resume: str | Path | None = None, progress: Progress | None = None,
                     device: str = "cpu") -> TrainResult:
    """Train the dataset's classifier on real clips (or resume a checkpoint); write the checkpoint
    `out` with its report. The same seed gives the same weights. `device`: as train_odmo's."""
    if len(clips) == 0:
        raise UserError("no clips to train the classifier on")
    with thread_count(tc.threads), training_group(device) as group:
        if resume is not None:
            trainer = ClassifierTrainer.resumed(resume, clips, tc, out, group)
        else:
            cfg = config_for(clips.manifest, hidden=tc.hidden or None, layers=tc.layers or None)
            trainer = ClassifierTrainer(clips, cfg, tc, out, group)
        history = trainer.run(progress)
        report = trainer.report()
        trainer.save({"report": report})
    return TrainResult(Path(out), trainer.epoch, history, report)
