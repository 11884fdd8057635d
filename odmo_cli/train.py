"""The training loop: pairs of class-balanced clips, Adam, linearly decayed teacher forcing,
atomic checkpoints at intervals, exact resume, and a clean stop on Ctrl-C.

A checkpoint holds only tensors and plain values (loadable with weights_only=True): the model
config, the training config, the state dicts, the epoch, every RNG state, the loss history,
the dataset description and, once training ends, the latent bank.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from odmo_cli import metrics
from odmo_cli.data.dataset import MotionDataset, pair_indices, split_indices
from odmo_cli.data.readers import ClipSet
from odmo_cli.errors import TrainingError, UserError
from odmo_cli.io import load_checkpoint, save_checkpoint
from odmo_cli.models.losses import odmo_terms, total_loss
from odmo_cli.models.odmo import ODMO, ODMOConfig, preset_values

FORMAT_VERSION = 1


@dataclass
class TrainConfig:
    epochs: int = 300
    batch_size: int = 256  # pairs per step (each step sees 2 x batch_size clips)
    lr: float = 1e-3
    lr_final: float = 1e-3  # cosine decay from lr to lr_final over the epochs; equal = constant (paper)
    tf_start: float = 1.0
    tf_end: float = 0.3
    tf_epochs: int = 0  # teacher forcing decays linearly over this many epochs (0: all epochs)
    tf_per: str = "step"  # one teacher-forcing coin per time step for the batch (the release), or per "clip" and step
    pairs_per_epoch: int = 0  # 0: as many pairs as training clips
    same_class_fraction: float = 0.5  # the release pairs each clip with its class half the time; < 0: independent pairs
    val_fraction: float = 0.1
    val_every: int = 10  # epochs between validation losses
    checkpoint_every: int = 25  # epochs between checkpoints (and one at the end)
    grad_clip: float = 1.0  # as in the authors' release
    seed: int = 0
    threads: int = 0  # torch intra-op threads; 0 leaves torch's default

    def __post_init__(self):
        if self.epochs <= 0 or self.batch_size <= 0:
            raise UserError(f"epochs and batch size must be positive, got {self.epochs} and {self.batch_size}")
        if self.lr <= 0 or self.lr_final <= 0:
            raise UserError(f"learning rates must be positive, got {self.lr} and {self.lr_final}")
        if not (0 <= self.tf_end <= 1 and 0 <= self.tf_start <= 1):
            raise UserError("teacher-forcing rates must be in [0, 1]")
        if self.tf_per not in ("step", "clip"):
            raise UserError(f"teacher forcing per step or clip, got {self.tf_per!r}")
        if self.same_class_fraction > 1:
            raise UserError(f"--same-class-fraction must be in [0, 1], got {self.same_class_fraction}")

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        known = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in known})

    def teacher_rate(self, epoch: int) -> float:
        span = self.tf_epochs or self.epochs
        frac = min(epoch / max(span - 1, 1), 1.0)
        return self.tf_start + (self.tf_end - self.tf_start) * frac

    def learning_rate(self, epoch: int) -> float:
        return cosine_rate(self.lr, self.lr_final, epoch, self.epochs)


def cosine_rate(lr: float, lr_final: float, epoch: int, epochs: int) -> float:
    """Cosine decay from lr (epoch 0) to lr_final (the last of `epochs`)."""
    frac = epoch / max(epochs - 1, 1)
    return lr_final + 0.5 * (lr - lr_final) * (1 + math.cos(math.pi * frac))


@dataclass
class EpochLog:
    epoch: int
    seconds: float
    clips_per_s: float
    teacher: float
    lr: float
    terms: dict[str, float]
    val: dict[str, float] = field(default_factory=dict)


def dataset_description(clips: ClipSet) -> dict:
    m = clips.manifest
    return {"name": m.name, "actions": list(m.action_names), "skeleton": m.skeleton_name,
            "fps": float(m.fps), "length": int(m.clip_length), "up_axis": m.up_axis}


def model_config_for(clips: ClipSet, overrides: dict | None = None, preset: str = "odmo") -> ODMOConfig:
    """ODMOConfig for the clips' dataset: its shapes, the preset's loss scales (models.odmo.PRESETS),
    then `overrides`."""
    m = clips.manifest
    base = dict(n_joints=m.skeleton.n_joints, n_classes=len(m.actions), length=m.clip_length,
                up_axis=m.skeleton.up_index, **preset_values(preset, m.name))
    base.update(overrides or {})
    return ODMOConfig.from_dict(base)


def seeded_start(tc) -> tuple[np.random.Generator, torch.Generator]:
    """Every trainer's start: its thread count, the seed for parameter initialisation (call this
    before building the model), and the numpy and torch generators it keeps, all from tc.seed."""
    if tc.threads:
        torch.set_num_threads(tc.threads)
    torch.manual_seed(tc.seed)
    return np.random.default_rng(tc.seed), torch.Generator().manual_seed(tc.seed)


class Trainer:
    """Holds model, optimizer, RNGs and data; `run` trains and checkpoints."""

    kind = "odmo"  # the checkpoint's model kind; subclasses for other models change it

    def __init__(self, clips: ClipSet, cfg: ODMOConfig, tc: TrainConfig, out: Path):
        self.clips, self.cfg, self.tc, self.out = clips, cfg, tc, Path(out)
        self.np_rng, self.torch_gen = seeded_start(tc)
        self.model = ODMO(cfg)
        self.opt = torch.optim.Adam(self.model.parameters(), lr=tc.lr)
        self.train_idx, self.val_idx = split_indices(clips, tc.val_fraction, tc.seed)
        if len(self.train_idx) < 2:
            raise UserError(f"need at least 2 training clips, have {len(self.train_idx)}")
        self.data = MotionDataset(clips, cfg.length, rng=self.np_rng)
        self.epoch = 0
        self.history: list[dict] = []

    # -- checkpoints -------------------------------------------------------------------------
    def state(self) -> dict:
        return {
            "format_version": FORMAT_VERSION, "kind": self.kind, "config": self.cfg.to_dict(),
            "train_config": asdict(self.tc), "dataset": dataset_description(self.clips),
            "state_dict": self.model.state_dict(), "optimizer": self.opt.state_dict(),
            "epoch": self.epoch, "history": self.history,
            "rng": {"numpy": _np_state(self.np_rng), "torch": self.torch_gen.get_state()},
            "split": {"train": torch.from_numpy(self.train_idx), "val": torch.from_numpy(self.val_idx)},
        }

    def load_state(self, ckpt: dict) -> None:
        if ckpt.get("kind") != self.kind:
            raise UserError(f"cannot resume: checkpoint is a {ckpt.get('kind')!r} model, not {self.kind}")
        if ckpt["dataset"] != dataset_description(self.clips):
            raise UserError(f"cannot resume: checkpoint was trained on {ckpt['dataset']['name']}, "
                            f"not {self.clips.manifest.name}")
        self.model.load_state_dict(ckpt["state_dict"])
        self.opt.load_state_dict(ckpt["optimizer"])
        self.epoch = int(ckpt["epoch"])
        self.history = list(ckpt["history"])
        self.np_rng.bit_generator.state = _np_state_from(ckpt["rng"]["numpy"])
        self.torch_gen.set_state(ckpt["rng"]["torch"])

    def save(self, extra: dict | None = None) -> None:
        payload = self.state()
        payload.update(extra or {})
        save_checkpoint(self.out, payload)

    # -- one epoch ---------------------------------------------------------------------------
    def train_epoch(self) -> EpochLog:
        tc, model = self.tc, self.model
        model.train()
        teacher_rate = tc.teacher_rate(self.epoch)
        lr = tc.learning_rate(self.epoch)
        for group in self.opt.param_groups:
            group["lr"] = lr
        n_pairs = tc.pairs_per_epoch or len(self.train_idx)
        same = tc.same_class_fraction if tc.same_class_fraction >= 0 else None
        labels = self.clips.labels[self.train_idx]
        pairs = self.train_idx[pair_indices(labels, n_pairs, self.np_rng, same)]  # (n, 2)
        sums: dict[str, float] = {}
        start = time.perf_counter()
        for b in range(0, n_pairs, tc.batch_size):
            chunk = pairs[b:b + tc.batch_size]
            motion, lab = self.data.batch(np.concatenate([chunk[:, 0], chunk[:, 1]]))  # (2B, T, J, 3)
            shape = (len(motion), self.cfg.length) if tc.tf_per == "clip" else (self.cfg.length,)
            teacher = torch.rand(shape, generator=self.torch_gen) < teacher_rate
            out = model(motion, lab, generator=self.torch_gen, teacher=teacher)
            terms = odmo_terms(out, motion, lab, self.cfg)
            loss = total_loss(terms, self.cfg)
            if not torch.isfinite(loss):
                raise TrainingError(f"non-finite loss at epoch {self.epoch + 1}; "
                                    f"the last good checkpoint is kept at {self.out}")
            self.opt.zero_grad(set_to_none=True)
            loss.backward()
            if tc.grad_clip > 0:
                torch.nn.utils.clip_grad_norm_(model.parameters(), tc.grad_clip)
            self.opt.step()
            for k, v in terms.items():
                sums[k] = sums.get(k, 0.0) + float(v.detach()) * len(chunk)
            sums["total"] = sums.get("total", 0.0) + float(loss.detach()) * len(chunk)
        seconds = time.perf_counter() - start
        self.epoch += 1
        return EpochLog(self.epoch, seconds, 2 * n_pairs / seconds, teacher_rate, lr,
                        {k: v / n_pairs for k, v in sums.items()})

    @torch.no_grad()
    def validate(self) -> dict[str, float]:
        """Reconstruction error of held-out clips from their mean code, with no teacher forcing."""
        idx = self.val_idx if len(self.val_idx) else self.train_idx
        return reconstruction_error(self.model, self.clips, idx)

    def run(self, progress: Callable[[EpochLog], None] | None = None) -> list[dict]:
        """Train up to tc.epochs. On Ctrl-C the last completed epoch is checkpointed, then re-raised."""
        try:
            while self.epoch < self.tc.epochs:
                log = self.train_epoch()
                if self.tc.val_every and (log.epoch % self.tc.val_every == 0 or log.epoch == self.tc.epochs):
                    log.val = self.validate()
                self.history.append({"epoch": log.epoch, "seconds": log.seconds, "teacher": log.teacher,
                                     "lr": log.lr, **log.terms, **{f"val_{k}": v for k, v in log.val.items()}})
                if self.tc.checkpoint_every and log.epoch % self.tc.checkpoint_every == 0:
                    self.save()
                if progress:
                    progress(log)
        except KeyboardInterrupt:
            self.save()
            raise
        return self.history


def crops_from_start(clips: ClipSet, idx: np.ndarray, length: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The first `length` frames of each clip (padded, root at origin): the canonical crop."""
    data = MotionDataset(clips, length, random_crop=False)
    return data.batch(idx)


