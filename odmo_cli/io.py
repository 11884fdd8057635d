"""Safe file writing: everything goes to a temp file in the target folder, then is renamed."""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass
import tempfile
import zipfile
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np
import torch

from odmo_cli.errors import UserError


@contextlib.contextmanager
def atomic_path(path: str | Path, suffix: str = "") -> Iterator[Path]:
    """Yield a temp path beside `path`; rename it onto `path` only if the block succeeds.

    On any exception the temp file is removed, so a failed write leaves nothing behind.
    `suffix` ends the temp name, for writers that pick the format from the extension.
    """
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise UserError(f"cannot write {path}: folder {folder} does not exist")
    if not os.access(folder, os.W_OK):
        raise UserError(f"cannot write {path}: folder {folder} is not writable")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + suffix, dir=folder)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.chmod(tmp_path, 0o666 & ~_umask())  # mkstemp makes 0600; give the usual permissions
        os.replace(tmp_path, path)
    except BaseException:
        tmp_path.unlink(missing_ok=True)
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@dataclass
class StreamedArray:
    """An array written batch by batch: its full shape and dtype, and an iterator of row blocks."""

    shape: tuple[int, ...]
    dtype: np.dtype
    blocks: Iterable[np.ndarray]


def save_npz(path: str | Path, **arrays) -> None:
    """Write an uncompressed .npz atomically, byte-for-byte reproducible (fixed zip timestamps).

    A StreamedArray value is written block by block, so it is never whole in memory.
    """
    with atomic_path(path) as tmp:
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED) as zf:
            for name, value in arrays.items():
                info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
                with zf.open(info, "w", force_zip64=True) as f:
                    if isinstance(value, StreamedArray):
                        _write_streamed(f, value)
                    else:
                        np.lib.format.write_array(f, np.asanyarray(value), allow_pickle=False)


def _write_streamed(f, value: StreamedArray) -> None:
    header = {"descr": np.lib.format.dtype_to_descr(np.dtype(value.dtype)), "fortran_order": False,
              "shape": tuple(value.shape)}
    try:  # the header version np.save would choose, so streamed and whole arrays give the same bytes
        np.lib.format.write_array_header_1_0(f, header)
    except ValueError:
        np.lib.format.write_array_header_2_0(f, header)
    rows = 0
    for block in value.blocks:
        block = np.ascontiguousarray(block, dtype=value.dtype)
        f.write(block.tobytes())
        rows += len(block)
    if rows != value.shape[0]:
        raise ValueError(f"streamed {rows} rows, the header says {value.shape[0]}")


def read_samples(path: str | Path, keys: tuple[str, ...] = ("motions", "actions"), rows: slice = slice(None),
                 optional: tuple[str, ...] = ()) -> dict:
    """A samples file's arrays (docs/formats.md) with motions and end points in the dataset's own
    frame (a file written with `--up y` is turned back), plus "skeleton" and "fps".

    rows: only these motions (the file is read lazily); `optional` keys are None when absent.
    UserError when the file is missing or unreadable or lacks one of `keys`.
    """
    from odmo_cli.skeletons import get_skeleton

    path = Path(path)
    if not path.is_file():
        raise UserError(f"samples file not found: {path}")
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
    except (ValueError, OSError, zipfile.BadZipFile) as exc:
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


ROW_KEYS = ("motions", "actions", "modes", "codes", "end_points", "end_mask")


def save_checkpoint(path: str | Path, payload: dict) -> None:
    """Write a checkpoint atomically. The payload must hold only tensors and plain values."""
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)


def load_checkpoint(path: str | Path) -> dict:
    """Load a checkpoint without unpickling classes (safe for untrusted files)."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"checkpoint not found: {path}")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises several types for bad or unsafe files
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise UserError(f"cannot load checkpoint {path}: {first}") from None
    if not isinstance(payload, dict):
        raise UserError(f"cannot load checkpoint {path}: not an odmo checkpoint (no dict inside)")
    return payload


def describe_checkpoint(path: str | Path) -> dict:
    """The plain-value parts of a checkpoint: what `odmo info` prints."""
    ckpt = load_checkpoint(path)
    if "kind" not in ckpt or "config" not in ckpt:
        raise UserError(f"{path} is not an odmo checkpoint (no model kind or config inside)")
    state = ckpt.get("state_dict", {})
    # buffers such as A2M's bone-length bank are data, not parameters
    n_params = sum(t.numel() for k, t in state.items() if k != "bone_bank")
    bank = ckpt.get("latent_bank")
    last = ckpt.get("history", [])[-1:] or [{}]
    banks = {"latent_bank": f"{len(bank['codes'])} codes" if bank else "none (training not finished)"}
    if ckpt["kind"] == "a2m":
        banks = {"bone_bank": f"{len(state['bone_bank'])} real bone-length sets for sampling"}
    return {
        "file": str(path), "format_version": ckpt.get("format_version"), "kind": ckpt["kind"],
        "parameters": n_params, "weights": ckpt.get("weights_dtype", "float32"),
        "epoch": ckpt.get("epoch"), "dataset": ckpt.get("dataset", {}),
        "config": ckpt["config"], "train_config": ckpt.get("train_config", {}), **banks,
        "last_epoch_losses": {k: round(v, 5) if isinstance(v, float) else v for k, v in last[0].items()},
        "report": ckpt.get("report", {}),
    }
