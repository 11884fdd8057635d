"""Readers for the on-disk dataset formats. Each returns a `ClipSet` in the dataset's own frame
after the manifest's scale, float32, one (T_i, J, 3) array per clip.

Formats: the HumanAct12 release (file names carry the labels), the CMU MoCap release of
Action2Motion (`pose_clip.csv` + `mocap_3djoints/`), and the motion folder of docs/formats.md
(`index.csv` + one npy per row), which is also ODMO's UESTC layout.
"""

from __future__ import annotations

import csv
import re
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from odmo_cli.data.manifest import Manifest
from odmo_cli.errors import UserError

HUMANACT12_NAME = re.compile(r"^P(\d+)G(\d+)R(\d+)F(\d+)T(\d+)A(\d\d)(\d\d)\.npy$")


@dataclass
class ClipSet:
    """Clips of one dataset with their labels. `modes` is -1 where no ground-truth mode exists."""

    manifest: Manifest
    root: Path
    motions: list[np.ndarray]  # each (T_i, J, 3) float32
    labels: np.ndarray  # (N,) int64 action index into manifest.actions
    names: list[str]  # motion ids (file stems)
    modes: np.ndarray  # (N,) int64 fine label, -1 when unknown
    subjects: list[str] = field(default_factory=list)
    splits: list[str] = field(default_factory=list)  # from a motion folder's `split` column
    problems: list[str] = field(default_factory=list)  # files skipped and why

    def __len__(self) -> int:
        return len(self.motions)

    def subset(self, index) -> "ClipSet":
        index = np.asarray(index, dtype=np.int64)
        pick = lambda xs: [xs[i] for i in index] if xs else []  # noqa: E731
        return replace(self, motions=pick(self.motions), labels=self.labels[index],
                       names=pick(self.names), modes=self.modes[index],
                       subjects=pick(self.subjects), splits=pick(self.splits), problems=[])

    def counts(self) -> np.ndarray:
        return np.bincount(self.labels, minlength=len(self.manifest.actions))


def read_clip(path: Path, manifest: Manifest) -> np.ndarray:
    """One clip as float32 (T, J, 3) after the manifest's scale; UserError when unusable."""
    try:
        arr = np.load(path, allow_pickle=False)
    except Exception as exc:  # numpy raises ValueError/OSError/EOFError for bad files
        raise UserError(f"{path.name}: unreadable npy ({type(exc).__name__})") from None
    n_joints = manifest.skeleton.n_joints
    if arr.ndim != 3 or arr.shape[2] != 3 or arr.shape[0] < 1:
        raise UserError(f"{path.name}: shape {arr.shape}, expected (T, {n_joints}, 3)")
    if arr.shape[1] != n_joints:
        raise UserError(f"{path.name}: {arr.shape[1]} joints, skeleton {manifest.skeleton_name} has {n_joints}")
    if not np.issubdtype(arr.dtype, np.number) or not np.isfinite(arr).all():
        raise UserError(f"{path.name}: contains non-finite or non-numeric values")
    return (arr * manifest.scale).astype(np.float32)


def read_dataset(root: Path, manifest: Manifest, strict: bool = True) -> ClipSet:
    """Read the release at `root` in the manifest's format.

    strict: the first unusable file raises UserError (training must not silently drop data);
    otherwise unusable files are skipped and listed in `ClipSet.problems` (for `odmo data info`).
    """
    root = Path(root)
    if not root.is_dir():
        raise UserError(f"dataset folder not found: {root}")
    reader = {"humanact12": _humanact12_rows, "cmu_a2m": _cmu_rows, "folder": _folder_rows}[manifest.format]
    out = ClipSet(manifest, root, [], np.zeros(0, np.int64), [], np.zeros(0, np.int64))
    labels, modes = [], []
    for row in reader(root, manifest, out.problems):
        try:
            motion = read_clip(row["path"], manifest)
        except UserError as exc:
            if strict:
                raise UserError(f"bad clip in {root}: {exc}") from None
            out.problems.append(str(exc))
            continue
        out.motions.append(motion)
        out.names.append(row["name"])
        labels.append(row["label"])
        modes.append(row.get("mode", -1))
        out.subjects.append(row.get("subject", ""))
        out.splits.append(row.get("split", ""))
    if strict and out.problems:
        raise UserError(f"bad dataset {root}: {out.problems[0]} ({len(out.problems)} problem(s))")
    out.labels = np.asarray(labels, dtype=np.int64)
    out.modes = np.asarray(modes, dtype=np.int64)
    _check_classes(out, strict)
    return out