@torch.no_grad()
def reconstruction_error(model: ODMO, clips: ClipSet, idx: np.ndarray, batch: int = 512) -> dict[str, float]:
    """Free-running reconstruction of clips[idx] from their mean codes and real end points (as at
    sampling time, no teacher forcing): mean per-joint position error and end-point error (dataset
    units), and the body's speed and amplitude over the clips' own (metrics.damping_ratios)."""
    model.eval()
    joint_err, end_err, recons, reals, labs = [], [], [], [], []
    for b in range(0, len(idx), batch):
        motion, labels = crops_from_start(clips, idx[b:b + batch], model.cfg.length)
        mu, _ = model.encode(motion)
        _, recon = model.decode(mu, labels, motion[:, -1, 0])
        joint_err.append((recon - motion).norm(dim=-1).mean(dim=(1, 2)))
        end_err.append((recon[:, -1, 0] - motion[:, -1, 0]).norm(dim=-1))
        recons.append(recon.numpy())
        reals.append(motion.numpy())
        labs.append(labels.numpy())
    labs = np.concatenate(labs)
    damp = metrics.damping_ratios(np.concatenate(recons), labs, np.concatenate(reals), labs)
    return {"mpjpe": float(torch.cat(joint_err).mean()), "end_error": float(torch.cat(end_err).mean()),
            "speed": damp["speed"], "amplitude": damp["amplitude"]}


