"""Download a dataset's directly downloadable files (`[[files]]` in its manifest), verified.

Each `[[files]]` entry names a `url`, a `path` relative to the dataset folder, its `sha256`, and
optionally its `size` in bytes and `archive = "zip" | "tar"`. `fetch_dataset` brings the folder
up to date:

* a file already at `dest/path` whose SHA-256 matches is left alone (reported as present);
* otherwise the file is downloaded (stdlib `urllib` only) into `dest/.<name>.part`, next to its
  destination. An interrupted download is resumed with `Range: bytes=N-`; a server answering
  200 instead of 206 (no range support) makes it start again from zero. Connection errors,
  time-outs, truncated bodies and 5xx answers are retried up to `retries` times, each retry
  resuming where the last one stopped;
* once the body is complete its SHA-256 is checked. On a mismatch the `.part` file is deleted
  and the file is reported as failed ("checksum mismatch for <path>: ..."). A mismatch after a
  resumed download is first retried once from zero, since the old bytes may come from another
  version of the file. Only a verified file is renamed (`os.replace`) onto `dest/path`, so the
  destination never holds a partial or corrupt file;
* when the retries run out the `.part` file is kept, so running the fetch again resumes it;
* an entry with `archive` is unpacked into `dest` after verification and before the rename.
  Every member is checked first (no absolute paths, no `..`, no links or devices), so an unsafe
  archive extracts nothing; each member is written atomically. The archive itself is kept at
  `dest/path`: its presence marks the entry as done, so a later fetch neither downloads nor
  extracts it again (delete the archive to extract it anew).

Files are fetched in manifest order; a failure does not stop the others. If any file failed,
`FetchError` (a `UserError`, so the CLI prints one line and exits 2) is raised at the end,
carrying the `FetchReport` in `.report`. A manifest without `[[files]]` whose sources are
browser-only pages (`kind = "folder-page"`, e.g. Google Drive folders) raises a `UserError`
telling the user where to download it by hand.
"""

from __future__ import annotations

import http.client
import os
import re
import shutil
import socket
import stat
import tarfile
import tempfile
import time
import urllib.error
import urllib.parse
import urllib.request
import zipfile
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Callable, Optional

from odmo_cli.data.manifest import Manifest, sha256_file
from odmo_cli.errors import UserError

Progress = Callable[[str, int, Optional[int]], None]

CHUNK = 1 << 16
USER_AGENT = "odmo-fetch/0.1 (+python urllib)"
ARCHIVES = ("zip", "tar")
_SHA256 = re.compile(r"^[0-9a-fA-F]{64}$")
_FATAL_HTTP = {401: "access denied", 403: "access denied", 404: "not found", 410: "gone"}
_RETRY_HTTP = {408, 425, 429}  # plus every 5xx


@dataclass
class FetchReport:
    """What `fetch_dataset` did, entry by entry (paths relative to `dest`)."""

    dest: Path
    downloaded: list[str] = field(default_factory=list)  # fetched and verified in this run
    present: list[str] = field(default_factory=list)  # already there with the right checksum
    failed: list[tuple[str, str]] = field(default_factory=list)  # (path, one-line reason)
    extracted: list[str] = field(default_factory=list)  # archive members written

    @property
    def ok(self) -> bool:
        return not self.failed


class FetchError(UserError):
    """One or more files could not be fetched; `.report` tells which ones and why."""

    def __init__(self, message: str, report: FetchReport):
        super().__init__(message)
        self.report = report


@dataclass(frozen=True)
class _Entry:
    url: str
    rel: str
    sha256: str
    size: int | None
    archive: str | None


class _Retry(Exception):
    """A transient failure: try again (resuming) if attempts remain."""


class _Fail(Exception):
    """A permanent failure for this file; the message is the reason."""


def fetch_dataset(
    manifest: Manifest,
    dest: Path,
    *,
    progress: Progress | None = None,
    timeout: float = 30.0,
    retries: int = 3,
    retry_delay: float = 1.0,
) -> FetchReport:
    """Download and verify every `[[files]]` entry of `manifest` into the folder `dest`.

    `progress(path, bytes_so_far, total_or_None)` is called as bytes arrive. `timeout` is the
    socket time-out in seconds for each request; `retries` the number of extra attempts after a
    transient failure, waiting `retry_delay * attempt` seconds before each. Raises `UserError`
    for a browser-only manifest, an invalid `[[files]]` entry or an unwritable `dest`, and
    `FetchError` (a `UserError`) after trying all files if any of them failed.
    """
    dest = Path(dest).expanduser()
    if not manifest.files:
        raise UserError(_manual_message(manifest, dest))
    entries = [_entry(manifest, i, raw) for i, raw in enumerate(manifest.files)]
    _prepare_dest(dest)
    root = dest.resolve()
    report = FetchReport(dest=dest)
    for e in entries:
        try:
            if _fetch_one(e, dest, root, report, progress, timeout, max(0, int(retries)), retry_delay):
                report.present.append(e.rel)
            else:
                report.downloaded.append(e.rel)
        except _Fail as exc:
            report.failed.append((e.rel, str(exc)))
    if report.failed:
        first = report.failed[0][1]
        more = report.failed[1:]
        if more:
            first += f" ({len(more)} more failed: {', '.join(rel for rel, _ in more)})"
        raise FetchError(first, report)
    return report