def _check_classes(clips: ClipSet, strict: bool) -> None:
    if len(clips) == 0:
        raise UserError(f"no usable clips in {clips.root}")
    empty = [a.name for a, n in zip(clips.manifest.actions, clips.counts()) if n == 0]
    if empty:
        msg = f"empty classes in {clips.root}: {', '.join(empty)}"
        if strict:
            raise UserError(msg)
        clips.problems.append(msg)


def _humanact12_rows(root: Path, manifest: Manifest, problems: list[str]):
    codes = {int(a.label): i for i, a in enumerate(manifest.actions)}
    files = sorted(root.glob("*.npy"))
    if not files:
        raise UserError(f"no HumanAct12 .npy files in {root}")
    for path in files:
        match = HUMANACT12_NAME.match(path.name)
        if match is None:
            problems.append(f"{path.name}: name does not follow P..G..R..F....T....A<cc><ff>.npy")
            continue
        coarse, fine = int(match.group(6)), int(match.group(7))
        if coarse not in codes:
            problems.append(f"{path.name}: action code {coarse:02d} not in the manifest (valid 01..{len(codes):02d})")
            continue
        yield {"path": path, "name": path.stem, "label": codes[coarse],
               "mode": coarse * 100 + fine, "subject": f"P{match.group(1)}"}


def _cmu_rows(root: Path, manifest: Manifest, problems: list[str]):
    index = root / "pose_clip.csv"
    if not index.is_file():
        raise UserError(f"{root} has no pose_clip.csv (expected the CMU MoCap release of Action2Motion)")
    by_label = {a.label: i for i, a in enumerate(manifest.actions)}
    with open(index, newline="") as f:
        reader = csv.DictReader(f)
        if not {"motion", "action_type"} <= set(reader.fieldnames or ()):
            raise UserError(f"{index}: needs columns motion,action_type, has {reader.fieldnames}")
        for row in reader:
            if row["action_type"] not in by_label:
                continue  # classes the manifest leaves out (ODMO drops Wash)
            path = root / "mocap_3djoints" / f"{row['motion']}.npy"
            if not path.is_file():
                problems.append(f"{path.name}: listed in pose_clip.csv but missing")
                continue
            yield {"path": path, "name": row["motion"], "label": by_label[row["action_type"]],
                   "subject": row["motion"].split("_")[0]}


def _folder_rows(root: Path, manifest: Manifest, problems: list[str]):
    index = root / "index.csv"
    if not index.is_file():
        raise UserError(f"{root} has no index.csv (a motion folder needs index.csv with columns motion,action)")
    with open(index, newline="") as f:
        reader = csv.DictReader(f)
        if not {"motion", "action"} <= set(reader.fieldnames or ()):
            raise UserError(f"{index}: needs columns motion,action, has {reader.fieldnames}")
        rows = list(reader)
    for row in rows:
        try:
            label = manifest.action_index(row["action"])
        except UserError:
            raise UserError(
                f"{index}: action {row['action']!r} of {row['motion']} is not in the manifest; "
                f"valid: {', '.join(manifest.action_names)}"
            ) from None
        path = root / f"{row['motion']}.npy"
        if not path.is_file():
            problems.append(f"{path.name}: listed in index.csv but missing")
            continue
        mode = row.get("mode") or "-1"
        try:
            mode = int(mode)
        except ValueError:
            raise UserError(f"{index}: mode {mode!r} of {row['motion']} is not an integer") from None
        yield {"path": path, "name": row["motion"], "label": label, "mode": mode,
               "subject": row.get("subject") or "", "split": row.get("split") or ""}