@torch.no_grad()
def noise_ceiling(model: ODMO, clips: ClipSet, idx: np.ndarray, seed: int, batch: int = 512) -> dict[str, float]:
    """metrics.noise_ceiling of the model's own posterior over clips[idx] (canonical crops): the
    speed and amplitude that the best squared-error decoder could reach under that noise."""
    model.eval()
    mus, stds, motions, labels = [], [], [], []
    for b in range(0, len(idx), batch):
        motion, lab = crops_from_start(clips, idx[b:b + batch], model.cfg.length)
        mu, logvar = model.encode(motion)
        mus.append(mu.numpy())
        stds.append(torch.exp(0.5 * logvar).numpy())
        motions.append(motion.numpy())
        labels.append(lab.numpy())
    c = metrics.noise_ceiling(np.concatenate(mus), np.concatenate(stds), np.concatenate(motions),
                              np.concatenate(labels), np.random.default_rng(seed), draws=2)
    return {"speed": c["speed"], "amplitude": c["amplitude"]}


def _np_state(rng: np.random.Generator) -> dict:
    """numpy's PCG64 state with its 128-bit integers as strings (checkpoints hold plain values)."""
    s = rng.bit_generator.state
    return {"bit_generator": s["bit_generator"], "state": str(s["state"]["state"]),
            "inc": str(s["state"]["inc"]), "has_uint32": int(s["has_uint32"]), "uinteger": int(s["uinteger"])}


