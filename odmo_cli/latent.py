"""The latent bank of a trained ODMO model and what it says about the latent space.

The bank holds, for every training clip, its mean code mu(P), action, end point and (where the
dataset has them) ground-truth mode: what mode discovery and KNN end points need, so sampling
never needs the dataset.
"""

from __future__ import annotations

import numpy as np
import torch

from odmo_cli.data.dataset import MotionDataset
from odmo_cli.data.readers import ClipSet


@torch.no_grad()
def latent_bank(model, clips: ClipSet, idx: np.ndarray, batch: int = 512) -> dict:
    """Codes of the canonical crop (first T frames) of clips[idx] -> plain-value dict of tensors."""
    model.eval()
    data = MotionDataset(clips, model.cfg.length, random_crop=False)
    codes, ends = [], []
    for b in range(0, len(idx), batch):
        motion, _ = data.batch(idx[b:b + batch])
        mu, _ = model.encode(motion)
        codes.append(mu)
        ends.append(motion[:, -1, 0])
    return {
        "codes": torch.cat(codes),  # (N, D)
        "labels": torch.from_numpy(clips.labels[idx].copy()),  # (N,)
        "end_points": torch.cat(ends),  # (N, 3)
        "modes": torch.from_numpy(clips.modes[idx].copy()),  # (N,) -1 when unknown
        "names": [clips.names[i] for i in idx],
    }


def centroids(codes: np.ndarray, labels: np.ndarray, n_classes: int) -> np.ndarray:
    """Per-class mean code, (C, D); NaN rows for classes with no code."""
    out = np.full((n_classes, codes.shape[1]), np.nan)
    for c in range(n_classes):
        if (labels == c).any():
            out[c] = codes[labels == c].mean(0)
    return out


def separation(train_codes: np.ndarray, train_labels: np.ndarray, test_codes: np.ndarray,
               test_labels: np.ndarray, n_classes: int) -> dict[str, float]:
    """How well codes of different actions separate.

    centroid_distance: mean distance between class centroids (compare with the margin alpha);
    spread: RMS distance of codes to their own centroid; nearest_centroid_acc: share of test
    codes whose nearest training centroid is their own class.
    """
    cent = centroids(train_codes, train_labels, n_classes)
    present = ~np.isnan(cent[:, 0])
    c = cent[present]
    d = np.linalg.norm(c[:, None] - c[None], axis=-1)
    off = d[~np.eye(len(c), dtype=bool)]
    spread = np.sqrt(np.mean(np.sum((train_codes - cent[train_labels]) ** 2, axis=1)))
    dist_test = np.linalg.norm(test_codes[:, None] - c[None], axis=-1)  # (N, C_present)
    pred = np.flatnonzero(present)[dist_test.argmin(1)]
    return {"centroid_distance": float(off.mean()) if len(off) else 0.0,
            "min_centroid_distance": float(off.min()) if len(off) else 0.0,
            "spread": float(spread), "nearest_centroid_acc": float((pred == test_labels).mean())}
