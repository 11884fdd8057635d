"""The samples file (.npz) that `odmo sample`, `interpolate` and `complete` write and `eval
--samples`, `export` and `render` read; its keys are described in docs/formats.md.

`write_samples` is its one writer and `read_samples` its one reader. Motions are stored in the
dataset's own frame, or turned y-up (`up="y"`, a proper rotation: left stays left); the reader
turns a y-up file back, so every consumer sees the dataset's frame.
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from odmo_cli.errors import UserError
from odmo_cli.geometry.skeletons import get_skeleton
from odmo_cli.io import StreamedArray, save_npz

FORMAT_VERSION = 1  # files without the key were written before the format had a version
UP_CHOICES = ("dataset", "y")
ROW_KEYS = ("motions", "actions", "modes", "codes", "end_points", "end_mask")  # one row per motion


def write_samples(path: str | Path, motions: np.ndarray | StreamedArray, *, actions: np.ndarray,
                  modes: np.ndarray, codes: np.ndarray, end_points: np.ndarray, end_mask: np.ndarray,
                  dataset: dict, model: str, seed: int, up: str = "dataset", extra: dict | None = None) -> None:
    """Write a samples file atomically. motions (N, T, J, 3), or a StreamedArray of row blocks
    (never whole in memory); dataset: the checkpoint's dataset description; model: the name to
    record (checkpoint.model_name). The same inputs give the same bytes."""
    if up not in UP_CHOICES:
        raise UserError(f"unknown --up {up!r}; valid: {', '.join(UP_CHOICES)}")
    sk = get_skeleton(dataset["skeleton"])
    rot = sk.y_up_rotation().astype(np.float32) if up == "y" else None
    if rot is not None:
        if isinstance(motions, StreamedArray):
            motions = StreamedArray(motions.shape, motions.dtype, (b @ rot.T for b in motions.blocks))
        else:
            motions = motions @ rot.T
        end_points = end_points @ rot.T
    save_npz(path, motions=motions, actions=np.asarray(actions).astype(str), modes=modes, codes=codes,
             end_points=end_points, end_mask=end_mask, fps=np.float32(dataset["fps"]),
             dataset=np.str_(dataset["name"]), skeleton=np.str_(sk.name), joint_names=np.array(sk.joint_names),
             parents=np.array(sk.parents), up_axis=np.str_("+y" if up == "y" else dataset["up_axis"]),
             units=np.str_(dataset.get("units", "m")), format_version=np.int64(FORMAT_VERSION),
             model=np.str_(model), seed=np.int64(seed), **(extra or {}))


def read_samples(path: str | Path, keys: tuple[str, ...] = ("motions", "actions"), rows: slice = slice(None),
                 optional: tuple[str, ...] = ()) -> dict:
    """A samples file's arrays with motions and end points in the dataset's own frame (a file
    written with `--up y` is turned back), plus "skeleton", "fps" and "n" (the number of motions).

    rows: only these motions (the file is read lazily); `optional` keys are None when absent.
    UserError when the file is missing or unreadable or lacks one of `keys`.
    """
    path = Path(path)
    if not path.is_file():
        raise UserError(f"samples file not found: {path}")
    if path.stat().st_size == 0:
        raise UserError(f"cannot read {path}: the file is empty")
    if not zipfile.is_zipfile(path):
        raise UserError(f"cannot read {path}: not an .npz samples file (not a zip archive)")
    try:
        with np.load(path, allow_pickle=False) as f:
            missing = [k for k in keys if k not in f]
            if missing:
                raise UserError(f"{path} is not an odmo samples file (no {missing[0]})")
            out = {k: (f[k][rows] if k in ROW_KEYS else f[k]) if k in f else None for k in keys + optional}
            out["skeleton"], out["fps"] = str(f["skeleton"]), float(f["fps"])
            up = str(f["up_axis"]) if "up_axis" in f else None
            out["n"] = len(f["motions"]) if "motions" in f else 0
    except KeyError as exc:
        raise UserError(f"{path} is not an odmo samples file (no {exc.args[0]})") from None
    except (ValueError, OSError, EOFError, zipfile.BadZipFile) as exc:
        raise UserError(f"cannot read {path}: {exc}") from None
    try:
        sk = get_skeleton(out["skeleton"])
    except UserError as exc:
        raise UserError(f"{path}: {exc}") from None
    if up is not None and up != sk.up_axis:
        if up != "+y":
            raise UserError(f"{path}: up axis {up!r} is neither the skeleton's ({sk.up_axis}) nor +y")
        back = sk.y_up_rotation()  # the inverse of a proper rotation is its transpose: x @ R
        for k in ("motions", "end_points"):
            if out.get(k) is not None:
                out[k] = (out[k] @ back).astype(out[k].dtype)
    return out
