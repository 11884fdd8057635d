"""`odmo_cli.data.fetch`: verified, resumable downloads from a local HTTP server (127.0.0.1 only)."""

from __future__ import annotations

import hashlib
import io
import socket
import tarfile
import threading
import zipfile
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest

from odmo_cli.data.fetch import FetchError, fetch_dataset
from odmo_cli.data.manifest import load_manifest, sha256_file
from odmo_cli.errors import UserError

PAYLOAD = bytes(range(256)) * 400  # 102,400 bytes: several read chunks


def sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


class _Handler(BaseHTTPRequestHandler):
    """Serves `server.routes[path] = (bytes, mode)`; logs (path, Range header) per request.

    mode: "range" (honours Range), "norange" (always 200 with the whole body),
    "cut" (first request sends half the body then closes; later ones honour Range).
    """

    timeout = 5  # bound every socket operation of the handler

    def do_GET(self):  # noqa: N802 (http.server's naming)
        srv = self.server
        rng = self.headers.get("Range")
        with srv.lock:
            srv.log.append((self.path, rng))
            n_before = sum(1 for p, _ in srv.log[:-1] if p == self.path)
        route = srv.routes.get(self.path)
        if route is None:
            self.send_error(404)
            return
        data, mode = route
        if mode == "cut" and n_before == 0:
            self.send_response(200)
            self.send_header("Content-Length", str(len(data)))
            self.end_headers()
            self.wfile.write(data[: len(data) // 2])
            self.wfile.flush()
            self.close_connection = True
            return
        start = 0
        if rng and mode != "norange":
            start = int(rng.removeprefix("bytes=").split("-")[0])
        if start:
            body = data[start:]
            self.send_response(206)
            self.send_header("Content-Range", f"bytes {start}-{len(data) - 1}/{len(data)}")
        else:
            body = data
            self.send_response(200)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args):  # keep pytest output clean
        pass


@pytest.fixture
def server():
    srv = ThreadingHTTPServer(("127.0.0.1", 0), _Handler)
    srv.daemon_threads = True
    srv.routes, srv.log, srv.lock = {}, [], threading.Lock()
    srv.base = f"http://127.0.0.1:{srv.server_address[1]}"
    thread = threading.Thread(target=srv.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
    thread.start()
    try:
        yield srv
    finally:
        srv.shutdown()
        srv.server_close()
        thread.join(timeout=5)


def requests_for(srv, path: str) -> list:
    return [rng for p, rng in srv.log if p == path]


HEADER = """name = "toy"
format = "folder"
skeleton = "cmu20"
up_axis = "+y"
fps = 12
clip_length = 10

[[actions]]
name = "walk"
"""


def write_manifest(tmp_path: Path, files: list[dict] = (), sources: list[dict] = ()):
    text = HEADER
    for table, rows in (("files", files), ("sources", sources)):
        for row in rows:
            text += f"\n[[{table}]]\n"
            for k, v in row.items():
                text += f"{k} = {v}\n" if isinstance(v, int) else f'{k} = "{v}"\n'
    path = tmp_path / "toy.toml"
    path.write_text(text)
    return load_manifest(path)


def serve(srv, tmp_path, route, data, mode="range", rel="a.bin", digest=None, **extra):
    srv.routes[route] = (data, mode)
    entry = {"url": srv.base + route, "path": rel, "sha256": digest or sha(data), **extra}
    return write_manifest(tmp_path, [entry])


def fetch(manifest, dest, **kw):
    kw.setdefault("timeout", 5.0)
    kw.setdefault("retry_delay", 0.0)
    return fetch_dataset(manifest, dest, **kw)


def leftovers(dest: Path) -> list[str]:
    return sorted(p.name for p in dest.rglob("*") if p.name.endswith((".part", ".tmp")))


def test_good_download(server, tmp_path):
    m = serve(server, tmp_path, "/a.bin", PAYLOAD, rel="sub/a.bin")
    dest = tmp_path / "data"
    seen = []
    report = fetch(m, dest, progress=lambda rel, done, total: seen.append((rel, done, total)))
    out = dest / "sub" / "a.bin"
    assert out.read_bytes() == PAYLOAD and sha256_file(out) == sha(PAYLOAD)
    assert report.downloaded == ["sub/a.bin"] and report.present == [] and report.ok
    assert leftovers(dest) == []
    assert seen[-1] == ("sub/a.bin", len(PAYLOAD), len(PAYLOAD))
    assert [d for _, d, _ in seen] == sorted(d for _, d, _ in seen)


def test_present_file_is_not_downloaded_again(server, tmp_path):
    m = serve(server, tmp_path, "/a.bin", PAYLOAD)
    dest = tmp_path / "data"
    fetch(m, dest)
    assert len(requests_for(server, "/a.bin")) == 1
    report = fetch(m, dest)
    assert report.present == ["a.bin"] and report.downloaded == []
    assert len(requests_for(server, "/a.bin")) == 1


def test_wrong_file_at_destination_is_replaced(server, tmp_path):
    m = serve(server, tmp_path, "/a.bin", PAYLOAD)
    dest = tmp_path / "data"
    dest.mkdir()
    (dest / "a.bin").write_bytes(b"stale")
    report = fetch(m, dest)
    assert report.downloaded == ["a.bin"] and (dest / "a.bin").read_bytes() == PAYLOAD


def test_corrupted_download_is_not_kept(server, tmp_path):
    m = serve(server, tmp_path, "/a.bin", PAYLOAD[::-1], digest=sha(PAYLOAD))
    dest = tmp_path / "data"
    with pytest.raises(UserError, match=r"checksum mismatch for a\.bin: expected .*, got .*not kept") as info:
        fetch(m, dest)
    assert "\n" not in str(info.value)
    assert sha(PAYLOAD) in str(info.value) and sha(PAYLOAD[::-1]) in str(info.value)
    assert not (dest / "a.bin").exists()
    assert leftovers(dest) == []
    assert info.value.report.failed[0][0] == "a.bin"


def test_interrupted_download_resumes_with_range(server, tmp_path):
    m = serve(server, tmp_path, "/a.bin", PAYLOAD, mode="cut")
    dest = tmp_path / "data"
    report = fetch(m, dest)
    assert (dest / "a.bin").read_bytes() == PAYLOAD and report.downloaded == ["a.bin"]
    assert requests_for(server, "/a.bin") == [None, f"bytes={len(PAYLOAD) // 2}-"]
    assert leftovers(dest) == []


def test_interrupted_download_resumes_in_a_later_run(server, tmp_path):
    m = serve(server, tmp_path, "/a.bin", PAYLOAD, mode="cut")
    dest = tmp_path / "data"
    with pytest.raises(UserError, match=r"cannot download a\.bin .*closed.*kept, run again to resume"):
        fetch(m, dest, retries=0)
    assert not (dest / "a.bin").exists()
    assert (dest / ".a.bin.part").stat().st_size == len(PAYLOAD) // 2
    fetch(m, dest, retries=0)
    assert (dest / "a.bin").read_bytes() == PAYLOAD
    assert requests_for(server, "/a.bin")[-1] == f"bytes={len(PAYLOAD) // 2}-"
    assert leftovers(dest) == []


def test_server_without_range_support_restarts_from_zero(server, tmp_path):
    m = serve(server, tmp_path, "/a.bin", PAYLOAD, mode="norange")
    dest = tmp_path / "data"
    dest.mkdir()
    (dest / ".a.bin.part").write_bytes(PAYLOAD[:1000])  # left by an interrupted run
    report = fetch(m, dest)
    assert (dest / "a.bin").read_bytes() == PAYLOAD and report.downloaded == ["a.bin"]
    assert requests_for(server, "/a.bin") == ["bytes=1000-"]  # asked to resume, got 200: restarted
    assert leftovers(dest) == []


def test_stale_partial_file_is_discarded_on_mismatch(server, tmp_path):
    m = serve(server, tmp_path, "/a.bin", PAYLOAD)
    dest = tmp_path / "data"
    dest.mkdir()
    (dest / ".a.bin.part").write_bytes(b"x" * 1000)  # bytes of another version of the file
    fetch(m, dest)
    assert (dest / "a.bin").read_bytes() == PAYLOAD
    assert requests_for(server, "/a.bin") == ["bytes=1000-", None]


def test_http_404_is_a_user_error(server, tmp_path):
    m = write_manifest(tmp_path, [{"url": server.base + "/missing.bin", "path": "m.bin",
                                   "sha256": sha(b"")}])
    dest = tmp_path / "data"
    with pytest.raises(UserError, match=r"cannot download m\.bin .*not found \(HTTP 404\)"):
        fetch(m, dest)
    assert len(requests_for(server, "/missing.bin")) == 1  # not retried
    assert list(dest.iterdir()) == []


def test_unreachable_url_fails_after_retries(tmp_path):
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    m = write_manifest(tmp_path, [{"url": f"http://127.0.0.1:{port}/a.bin", "path": "a.bin",
                                   "sha256": sha(PAYLOAD)}])
    with pytest.raises(UserError, match=r"cannot download a\.bin .*\(after 3 attempts\)"):
        fetch(m, tmp_path / "data", retries=2)


def test_one_failure_does_not_stop_the_others(server, tmp_path):
    server.routes["/a.bin"] = (PAYLOAD, "range")
    m = write_manifest(tmp_path, [
        {"url": server.base + "/missing.bin", "path": "m.bin", "sha256": sha(b"")},
        {"url": server.base + "/a.bin", "path": "a.bin", "sha256": sha(PAYLOAD)},
    ])
    dest = tmp_path / "data"
    with pytest.raises(FetchError) as info:
        fetch(m, dest)
    assert info.value.report.downloaded == ["a.bin"]
    assert [rel for rel, _ in info.value.report.failed] == ["m.bin"]
    assert (dest / "a.bin").read_bytes() == PAYLOAD


def test_unwritable_destination_is_a_user_error(server, tmp_path):
    m = serve(server, tmp_path, "/a.bin", PAYLOAD)
    blocker = tmp_path / "plain-file"
    blocker.write_text("not a folder")
    with pytest.raises(UserError, match="cannot create the dataset folder"):
        fetch(m, blocker / "data")
    assert server.log == []


@pytest.mark.parametrize("bad, why", [("../up.bin", r"'\.\.'"), ("/abs.bin", "absolute")])
def test_manifest_paths_must_stay_inside_dest(server, tmp_path, bad, why):
    m = serve(server, tmp_path, "/a.bin", PAYLOAD, rel=bad)
    with pytest.raises(UserError, match=why):
        fetch(m, tmp_path / "data")
    assert server.log == []


def test_folder_page_manifest_asks_for_a_browser(tmp_path):
    url = "https://drive.google.com/drive/folders/abc"
    m = write_manifest(tmp_path, sources=[{"url": url, "kind": "folder-page",
                                           "note": "Place it so that DIR/pose_clip.csv exists."}])
    dest = tmp_path / "data"
    with pytest.raises(UserError) as info:
        fetch(m, dest)
    msg = str(info.value)
    assert "\n" not in msg and "browser" in msg and url in msg
    assert f"{dest}/pose_clip.csv" in msg
    assert f"odmo data info toy --data {dest}" in msg
    assert not dest.exists()


def zip_bytes(members: dict[str, bytes]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    return buf.getvalue()


def test_safe_zip_is_extracted(server, tmp_path):
    data = zip_bytes({"clips/a.npy": b"A" * 10, "labels.csv": b"motion,action\n"})
    m = serve(server, tmp_path, "/d.zip", data, rel="d.zip", archive="zip")
    dest = tmp_path / "data"
    report = fetch(m, dest)
    assert (dest / "clips" / "a.npy").read_bytes() == b"A" * 10
    assert (dest / "labels.csv").read_bytes() == b"motion,action\n"
    assert sorted(report.extracted) == ["clips/a.npy", "labels.csv"]
    assert sha256_file(dest / "d.zip") == sha(data)  # the archive is kept
    assert leftovers(dest) == []


def test_zip_with_parent_path_is_rejected(server, tmp_path):
    data = zip_bytes({"ok.txt": b"fine", "../evil": b"gotcha"})
    m = serve(server, tmp_path, "/d.zip", data, rel="d.zip", archive="zip")
    dest = tmp_path / "data"
    with pytest.raises(UserError, match=r"unsafe archive d\.zip: member '\.\./evil'.*nothing was extracted"):
        fetch(m, dest)
    assert not (tmp_path / "evil").exists()
    assert list(dest.iterdir()) == []  # neither ok.txt nor the archive nor a .part


def test_tar_with_symlink_is_rejected_and_safe_tar_extracted(server, tmp_path):
    def tar_bytes(link: bool) -> bytes:
        buf = io.BytesIO()
        with tarfile.open(fileobj=buf, mode="w:gz") as tf:
            info = tarfile.TarInfo("sub/x.txt")
            info.size = 3
            tf.addfile(info, io.BytesIO(b"xyz"))
            if link:
                ln = tarfile.TarInfo("escape")
                ln.type, ln.linkname = tarfile.SYMTYPE, "/etc"
                tf.addfile(ln)
        return buf.getvalue()

    bad = tar_bytes(True)
    m = serve(server, tmp_path, "/bad.tgz", bad, rel="bad.tgz", archive="tar")
    with pytest.raises(UserError, match="unsafe archive bad.tgz: member 'escape'"):
        fetch(m, tmp_path / "bad")
    assert list((tmp_path / "bad").iterdir()) == []

    good = tar_bytes(False)
    m = serve(server, tmp_path, "/good.tgz", good, rel="good.tgz", archive="tar")
    fetch(m, tmp_path / "good")
    assert (tmp_path / "good" / "sub" / "x.txt").read_bytes() == b"xyz"


# -- the command line ----------------------------------------------------------------------------

def test_cli_fetch_downloads_and_reports(server, tmp_path):
    from typer.testing import CliRunner

    from odmo_cli.cli import app

    m = serve(server, tmp_path, "/a.bin", PAYLOAD, rel="a.bin")
    dest = tmp_path / "data"
    res = CliRunner().invoke(app, ["data", "fetch", str(m.path), "--to", str(dest), "--json"])
    assert res.exit_code == 0, res.output
    assert '"downloaded": [\n    "a.bin"\n  ]' in res.stdout
    assert (dest / "a.bin").read_bytes() == PAYLOAD
    res = CliRunner().invoke(app, ["data", "fetch", str(m.path), "--to", str(dest)])
    assert res.exit_code == 0 and "1 already present and verified" in res.stdout


def test_cli_fetch_corrupted_is_exit_2_and_nothing_kept(server, tmp_path):
    from typer.testing import CliRunner

    from odmo_cli.cli import app

    m = serve(server, tmp_path, "/a.bin", PAYLOAD, rel="a.bin", digest=sha(b"other bytes"))
    dest = tmp_path / "data"
    res = CliRunner().invoke(app, ["data", "fetch", str(m.path), "--to", str(dest)])
    assert res.exit_code == 2 and "checksum mismatch for a.bin" in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1  # the bar that ran before leaves no text behind
    assert not (dest / "a.bin").exists() and leftovers(dest) == []
