"""What generation returns: a batch of motions with their actions, modes, codes and asked end
points, written as a samples file (odmo_cli.formats.samples, docs/formats.md).

A batch holds data only, never the model. A lazy batch (`sample(..., lazy=True)`) has its codes
but not yet its motions; `save` decodes them block by block while writing, with the model passed
in, so memory stays flat in the number of motions.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from odmo_cli.checkpoint import LoadedODMO, model_name
from odmo_cli.device import model_device
from odmo_cli.formats.samples import write_samples
from odmo_cli.io import StreamedArray

DECODE_BATCH = 1000  # motions decoded at once: memory stays flat in N; the evaluation's numbers assume it


@dataclass
class MotionBatch:
    motions: np.ndarray | None  # (N, T, J, 3) float32; None until decoded (lazy)
    actions: np.ndarray  # (N,) str
    modes: np.ndarray  # (N,) int, -1 when not mode-aware
    codes: np.ndarray  # (N, D); (N, 0) for baselines
    end_points: np.ndarray  # (N, 3) asked end points (NaN for models without end points)
    dataset: dict  # the checkpoint's dataset description
    model: str  # the checkpoint file it came from
    seed: int
    end_axes: tuple[int, ...] = ()  # axes the user fixed, for dist_e
    extra: dict = field(default_factory=dict)  # more keys for the samples file (interpolation weights, ...)
    labels: np.ndarray | None = None  # (N,) action indices, for lazy decoding
    note: str = ""  # what a default chose, for the user
    _reached: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.codes)

    @property
    def reached(self) -> np.ndarray:
        """(N, 3) root at the last frame."""
        if self.motions is not None:
            return self.motions[:, -1, 0]
        if self._reached is None:
            raise ValueError("motions not decoded yet: save() them first")
        return self._reached

    def dist_e(self) -> float | None:
        """Mean squared distance between asked and reached end points over the fixed axes."""
        if not self.end_axes:
            return None
        axes = list(self.end_axes)
        return float(np.mean(np.sum((self.end_points[:, axes] - self.reached[:, axes]) ** 2, axis=1)))

    def end_mask(self) -> np.ndarray:
        """(N, 3) bool: the end-point coordinates the user asked for (the others came from the
        nearest latent-bank clip, or are NaN for models that take no end point)."""
        mask = np.zeros((len(self), 3), dtype=bool)
        mask[:, list(self.end_axes)] = True
        return mask

    def head(self, k: int, loaded: LoadedODMO | None = None) -> np.ndarray:
        """The first k motions, decoded with `loaded` if the batch is lazy."""
        if self.motions is not None:
            return self.motions[:k]
        return decode(loaded, self.codes[:k], self.labels[:k], self.end_points[:k])

    def save(self, path: str | Path, up: str = "dataset", loaded: LoadedODMO | None = None) -> None:
        """Write the samples file (docs/formats.md); a lazy batch is decoded on the way with `loaded`.
        up="y" turns positions and end points y-up; "dataset" keeps the dataset's own frame."""
        motions = self.motions
        if motions is None:
            cfg = loaded.model.cfg
            motions = StreamedArray((len(self), cfg.length, cfg.n_joints, 3), np.float32, self._blocks(loaded))
        write_samples(path, motions, actions=self.actions, modes=self.modes, codes=self.codes,
                      end_points=self.end_points, end_mask=self.end_mask(), dataset=self.dataset,
                      model=model_name(self.model), seed=self.seed, up=up, extra=self.extra)

    def _blocks(self, loaded: LoadedODMO):
        self._reached = np.empty((len(self), 3), dtype=np.float32)
        for b in range(0, len(self), DECODE_BATCH):
            block = decode(loaded, self.codes[b:b + DECODE_BATCH], self.labels[b:b + DECODE_BATCH],
                           self.end_points[b:b + DECODE_BATCH])
            self._reached[b:b + len(block)] = block[:, -1, 0]
            yield block


@torch.inference_mode()
def decode(loaded: LoadedODMO, codes: np.ndarray, labels: np.ndarray, end_points: np.ndarray,
           batch: int = DECODE_BATCH) -> np.ndarray:
    """Codes (N, D), labels (N,), end points (N, 3) -> motions (N, T, J, 3), batch by batch."""
    cfg, dev = loaded.model.cfg, model_device(loaded.model)
    out = np.empty((len(codes), cfg.length, cfg.n_joints, 3), dtype=np.float32)
    for b in range(0, len(codes), batch):
        z = torch.from_numpy(np.ascontiguousarray(codes[b:b + batch], dtype=np.float32)).to(dev)
        lab = torch.from_numpy(np.asarray(labels[b:b + batch], dtype=np.int64)).to(dev)
        end = torch.from_numpy(np.ascontiguousarray(end_points[b:b + batch], dtype=np.float32)).to(dev)
        _, motion = loaded.model.decode(z, lab, end)
        out[b:b + batch] = motion.cpu().numpy()
    return out