# --- manifest checks ------------------------------------------------------------------------


def _manual_message(m: Manifest, dest: Path) -> str:
    pages = [s for s in m.sources if isinstance(s, dict) and s.get("kind") == "folder-page"]
    if not pages:
        where = f" (see {m.homepage})" if m.homepage else ""
        return f"dataset {m.name} lists no downloadable files in its manifest{where}"
    urls = " or ".join(str(s.get("url", "")) for s in pages)
    notes = " ".join(str(s.get("note", "")).strip() for s in pages if s.get("note"))
    notes = re.sub(r"\bDIR\b", str(dest), " ".join(notes.split()))  # one line, DIR spelled out
    msg = (
        f"dataset {m.name} cannot be downloaded automatically: download it in a browser from "
        f"{urls} and place it under {dest}"
    )
    if notes:
        msg += f" ({notes.rstrip('.')})"
    return msg + f"; then `odmo data info {m.name} --data {dest}` verifies it"


def _entry(m: Manifest, i: int, raw: dict) -> _Entry:
    where = f"manifest {m.name}: [[files]] entry {i + 1}"
    if not isinstance(raw, dict):
        raise UserError(f"{where} is not a table")
    for key in ("url", "path", "sha256"):
        if not isinstance(raw.get(key), str) or not raw[key].strip():
            raise UserError(f"{where} lacks the field {key!r}")
    url, rel, digest = raw["url"].strip(), raw["path"].strip(), raw["sha256"].strip()
    if urllib.parse.urlsplit(url).scheme not in ("http", "https"):
        raise UserError(f"{where}: url {url!r} is not http or https")
    bad = _unsafe_name(rel)
    if bad:
        raise UserError(f"{where}: path {rel!r} {bad}")
    if not _SHA256.match(digest):
        raise UserError(f"{where}: sha256 {digest!r} is not 64 hex digits")
    size = raw.get("size")
    if size is not None and (isinstance(size, bool) or not isinstance(size, int) or size < 0):
        raise UserError(f"{where}: size {size!r} is not a byte count")
    archive = raw.get("archive")
    if archive is not None and archive not in ARCHIVES:
        raise UserError(f"{where}: archive {archive!r} is not one of {', '.join(ARCHIVES)}")
    return _Entry(url, str(PurePosixPath(rel)), digest.lower(), size, archive)


def _unsafe_name(name: str) -> str:
    """Why `name` may not be written below the dataset folder, or "" if it may."""
    if "\\" in name:
        return "contains a backslash"
    p = PurePosixPath(name)
    if p.is_absolute() or re.match(r"^[A-Za-z]:", name):
        return "is absolute"
    if ".." in p.parts:
        return "contains '..'"
    if not p.parts or p == PurePosixPath("."):
        return "is empty"
    return ""


def _prepare_dest(dest: Path) -> None:
    try:
        dest.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"cannot create the dataset folder {dest}: {_os_reason(exc)}") from None
    if not os.access(dest, os.W_OK | os.X_OK):
        raise UserError(f"cannot write to the dataset folder {dest}: permission denied")


def _os_reason(exc: OSError) -> str:
    return exc.strerror or str(exc) or type(exc).__name__


# --- one file -------------------------------------------------------------------------------


def _fetch_one(e, dest, root, report, progress, timeout, retries, retry_delay) -> bool:
    """Bring one entry up to date; True if it was already present and verified."""
    final = dest / e.rel
    if not final.resolve().is_relative_to(root):
        raise _Fail(f"cannot write {e.rel}: it resolves outside {dest} (through a link)")
    part = final.parent / f".{final.name}.part"
    if final.is_file():
        try:
            if sha256_file(final) == e.sha256:
                return True
        except OSError as exc:
            raise _Fail(f"cannot read {final}: {_os_reason(exc)}") from None
    elif final.exists():
        raise _Fail(f"cannot write {e.rel}: {final} exists and is not a file")
    try:
        final.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise _Fail(f"cannot write {e.rel}: {_os_reason(exc)}") from None

    resumed = _download(e, part, progress, timeout, retries, retry_delay)
    got = _sha256(part, e.rel)
    if got != e.sha256 and resumed:
        # The earlier bytes may belong to another version of the file: once more from zero.
        part.unlink(missing_ok=True)
        _download(e, part, progress, timeout, retries, retry_delay)
        got = _sha256(part, e.rel)
    if got != e.sha256:
        part.unlink(missing_ok=True)
        raise _Fail(
            f"checksum mismatch for {e.rel}: expected {e.sha256}, got {got}; the file was not kept"
        )
    if e.archive:
        try:
            report.extracted.extend(_extract(part, e, dest, root))
        except BaseException:
            part.unlink(missing_ok=True)
            raise
    try:
        os.replace(part, final)
    except OSError as exc:
        raise _Fail(f"cannot write {e.rel}: {_os_reason(exc)}") from None
    return False


