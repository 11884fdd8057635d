"""Safe file writing: everything goes to a temp file in the target folder, then is renamed.

The formats built on it: samples files (odmo_cli.formats.samples), checkpoints (odmo_cli.checkpoint).
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass
import tempfile
import zipfile
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

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
    if path.is_dir():
        raise UserError(f"cannot write {path}: it is a folder; name a file")
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + suffix, dir=folder)
    except OSError as exc:  # a folder that says writable but takes no new file (/proc, a read-only mount)
        raise UserError(f"cannot write {path}: {exc.strerror or exc} in {folder}") from None
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.chmod(tmp_path, 0o666 & ~_umask())  # mkstemp makes 0600; give the usual permissions
        try:
            os.replace(tmp_path, path)
        except OSError as exc:
            raise UserError(f"cannot write {path}: {exc.strerror or exc}") from None
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
