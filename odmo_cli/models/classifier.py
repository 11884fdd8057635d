"""The action classifier used for evaluation (Acc, FID, Diversity, Multimodality).

Architecture (ODMO supplement Tables 3/4, the same as Action2Motion's `MotionDiscriminator`):
a GRU over the frames, not batch-first, with parameter names `recurrent.*`; the output of the
last time step goes through `linear1` (hidden -> 30) and tanh, which is the 30-d *feature* that
FID, Diversity and Multimodality use; `linear2` (30 -> C) gives the class logits. HumanAct12 and
CMU MoCap use 2 GRU layers of 128 units, UESTC 3 layers of 256 (supplement Table S4).

Input: motions in the dataset's own frame and units after its manifest's scale, cropped to the
dataset's T with the first root at the origin (docs/formats.md), as a (B, T, J, 3) or (B, T, J*3)
batch.

The initial GRU hidden state is **zeros**. Action2Motion draws it from N(0, 1) at every call
(`initHidden` uses `torch.randn`), which makes its metrics vary from run to run; zeros is that
distribution's mean and makes every feature a deterministic function of the motion. The released
weights load unchanged (same parameter names and shapes): `odmo_cli.evaluation.classifier`.
Training: `odmo_cli.training.classifier`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from odmo_cli.config import Config
from odmo_cli.errors import UserError

FEATURE_DIM = 30  # Action2Motion's feature layer; the metrics are defined on it


# -- configuration -------------------------------------------------------------------------------

@dataclass
class ClassifierConfig(Config):
    input_size: int  # J * 3
    n_classes: int
    hidden: int = 128
    layers: int = 2
    feature: int = FEATURE_DIM

    def __post_init__(self):
        for name in ("input_size", "n_classes", "hidden", "layers", "feature"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value <= 0:
                raise UserError(f"classifier {name} must be a positive integer, got {value!r}")
            setattr(self, name, int(value))
        if self.input_size % 3:
            raise UserError(f"classifier input size must be joints x 3, got {self.input_size}")

    @property
    def n_joints(self) -> int:
        return self.input_size // 3




# Presets (supplement Tables 3 and 4): (GRU layers, hidden units).
A2M_PRESET = (2, 128)  # HumanAct12 and CMU MoCap, as in Action2Motion
UESTC_PRESET = (3, 256)  # ODMO's UESTC classifier


def config_for(manifest, **overrides) -> ClassifierConfig:
    """The classifier of a dataset (its manifest): UESTC -> 3 GRU layers of 256, otherwise 2 of 128."""
    layers, hidden = UESTC_PRESET if "uestc" in manifest.name.lower() else A2M_PRESET
    base = dict(input_size=3 * manifest.skeleton.n_joints, n_classes=len(manifest.actions),
                hidden=hidden, layers=layers)
    base.update({k: v for k, v in overrides.items() if v is not None})
    return ClassifierConfig.from_dict(base)


# -- the model -----------------------------------------------------------------------------------

class MotionClassifier(nn.Module):
    """GRU action classifier; `forward` gives logits, `features` the 30-d tanh feature."""

    def __init__(self, cfg: ClassifierConfig, dropout: float = 0.0):
        super().__init__()
        self.cfg = cfg
        # (T, B, D) as in A2M; `dropout` acts between GRU layers in training mode only (no parameters)
        self.recurrent = nn.GRU(cfg.input_size, cfg.hidden, cfg.layers, dropout=dropout if cfg.layers > 1 else 0.0)
        self.linear1 = nn.Linear(cfg.hidden, cfg.feature)
        self.linear2 = nn.Linear(cfg.feature, cfg.n_classes)
        self.info: dict = {}  # where the weights came from (set by load_classifier)
        self.keep: list[int] | None = None  # logits kept, in the dataset's action order (set by check_matches)

    def _frames(self, motion) -> torch.Tensor:
        """(B, T, J, 3) or (B, T, J*3) -> (T, B, J*3) float32, with a clear error on a shape mismatch."""
        motion = torch.as_tensor(motion)
        if motion.dim() == 4 and motion.shape[-1] == 3:
            motion = motion.reshape(motion.shape[0], motion.shape[1], -1)
        if motion.dim() != 3:
            raise UserError(f"classifier input must be (B, T, J, 3) or (B, T, J*3), got shape {tuple(motion.shape)}")
        if motion.shape[1] < 1:
            raise UserError("classifier input has no frames")
        if motion.shape[-1] != self.cfg.input_size:
            got = motion.shape[-1]
            joints = f" ({got // 3} joints)" if got % 3 == 0 else ""
            raise UserError(f"classifier expects {self.cfg.input_size} inputs per frame "
                            f"({self.cfg.n_joints} joints), got {got}{joints}")
        param = self.linear1.weight
        return motion.to(device=param.device, dtype=param.dtype).transpose(0, 1)

    def logits_and_features(self, motion) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, C) logits and (B, 30) features in [-1, 1]; the initial hidden state is zeros."""
        frames = self._frames(motion)
        h0 = frames.new_zeros(self.cfg.layers, frames.shape[1], self.cfg.hidden)
        out, _ = self.recurrent(frames, h0)
        feature = torch.tanh(self.linear1(out[-1]))
        logits = self.linear2(feature)
        return (logits if self.keep is None else logits[:, self.keep]), feature

    def forward(self, motion) -> torch.Tensor:
        return self.logits_and_features(motion)[0]

    def features(self, motion) -> torch.Tensor:
        return self.logits_and_features(motion)[1]

    @torch.no_grad()
    def predict(self, motions, batch: int = 1024) -> tuple[np.ndarray, np.ndarray]:
        """Logits (N, C) and features (N, 30) as float32 numpy, in eval mode, `batch` motions at a time."""
        if batch <= 0:
            raise UserError(f"batch size must be positive, got {batch}")
        was_training = self.training
        self.eval()
        try:
            motions = torch.as_tensor(np.asarray(motions) if not torch.is_tensor(motions) else motions)
            logits, feats = [], []
            for b in range(0, len(motions), batch):
                lo, fe = self.logits_and_features(motions[b:b + batch])
                logits.append(lo.cpu().float().numpy())
                feats.append(fe.cpu().float().numpy())
        finally:
            self.train(was_training)
        if not logits:
            return (np.zeros((0, self.cfg.n_classes), np.float32), np.zeros((0, self.cfg.feature), np.float32))
        return np.concatenate(logits), np.concatenate(feats)
