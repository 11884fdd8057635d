"""What a user can get wrong with files gets one line, exit 2, and nothing written: an --out that cannot
be written or is a folder, samples files and checkpoints that are empty or not what they claim."""

from __future__ import annotations

import os

import pytest
from typer.testing import CliRunner

from odmo_cli.cli import app

runner = CliRunner()


@pytest.fixture(scope="module")
def samples(tmp_path_factory):
    path = tmp_path_factory.mktemp("s") / "s.npz"
    r = runner.invoke(app, ["sample", "--action", "jump", "--n", "2", "--out", str(path)])
    assert r.exit_code == 0, r.output
    return path


def one_line_error(args: list[str], *expected: str) -> str:
    r = runner.invoke(app, args)
    assert r.exit_code == 2, r.output
    text = r.output.strip()
    assert "Traceback" not in text and len(text.splitlines()) == 1 and text.startswith("error:"), text
    for part in expected:
        assert part in text, text
    return text


@pytest.mark.skipif(not os.path.isdir("/proc"), reason="needs /proc, a folder that takes no new file")
@pytest.mark.parametrize("args", [
    ["sample", "--action", "jump", "--n", "1", "--out", "/proc/x.npz"],
    ["render", "SAMPLES", "--out", "/proc/x.gif"],
    ["export", "SAMPLES", "--bvh", "/proc/bvh"],
])
def test_an_output_that_cannot_be_written(args, samples):
    one_line_error([str(samples) if a == "SAMPLES" else a for a in args], "/proc/")


def test_an_output_that_names_a_folder(tmp_path):
    (tmp_path / "d").mkdir()
    one_line_error(["sample", "--action", "jump", "--n", "1", "--out", str(tmp_path / "d")], "is a folder")
    assert os.listdir(tmp_path) == ["d"] and os.listdir(tmp_path / "d") == []  # nothing half-written


@pytest.mark.parametrize("content, message", [(b"", "the file is empty"), (os.urandom(1000), "not a zip archive"),
                                              (b"motion,action\n", "not a zip archive")])
def test_a_samples_file_that_is_not_one(tmp_path, content, message):
    path = tmp_path / "bad.npz"
    path.write_bytes(content)
    text = one_line_error(["render", str(path), "--out", str(tmp_path / "a.gif")], message)
    assert "allow_pickle" not in text  # never the advice to unpickle an unknown file
    assert sorted(os.listdir(tmp_path)) == ["bad.npz"]


@pytest.mark.parametrize("content, message", [(b"", "the file is empty"), (b"hello\n", "not a PyTorch checkpoint")])
def test_a_checkpoint_that_is_not_one(tmp_path, content, message):
    path = tmp_path / "notckpt.pt"
    path.write_bytes(content)
    one_line_error(["sample", "--model", str(path), "--action", "jump", "--n", "1", "--out", str(tmp_path / "s.npz")],
                   "notckpt.pt", message)
    assert sorted(os.listdir(tmp_path)) == ["notckpt.pt"]


def test_render_writes_beside_its_samples_by_default_at_a_readable_size(samples):
    from PIL import Image

    r = runner.invoke(app, ["render", str(samples)])
    assert r.exit_code == 0, r.output
    gif = samples.with_suffix(".gif")
    with Image.open(gif) as im:
        assert im.size[0] >= 480


def test_info_takes_the_checkpoint_as_its_argument():
    for args in (["info", "cmu"], ["info", "--model", "cmu"]):
        r = runner.invoke(app, args)
        assert r.exit_code == 0 and "cmu_mocap" in r.output, r.output
    one_line_error(["info", "cmu", "--model", "humanact12"], "give the checkpoint once")