def _np_state_from(d: dict) -> dict:
    return {"bit_generator": d["bit_generator"], "state": {"state": int(d["state"]), "inc": int(d["inc"])},
            "has_uint32": d["has_uint32"], "uinteger": d["uinteger"]}


def resumed_config(saved: dict, given):
    """A resumed run keeps its saved schedule; only the length (epochs) and the thread count may change.
    `given` is the training config asked for now (any of the trainers' config dataclasses)."""
    cls = type(given)
    old = cls.from_dict(saved)
    return cls.from_dict({**asdict(old), "epochs": max(given.epochs, old.epochs),
                          "threads": given.threads or old.threads})


@dataclass
class TrainResult:
    out: Path
    epochs: int
    history: list[dict]
    report: dict


def finish(trainer: Trainer) -> dict:
    """Latent bank, held-out reconstruction and latent separation; written into the checkpoint."""
    from odmo_cli.latent import fit_modes, latent_bank, separation

    model, clips = trainer.model, trainer.clips
    bank = latent_bank(model, clips, trainer.train_idx)
    held = trainer.val_idx if len(trainer.val_idx) else trainer.train_idx
    held_bank = latent_bank(model, clips, held)
    report = {
        "held_out_clips": int(len(held)),
        **{f"held_out_{k}": v for k, v in reconstruction_error(model, clips, held).items()},
        **{f"ceiling_{k}": v for k, v in noise_ceiling(model, clips, trainer.train_idx, trainer.tc.seed).items()},
        **separation(bank["codes"].numpy(), bank["labels"].numpy(), held_bank["codes"].numpy(),
                     held_bank["labels"].numpy(), trainer.cfg.n_classes),
        "alpha": trainer.cfg.alpha,
    }
    modes = fit_modes(bank, trainer.cfg.n_classes, seed=trainer.tc.seed)
    trainer.save({"latent_bank": bank, "modes": modes, "report": report})
    return report


def train_odmo(clips: ClipSet, tc: TrainConfig, out: Path, overrides: dict | None = None,
               resume: Path | None = None, progress: Callable[[EpochLog], None] | None = None,
               preset: str = "odmo") -> TrainResult:
    """Train ODMO on clips (or resume a checkpoint), then write the final checkpoint with its bank."""
    if resume is not None:
        ckpt = load_checkpoint(resume)
        cfg = ODMOConfig.from_dict(ckpt["config"])
        tc = resumed_config(ckpt["train_config"], tc)
        trainer = Trainer(clips, cfg, tc, out)
        trainer.load_state(ckpt)
    else:
        trainer = Trainer(clips, model_config_for(clips, overrides, preset), tc, out)
    history = trainer.run(progress)
    return TrainResult(Path(out), trainer.epoch, history, finish(trainer))
