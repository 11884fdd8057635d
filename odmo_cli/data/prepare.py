"""Summaries of a dataset on disk (`odmo data info`) and conversion to a motion folder
(`odmo data prepare`)."""

from __future__ import annotations

import csv
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from odmo_cli.data.locate import FOLDER_MANIFEST
from odmo_cli.data.manifest import Manifest, listing_digest, sha256_file
from odmo_cli.data.readers import ClipSet, read_dataset
from odmo_cli.errors import UserError


@dataclass
class ActionRow:
    name: str
    clips: int
    expected: int
    min_len: int
    median_len: float
    max_len: int
    modes: int  # distinct ground-truth modes (0 when the dataset has none)


@dataclass
class DatasetSummary:
    name: str
    root: Path
    skeleton: str
    fps: float
    clip_length: int
    rows: list[ActionRow]
    problems: list[str] = field(default_factory=list)
    missing: list[str] = field(default_factory=list)
    extra: list[str] = field(default_factory=list)
    corrupt: list[str] = field(default_factory=list)
    digest_ok: bool | None = None  # None: the manifest has no checksums to compare with

    @property
    def total(self) -> int:
        return sum(r.clips for r in self.rows)

    def to_json(self) -> dict:
        return {
            "name": self.name, "root": str(self.root), "skeleton": self.skeleton, "fps": self.fps,
            "clip_length": self.clip_length, "clips": self.total,
            "actions": [r.__dict__ for r in self.rows], "problems": self.problems,
            "missing": self.missing, "extra": self.extra, "corrupt": self.corrupt,
            "digest_ok": self.digest_ok,
        }


def summarize(manifest: Manifest, root: Path, verify: bool = True) -> DatasetSummary:
    """Per-action clip counts and lengths; with `verify`, files checked against the manifest's hashes."""
    clips = read_dataset(root, manifest, strict=False)
    summary = DatasetSummary(manifest.name, root, manifest.skeleton_name, manifest.fps,
                             manifest.clip_length, _rows(clips), problems=list(clips.problems))
    expected = manifest.checksums()
    if verify and expected:
        _verify(summary, root, expected, manifest.digest)
    return summary


def _rows(clips: ClipSet) -> list[ActionRow]:
    rows = []
    for i, action in enumerate(clips.manifest.actions):
        idx = np.flatnonzero(clips.labels == i)
        lengths = np.array([len(clips.motions[k]) for k in idx]) if len(idx) else np.zeros(1, int)
        modes = clips.modes[idx]
        rows.append(ActionRow(action.name, len(idx), action.count, int(lengths.min()),
                              float(np.median(lengths)), int(lengths.max()),
                              len(set(modes[modes >= 0].tolist()))))
    return rows


def _verify(summary: DatasetSummary, root: Path, expected: dict[str, str], digest: str) -> None:
    present = {p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file()}
    summary.missing = sorted(set(expected) - present)
    summary.extra = sorted(p for p in present - set(expected) if not Path(p).name.startswith("."))
    found = {rel: sha256_file(root / rel) for rel in sorted(present & set(expected))}
    summary.corrupt = sorted(rel for rel, h in found.items() if h != expected[rel])
    summary.digest_ok = (not summary.missing and not summary.corrupt
                         and (not digest or listing_digest(found) == digest))


def manifest_toml(manifest: Manifest, name: str) -> str:
    """The manifest of a converted motion folder (format folder, scale already applied)."""
    q = lambda s: '"' + str(s).replace("\\", "\\\\").replace('"', '\\"') + '"'  # noqa: E731
    lines = [f"name = {q(name)}", f"title = {q(manifest.title + ' (motion folder)')}", 'format = "folder"',
             f"skeleton = {q(manifest.skeleton_name)}", f"up_axis = {q(manifest.up_axis)}",
             "scale = 1.0", f"fps = {manifest.fps}", f"clip_length = {manifest.clip_length}",
             f"homepage = {q(manifest.homepage)}", f"licence = {q(manifest.licence)}",
             f"citation = {q(manifest.citation)}", f"labels = {q('converted from ' + manifest.name)}", ""]
    for a in manifest.actions:
        lines += ["[[actions]]", f"name = {q(a.name)}", f"label = {q(a.name)}", f"count = {a.count}", ""]
    return "\n".join(lines)


def prepare(manifest: Manifest, source: Path, out: Path) -> ClipSet:
    """Validate the release at `source` and write it as a motion folder at `out` (a new folder)."""
    clips = read_dataset(source, manifest, strict=True)
    write_folder(clips, out)
    return clips


def write_folder(clips: ClipSet, out: Path) -> None:
    """Write clips as a motion folder: index.csv, one npy per clip, dataset.toml.

    Everything goes into a temp folder beside `out`, renamed at the end: a failure leaves nothing.
    """
    out = Path(out)
    if out.exists():
        raise UserError(f"output folder {out} already exists; choose a new path")
    if not out.parent.is_dir():
        raise UserError(f"cannot write {out}: folder {out.parent} does not exist")
    manifest = clips.manifest
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        with open(tmp / "index.csv", "w", newline="") as f:
            writer = csv.writer(f)
            has_split = any(clips.splits)  # keep a source motion folder's train/val/test split
            writer.writerow(["motion", "action", "mode", "subject"] + (["split"] if has_split else []))
            for i, name in enumerate(clips.names):
                writer.writerow([name, manifest.actions[clips.labels[i]].name, int(clips.modes[i]),
                                 clips.subjects[i] if clips.subjects else ""]
                                + ([clips.splits[i]] if has_split else []))
                np.save(tmp / f"{name}.npy", clips.motions[i].astype(np.float32))
        (tmp / FOLDER_MANIFEST).write_text(manifest_toml(manifest, manifest.name))
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o777 & ~umask)  # mkdtemp makes 0700; give the folder the usual permissions
        tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