def _sha256(path: Path, rel: str) -> str:
    try:
        return sha256_file(path)
    except OSError as exc:
        raise _Fail(f"cannot read the download of {rel}: {_os_reason(exc)}") from None


def _download(e, part, progress, timeout, retries, retry_delay) -> bool:
    """Complete `part` from `e.url`, resuming it; True if bytes from an earlier attempt were kept."""
    resumed = False
    attempt = 0
    while True:
        try:
            if _attempt(e, part, progress, timeout):
                resumed = True
            return resumed
        except _Retry as exc:
            attempt += 1
            if attempt > retries:
                kept = part.is_file() and part.stat().st_size > 0
                tail = f"; the partial file {part.name} is kept, run again to resume" if kept else ""
                n = retries + 1
                raise _Fail(
                    f"cannot download {e.rel} from {e.url}: {exc} "
                    f"(after {n} attempt{'s' if n != 1 else ''}){tail}"
                ) from None
            if retry_delay > 0:
                time.sleep(retry_delay * attempt)


def _attempt(e: _Entry, part: Path, progress: Progress | None, timeout: float) -> bool:
    """One request. Returns True if it appended to existing bytes; raises _Retry or _Fail."""
    have = part.stat().st_size if part.is_file() else 0
    if e.size is not None and have > e.size:
        _truncate(part, e.rel)
        have = 0
    if e.size is not None and have == e.size and have > 0:
        return True  # complete from an earlier run; the checksum decides
    headers = {"User-Agent": USER_AGENT, "Accept-Encoding": "identity"}
    if have:
        headers["Range"] = f"bytes={have}-"
    req = urllib.request.Request(e.url, headers=headers)
    try:
        resp = urllib.request.urlopen(req, timeout=timeout)
    except urllib.error.HTTPError as exc:
        exc.close()
        if exc.code == 416 and have:
            total = _content_range(exc.headers.get("Content-Range", ""))[2]
            if total == have:
                return True  # the part already holds the whole file
            _truncate(part, e.rel)
            raise _Retry("the server refused to resume (HTTP 416)") from None
        if exc.code in _RETRY_HTTP or exc.code >= 500:
            raise _Retry(f"HTTP {exc.code} {exc.reason}") from None
        why = _FATAL_HTTP.get(exc.code, "refused")
        raise _Fail(f"cannot download {e.rel} from {e.url}: {why} (HTTP {exc.code})") from None
    except urllib.error.URLError as exc:
        raise _Retry(_net_reason(exc.reason)) from None
    except (OSError, http.client.HTTPException) as exc:
        raise _Retry(_net_reason(exc)) from None

    with resp:
        status = resp.status
        length = resp.headers.get("Content-Length")
        length = int(length) if length and length.isdigit() else None
        if status == 206 and have:
            start, _, total = _content_range(resp.headers.get("Content-Range", ""))
            if start != have:
                _truncate(part, e.rel)
                raise _Retry("the server resumed at the wrong offset")
            if total is None and length is not None:
                total = have + length
            mode, appended = "ab", True
        elif status == 200 or (status == 206 and not have):
            have, total, mode, appended = 0, length, "wb", False  # no range support: from zero
        else:
            raise _Fail(f"cannot download {e.rel} from {e.url}: unexpected HTTP {status}")
        if total is None:
            total = e.size
        if progress:
            progress(e.rel, have, total)
        try:
            f = open(part, mode)
        except OSError as exc:
            raise _Fail(f"cannot write {e.rel}: {_os_reason(exc)}") from None
        with f:
            while True:
                try:
                    chunk = resp.read(CHUNK)
                except (OSError, http.client.HTTPException) as exc:
                    raise _Retry(_net_reason(exc)) from None
                if not chunk:
                    break
                try:
                    f.write(chunk)
                except OSError as exc:
                    raise _Fail(f"cannot write {e.rel}: {_os_reason(exc)}") from None
                have += len(chunk)
                if progress:
                    progress(e.rel, have, total)
                if e.size is not None and have > e.size:
                    break  # more than the manifest's size: the checksum will say no
    if total is not None and have < total:
        raise _Retry(f"the connection closed after {have} of {total} bytes")
    return appended


