"""The training loop every model shares: seeding, the train/validation split, the learning-rate
schedule, exact resume, atomic checkpoints, a clean stop on Ctrl-C and on a non-finite loss.

A model's trainer subclasses `Trainer` and fills in four things:
    model_class        the network, built as model_class(cfg) right after seeding (or build_model())
    build_optimizers() {checkpoint key: optimizer}
    train_epoch()      one pass over the data -> {term: mean value}; call self.check_finite(loss)
    validate()         held-out figures -> {name: value} (optional; logged as val_<name>)
and, when it keeps more than weights, optimizers and RNGs, extra_state() / load_extra_state().

What the loop guarantees for every model:
- seed(tc.seed) sets torch's global generator (parameter initialisation, dropout) and gives the
  trainer its own numpy and torch generators; every random draw of training comes from these.
- Each epoch's state (weights, optimizers, epoch, every RNG, history) is snapshotted when the epoch
  ends. A checkpoint is written atomically every `checkpoint_every` epochs and at the end, from
  that snapshot, so `resume` continues bitwise as if never stopped.
- Ctrl-C (KeyboardInterrupt) writes the snapshot of the last completed epoch, then re-raises:
  never a half-trained epoch, so resuming gives the uninterrupted run's numbers.
- A non-finite loss raises TrainingError naming the epoch and the last checkpoint written, which
  is left as it is (the epochs since may already carry the damage that made the loss blow up).
- The learning rate of every optimizer follows tc.learning_rate(epoch) (cosine from lr to
  lr_final, or constant).

Devices and processes (training/distributed.py): a trainer gets a `Group` (device, rank,
world_size; default one CPU process, which computes exactly as before). The model is built on
the CPU from the seed, then moved to the device; `self.net` is what forward passes run through
(DistributedDataParallel on several processes); `self.group.share(n)` is this rank's rows of a
batch of n. Only the writer (rank 0) writes checkpoints (`is_writer`), always with CPU tensors.
When another process of the run stops, the collective that waited on it fails: the writer keeps
the last completed epoch, as for Ctrl-C.
"""

from __future__ import annotations

import copy
import signal
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from odmo_cli.checkpoint import (FORMAT_VERSION, cpu_tensors, dataset_description, load_checkpoint, restore_rng,
                                 rng_state, save_checkpoint)
from odmo_cli.data.dataset import split_indices
from odmo_cli.data.readers import ClipSet
from odmo_cli.device import generator
from odmo_cli.errors import PeerStopped, TrainingError, UserError
from odmo_cli.config import Config
from odmo_cli.training.configs import LoopConfig
from odmo_cli.training.distributed import Group, peer_lost

Progress = Callable[[dict], None]  # called after every epoch with that epoch's log (a dict)


def dataset_shapes(clips: ClipSet, config_class: type[Config]) -> dict:
    """What a model config of `config_class` takes from the dataset, of joints, classes, clip length T,
    skeleton name, action names and the up axis's index: the ones the class has."""
    m = clips.manifest
    return config_class.pick(dict(n_joints=m.skeleton.n_joints, n_classes=len(m.actions), length=m.clip_length,
                                  skeleton=m.skeleton_name, actions=list(m.action_names),
                                  up_axis=m.skeleton.up_index))


def resume_epochs(path: str | Path | None, epochs: int | None) -> int | None:
    """The length of a run: `epochs` when given; resuming without it, the checkpoint's own length
    (a default would otherwise lengthen a shorter run and stretch its schedules)."""
    if epochs is not None or path is None:
        return epochs
    return load_checkpoint(path).get("train_config", {}).get("epochs")


def seed(value: int, device: torch.device = torch.device("cpu")) -> tuple[np.random.Generator, torch.Generator]:
    """Seed torch's global generators and return the numpy generator and the torch generator (on
    `device`, where its draws are made) that a trainer keeps."""
    torch.manual_seed(value)
    return np.random.default_rng(value), generator(device, value)


@dataclass
class TrainResult:
    out: Path
    epochs: int
    history: list[dict]
    report: dict


