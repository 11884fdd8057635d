"""The torch Dataset over a ClipSet, with the supplement §4 clip rules, its samplers, the split and
the left-right mirroring that training may augment with.

Every clip is cropped to the dataset's length T at a random start, padded with its last frame
when shorter, then shifted so that the first frame's root is at the origin. Randomness comes
only from the generators passed in, so a seed fixes every crop and every pair.
"""

from __future__ import annotations

import numpy as np
import torch

from odmo_cli.data.readers import ClipSet
from odmo_cli.errors import UserError


def crop_pad_shift(motion: np.ndarray, length: int, start: int = 0) -> np.ndarray:
    """(T_i, J, 3) -> (length, J, 3): frames [start, start+length), last frame repeated, root_0 at 0."""
    if not 0 <= start <= max(len(motion) - length, 0):
        raise ValueError(f"crop start {start} out of range for a clip of {len(motion)} frames")
    out = motion[start:start + length]
    if len(out) < length:
        pad = np.repeat(out[-1:], length - len(out), axis=0)
        out = np.concatenate([out, pad], axis=0)
    return (out - out[0, 0]).astype(np.float32, copy=False)


def random_start(n_frames: int, length: int, rng: np.random.Generator) -> int:
    return int(rng.integers(0, n_frames - length + 1)) if n_frames > length else 0


class MotionDataset(torch.utils.data.Dataset):
    """Item i: (motion (T, J, 3) float32 tensor, action index). Crops draw from `rng`."""

    def __init__(self, clips: ClipSet, length: int | None = None, rng: np.random.Generator | None = None,
                 random_crop: bool = True):
        self.clips = clips
        self.length = int(length or clips.manifest.clip_length)
        self.rng = rng if rng is not None else np.random.default_rng(0)
        self.random_crop = random_crop

    def __len__(self) -> int:
        return len(self.clips)

    def __getitem__(self, i: int) -> tuple[torch.Tensor, int]:
        motion = self.clips.motions[i]
        start = random_start(len(motion), self.length, self.rng) if self.random_crop else 0
        return torch.from_numpy(crop_pad_shift(motion, self.length, start)), int(self.clips.labels[i])

    def batch(self, index, rows=None) -> tuple[torch.Tensor, torch.Tensor]:
        """Many items at once: (B, T, J, 3) motions and (B,) labels. With `rows` (positions in
        `index`), only those items are built, after drawing the crops of all of `index`: one
        training process's share of a batch, with the stream where the whole batch leaves it."""
        if rows is None:
            items = [self[int(i)] for i in index]
        else:
            starts = [random_start(len(self.clips.motions[int(i)]), self.length, self.rng) if self.random_crop else 0
                      for i in index]
            items = [(torch.from_numpy(crop_pad_shift(self.clips.motions[int(index[r])], self.length, starts[r])),
                      int(self.clips.labels[int(index[r])])) for r in rows]
        return torch.stack([m for m, _ in items]), torch.tensor([c for _, c in items], dtype=torch.long)


def mirror_map(joint_names) -> list[int]:
    """Joint permutation swapping left_*/right_* (or *_a/*_b) partners; unpaired joints stay."""
    names = list(joint_names)
    swaps = (("left_", "right_"), ("right_", "left_"))
    perm = []
    for j, name in enumerate(names):
        partner = name
        for a, b in swaps:
            if name.startswith(a):
                partner = b + name[len(a):]
        for a, b in (("_a", "_b"), ("_b", "_a")):
            if name.endswith(a):
                partner = name[:-len(a)] + b
        perm.append(names.index(partner) if partner in names else j)
    return perm


def mirror(motions, perm: list[int], axis: int):
    """(N, T, J, 3) motions, a numpy array or a tensor, mirrored: partner joints swapped, `axis`
    negated. A ground axis that runs from side to side (x on HumanAct12) keeps the clips' facing."""
    sign = np.ones(3, dtype=np.float32)
    sign[axis] = -1.0
    out = motions[:, :, perm]
    return out * (torch.from_numpy(sign).to(out) if isinstance(out, torch.Tensor) else sign)


def mirror_rows(motions, flip: np.ndarray, perm: list[int], axis: int):
    """A copy of (N, T, J, 3) motions, an array or a tensor, with the rows where `flip` (N,) is true mirrored."""
    out = motions.clone() if isinstance(motions, torch.Tensor) else motions.copy()
    out[flip] = mirror(motions[flip], perm, axis)
    return out


def mirror_half(motions: np.ndarray, perm: list[int], axis: int, rng: np.random.Generator) -> np.ndarray:
    """Mirror a random half of (N, T, J, 3) motions: swap partner joints, negate `axis`."""
    return mirror_rows(motions, rng.random(len(motions)) < 0.5, perm, axis)


def stratified_indices(labels: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """n clip indices with every class equally likely (supplement §4's stratified sampling)."""
    classes = np.unique(labels)
    by_class = [np.flatnonzero(labels == c) for c in classes]
    picks = rng.integers(0, len(classes), size=n)
    return np.array([rng.choice(by_class[k]) for k in picks], dtype=np.int64)


def pair_indices(labels: np.ndarray, n: int, rng: np.random.Generator,
                 same_fraction: float | None = None) -> np.ndarray:
    """n pairs (i, j), shape (n, 2), for the contrastive loss; both sides class-balanced.

    same_fraction=None draws the two sides independently (the paper's random pairs: same-class
    with probability 1/C); a number forces that share of same-class pairs, the rest different-class.
    """
    first = stratified_indices(labels, n, rng)
    if same_fraction is None:
        return np.stack([first, stratified_indices(labels, n, rng)], axis=1)
    classes = np.unique(labels)
    if len(classes) < 2 and same_fraction < 1:
        raise UserError("different-class pairs need at least two actions")
    by_class = {c: np.flatnonzero(labels == c) for c in classes}
    second = np.empty(n, dtype=np.int64)
    same = rng.random(n) < same_fraction
    for k in range(n):
        c = labels[first[k]]
        if not same[k]:
            c = rng.choice(classes[classes != c])
        second[k] = rng.choice(by_class[c])
    return np.stack([first, second], axis=1)


def split_indices(clips: ClipSet, val_fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A fixed, seeded, per-class split -> (train, validation) indices.

    A motion folder with a `split` column is split by it (train/val|test) instead.
    """
    if clips.splits and any(clips.splits):
        splits = np.array(clips.splits)
        return np.flatnonzero(splits == "train"), np.flatnonzero(np.isin(splits, ["val", "test"]))
    if not 0 <= val_fraction < 1:
        raise UserError(f"validation fraction must be in [0, 1), got {val_fraction}")
    rng = np.random.default_rng(seed)
    train, val = [], []
    for c in np.unique(clips.labels):
        idx = rng.permutation(np.flatnonzero(clips.labels == c))
        n_val = int(round(len(idx) * val_fraction)) if len(idx) > 1 else 0
        val.extend(idx[:n_val])
        train.extend(idx[n_val:])
    return np.sort(np.array(train, dtype=np.int64)), np.sort(np.array(val, dtype=np.int64))


def crops_from_start(clips: ClipSet, idx: np.ndarray, length: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The first `length` frames of each clip (padded, root at origin): the canonical crop.
    Returns (B, length, J, 3) motions and (B,) labels."""
    return MotionDataset(clips, length, random_crop=False).batch(idx)
