"""The tiny demo subset of real clips shipped in `odmo_cli/assets/demo/` (see its README).

A few clips per action of HumanAct12 and CMU MoCap, each cropped to at most twice the dataset's
clip length, float32, stored as motion folders. Rebuilt with `build_demo` from the full releases.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import numpy as np

from odmo_cli.data.locate import manifest_for_folder
from odmo_cli.data.manifest import canonical_name
from odmo_cli.data.prepare import write_folder
from odmo_cli.data.readers import ClipSet, read_dataset
from odmo_cli.errors import UserError

DEMO_NAMES = ("humanact12", "cmu_mocap")


def demo_folder(name: str) -> Path:
    """The shipped demo motion folder of a dataset (`humanact12`, `cmu_mocap` or `cmu`)."""
    if canonical_name(name) not in DEMO_NAMES:
        raise UserError(f"no demo subset for {name!r}; valid: {', '.join(DEMO_NAMES)}, cmu")
    return Path(str(resources.files("odmo_cli") / "assets" / "demo" / canonical_name(name)))


def load_demo(name: str) -> ClipSet:
    """The shipped demo clips of a dataset, read with the folder's own manifest."""
    folder = demo_folder(name)
    return read_dataset(folder, manifest_for_folder(folder))


def pick_demo(clips: ClipSet, per_action: int = 3) -> list[int]:
    """Up to `per_action` clips per action, preferring distinct ground-truth modes (first by name)."""
    picks = []
    for k in range(len(clips.manifest.actions)):
        idx = sorted(np.flatnonzero(clips.labels == k), key=lambda i: clips.names[i])
        seen, chosen = set(), []
        for i in idx:  # one clip per mode first, then fill up in name order
            if clips.modes[i] not in seen:
                seen.add(clips.modes[i])
                chosen.append(i)
        chosen += [i for i in idx if i not in chosen]
        picks += chosen[:per_action]
    return picks


def build_demo(clips: ClipSet, out: Path, per_action: int = 3) -> None:
    """Write the demo subset of `clips` to the new motion folder `out`."""
    sub = clips.subset(pick_demo(clips, per_action))
    limit = 2 * clips.manifest.clip_length
    sub.motions = [m[:limit] for m in sub.motions]
    write_folder(sub, out)