class Trainer:
    """Model, optimizers, RNGs, split and data of one training run; `run` trains and checkpoints."""

    kind = ""  # the checkpoint's model kind
    config_class = Config  # the model config's class (to rebuild it from a checkpoint)
    model_class: type[torch.nn.Module] | None = None  # built as model_class(cfg) unless build_model says otherwise
    min_train_clips = 2

    def __init__(self, clips: ClipSet, cfg, tc: LoopConfig, out: str | Path, group: Group | None = None):
        self.clips, self.cfg, self.tc, self.out = clips, cfg, tc, Path(out)
        if not self.out.absolute().parent.is_dir():  # fail before training, not at the first checkpoint
            raise UserError(f"cannot write {self.out}: folder {self.out.parent} does not exist")
        self.group = group or Group()
        self.device, self.rank, self.world_size = self.group.device, self.group.rank, self.group.world_size
        self.np_rng, self.torch_gen = seed(tc.seed, self.device)
        # built on the CPU from the seed: the same initial weights on every device and every rank
        self.model = self.build_model().to(self.device)
        self.optimizers = self.build_optimizers()
        self.net = self.group.wrap(self.model)
        self.train_idx, self.val_idx = split_indices(clips, tc.val_fraction, tc.data_split_seed())
        if len(self.train_idx) < self.min_train_clips:
            raise UserError(f"need at least {self.min_train_clips} training clips, have {len(self.train_idx)}")
        self.epoch = 0
        self.history: list[dict] = []
        self._snapshot: dict | None = None  # the state after the last completed epoch
        self._saved_epoch: int | None = None  # the epoch `out` holds, once this trainer wrote it
        self.setup()

    # -- what a model fills in -------------------------------------------------------------------
    def build_model(self) -> torch.nn.Module:
        return self.model_class(self.cfg)

    def build_optimizers(self) -> dict[str, torch.optim.Optimizer]:
        raise NotImplementedError

    def setup(self) -> None:
        """Anything built from the split (datasets, statistics); runs at the end of __init__."""

    def train_epoch(self) -> dict[str, float]:
        """One epoch -> mean loss terms; the key "clips" (clips seen), if given, becomes clips_per_s."""
        raise NotImplementedError

    def validate(self) -> dict[str, float]:
        return {}

    def extra_state(self) -> dict:
        return {}

    def load_extra_state(self, ckpt: dict) -> None:
        pass

    # -- shared ------------------------------------------------------------------------------
    @property
    def is_writer(self) -> bool:
        return self.rank == 0

    def check_finite(self, loss: torch.Tensor) -> None:
        """TrainingError when the loss is not finite (on any rank: all ranks stop together)."""
        if self.group.any(not bool(torch.isfinite(loss))):
            raise TrainingError(f"non-finite loss at epoch {self.epoch + 1}")

    def state(self) -> dict:
        return {
            "format_version": FORMAT_VERSION, "kind": self.kind, "config": self.cfg.to_dict(),
            "train_config": self.tc.to_dict(), "dataset": dataset_description(self.clips),
            "state_dict": self.model.state_dict(),
            **{key: opt.state_dict() for key, opt in self.optimizers.items()},
            "epoch": self.epoch, "history": self.history, **self.extra_state(),
            "rng": rng_state(self.np_rng, self.torch_gen),
            "split": {"train": torch.from_numpy(self.train_idx), "val": torch.from_numpy(self.val_idx)},
        }

    def load_state(self, ckpt: dict) -> None:
        if ckpt.get("kind") != self.kind:
            raise UserError(f"cannot resume: checkpoint is a {ckpt.get('kind')!r} model, not {self.kind}")
        if ckpt["dataset"] != dataset_description(self.clips):
            raise UserError(f"cannot resume: checkpoint was trained on {ckpt['dataset']['name']}, "
                            f"not {self.clips.manifest.name}")
        self.model.load_state_dict(ckpt["state_dict"])
        for key, opt in self.optimizers.items():
            opt.load_state_dict(ckpt[key])
        self.epoch = int(ckpt["epoch"])
        self.history = list(ckpt["history"])
        self.load_extra_state(ckpt)
        if not restore_rng(ckpt["rng"], self.np_rng, self.torch_gen):
            # saved from a generator on another kind of device: its stream cannot go on here
            self.torch_gen.manual_seed(self.tc.seed * 1_000_003 + self.epoch)
        self._snapshot = self.snapshot()

    def snapshot(self) -> dict:
        """A copy of the current state, on the CPU (a GPU's memory holds only the live state)."""
        return copy.deepcopy(cpu_tensors(self.state()))

    def save(self, extra: dict | None = None, state: dict | None = None) -> None:
        """Write the checkpoint `out` atomically: `state` (default: the current one) plus `extra`."""
        if self.is_writer:
            state = state or self.state()
            save_checkpoint(self.out, {**state, **(extra or {})})
            self._saved_epoch = state["epoch"]

    @classmethod
    def resumed(cls, path: str | Path, clips: ClipSet, tc: LoopConfig, out: str | Path,
                group: Group | None = None) -> "Trainer":
        """The trainer of checkpoint `path`, in the state it was saved in, on `group`'s device and
        processes (any number). Its model config and schedule are kept; only the length (tc.epochs,
        if longer) and the thread count may change."""
        ckpt = load_checkpoint(path)
        if ckpt.get("kind") != cls.kind:
            raise UserError(f"cannot resume: {path} holds a {ckpt.get('kind')!r} model, not {cls.kind}")
        if "rng" not in ckpt or "epoch" not in ckpt:
            raise UserError(f"cannot resume: {path} has no training state (a compact, shipped file?)")
        saved = type(tc).from_saved(ckpt["train_config"])
        tc = replace(saved, epochs=max(tc.epochs, saved.epochs), threads=tc.threads or saved.threads)
        trainer = cls(clips, cls.config_class.from_saved(ckpt["config"]), tc, out, group)
        trainer.load_state(ckpt)
        if Path(path).resolve() == trainer.out.resolve():
            trainer._saved_epoch = trainer.epoch
        return trainer

    def run(self, progress: Progress | None = None) -> list[dict]:
        """Train up to tc.epochs (see the module docstring for what is saved when)."""
        tc = self.tc
        try:
            while self.epoch < tc.epochs:
                lr = tc.learning_rate(self.epoch)
                for opt in self.optimizers.values():
                    for group in opt.param_groups:
                        group["lr"] = lr
                start = time.perf_counter()
                terms = self.train_epoch()
                seconds = time.perf_counter() - start
                self.epoch += 1
                log = {"epoch": self.epoch, "seconds": seconds, "lr": lr}
                clips = terms.pop("clips", None)
                if clips is not None:
                    log["clips_per_s"] = clips / seconds
                log.update(terms)
                if tc.val_every and (self.epoch % tc.val_every == 0 or self.epoch == tc.epochs):
                    log.update({f"val_{k}": v for k, v in self.validate().items()})
                self.history.append(log)
                self._snapshot = self.snapshot()
                if (tc.checkpoint_every and self.epoch % tc.checkpoint_every == 0) or self.epoch == tc.epochs:
                    self.save(state=self._snapshot)
                if progress:
                    progress(log)
        except KeyboardInterrupt:
            self._keep_snapshot()
            raise
        except TrainingError as exc:
            kept = (f"the last good checkpoint (epoch {self._saved_epoch}) is kept at {self.out}"
                    if self._saved_epoch is not None else f"no checkpoint was written to {self.out}")
            raise TrainingError(f"{exc}; {kept}") from None
        except Exception as exc:
            if not (self.group.distributed and peer_lost(exc)):
                raise
            self._keep_snapshot()
            kept = f"epoch {self._snapshot['epoch']} is kept in {self.out}" if self._snapshot else "nothing was saved"
            raise PeerStopped(f"another training process stopped; {kept}") from None
        return self.history

    def stopped_extra(self, snapshot: dict) -> dict:
        """What a model adds to the checkpoint of a stopped run (Ctrl-C), so that it can be used as it is."""
        return {}

    def _keep_snapshot(self) -> None:
        if self._snapshot is None:
            return
        with _signals_held():
            self.save(state=self._snapshot)  # first the epoch itself: what follows may be slow, or fail
        if not self.is_writer:
            return
        try:  # a second Ctrl-C here leaves the file saved just above
            extra = self.stopped_extra(self._snapshot)
        except (KeyboardInterrupt, Exception):  # noqa: BLE001 - the saved epoch stands without the extras
            return
        if extra:
            with _signals_held():
                self.save(extra, state=self._snapshot)


@contextmanager
def _signals_held():
    """Ctrl-C and SIGTERM wait while the block runs: a second one must not cut the snapshot's write
    short (a launcher may pass the same Ctrl-C on to every process)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = {sig: signal.signal(sig, signal.SIG_IGN) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