def _truncate(part: Path, rel: str) -> None:
    try:
        part.unlink(missing_ok=True)
    except OSError as exc:
        raise _Fail(f"cannot write {rel}: {_os_reason(exc)}") from None


def _content_range(value: str) -> tuple[int | None, int | None, int | None]:
    """(start, end, total) of a `Content-Range: bytes a-b/n` header; None where absent."""
    m = re.match(r"^\s*bytes\s+(?:(\d+)-(\d+)|\*)/(\d+|\*)\s*$", value or "")
    if not m:
        return None, None, None
    start, end, total = m.groups()
    as_int = lambda s: int(s) if s and s != "*" else None  # noqa: E731
    return as_int(start), as_int(end), as_int(total)


def _net_reason(reason) -> str:
    if isinstance(reason, (socket.timeout, TimeoutError)):
        return "timed out"
    if isinstance(reason, socket.gaierror):
        return "host not found"
    if isinstance(reason, ConnectionRefusedError):
        return "connection refused"
    if isinstance(reason, (ConnectionResetError, http.client.RemoteDisconnected)):
        return "connection closed by the server"
    if isinstance(reason, http.client.IncompleteRead):
        return "the connection closed mid-transfer"
    if isinstance(reason, OSError) and reason.strerror:
        return reason.strerror
    text = str(reason).strip()
    return text.splitlines()[0] if text else type(reason).__name__


# --- archives -------------------------------------------------------------------------------


def _extract(archive: Path, e: _Entry, dest: Path, root: Path) -> list[str]:
    """Unpack a verified archive into `dest` after checking every member; returns member paths."""
    try:
        if e.archive == "zip":
            return _extract_zip(archive, e, dest, root)
        return _extract_tar(archive, e, dest, root)
    except (zipfile.BadZipFile, tarfile.TarError, EOFError) as exc:
        raise _Fail(f"cannot extract {e.rel}: not a valid {e.archive} archive ({exc})") from None


def _check_member(name: str, e: _Entry, dest: Path, root: Path) -> Path:
    stripped = name.rstrip("/")
    if stripped and PurePosixPath(stripped) == PurePosixPath("."):
        return dest  # the "./" entry of `tar -C dir .`: the dataset folder itself
    bad = _unsafe_name(stripped) if stripped else "is empty"
    target = dest / name
    if not bad and not target.resolve().is_relative_to(root):
        bad = "resolves outside the dataset folder"
    if bad:
        raise _Fail(f"unsafe archive {e.rel}: member {name!r} {bad}; nothing was extracted")
    return target


def _extract_zip(archive: Path, e: _Entry, dest: Path, root: Path) -> list[str]:
    with zipfile.ZipFile(archive) as zf:
        plan = []
        for info in zf.infolist():
            target = _check_member(info.filename, e, dest, root)
            mode = info.external_attr >> 16
            if stat.S_ISLNK(mode):
                raise _Fail(
                    f"unsafe archive {e.rel}: member {info.filename!r} is a link; nothing was extracted"
                )
            plan.append((info, target))
        written = []
        for info, target in plan:
            if info.is_dir():
                _mkdir(target, e)
                continue
            with zf.open(info) as src:
                _write_atomic(src, target, e)
            written.append(str(PurePosixPath(info.filename)))
        return written


def _extract_tar(archive: Path, e: _Entry, dest: Path, root: Path) -> list[str]:
    with tarfile.open(archive, "r:*") as tf:
        plan = []
        for m in tf.getmembers():
            target = _check_member(m.name, e, dest, root)
            if not (m.isfile() or m.isdir()):
                raise _Fail(
                    f"unsafe archive {e.rel}: member {m.name!r} is a link or special file; "
                    "nothing was extracted"
                )
            plan.append((m, target))
        written = []
        for m, target in plan:
            if m.isdir():
                _mkdir(target, e)
                continue
            src = tf.extractfile(m)
            if src is None:  # pragma: no cover - isfile() members always have data
                continue
            with src:
                _write_atomic(src, target, e)
            written.append(str(PurePosixPath(m.name)))
        return written


def _mkdir(target: Path, e: _Entry) -> None:
    try:
        target.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise _Fail(f"cannot extract {e.rel} into {target}: {_os_reason(exc)}") from None


def _write_atomic(src, target: Path, e: _Entry) -> None:
    _mkdir(target.parent, e)
    tmp = None
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
        with os.fdopen(fd, "wb") as out:
            shutil.copyfileobj(src, out, CHUNK)
        os.replace(tmp, target)
    except OSError as exc:
        if tmp:
            Path(tmp).unlink(missing_ok=True)
        raise _Fail(f"cannot extract {e.rel} into {target}: {_os_reason(exc)}") from None
