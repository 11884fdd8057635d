"""The `odmo data ...` commands through typer's CliRunner (and `python -m odmo_cli` in a subprocess).

Errors a user can cause end with exit status 2, one line `error: ...` on stderr, no traceback,
and nothing written. Real-data tests read $ODMO_DATA_DIR and are skipped when it is unset.
"""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from odmo_cli.cli import app

HUMANACT12_COUNTS = [215, 47, 50, 94, 88, 218, 54, 77, 56, 61, 140, 91]
CMU_COUNTS = {"walk": 474, "run": 109, "jump": 108, "animal_behavior": 101, "dance": 77, "step": 68,
              "climb": 33}


@pytest.fixture
def run(tmp_path, monkeypatch):
    """Invoke `odmo ARGS...` inside tmp_path/cwd (so stray outputs would be seen there)."""
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    monkeypatch.chdir(cwd)
    runner = CliRunner()

    def invoke(*args):
        return runner.invoke(app, [str(a) for a in args])

    return invoke


def _stderr(result) -> str:
    try:
        return result.stderr
    except ValueError:  # older click/typer: stderr mixed into output
        return result.output


def _ok(result) -> str:
    assert result.exit_code == 0, f"exit {result.exit_code}\n{result.output}\n{result.exception!r}"
    return result.stdout


def _json(result) -> dict:
    return json.loads(_ok(result))


def _listing(folder: Path) -> list[str]:
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*"))


def assert_user_error(result, *fragments: str) -> str:
    """Exit 2, one line `error: ...` on stderr naming `fragments`, nothing on stdout, no traceback."""
    err = _stderr(result)
    assert result.exit_code == 2, f"exit {result.exit_code}; output:\n{result.output}\n{result.exception!r}"
    assert isinstance(result.exception, SystemExit) or result.exception is None, repr(result.exception)
    assert result.stdout == ""
    assert err.startswith("error: ") and err.endswith("\n"), repr(err)
    assert err.count("\n") == 1, f"not one line: {err!r}"
    assert "Traceback" not in result.output
    for fragment in fragments:
        assert fragment in err, f"{fragment!r} not in {err!r}"
    return err


# ================================================================ help and entry points


def test_help_lists_subcommands(run):
    out = _ok(run("--help"))
    for name in ("data", "train", "info"):
        assert name in out
    data_help = _ok(run("data", "--help"))
    for name in ("list", "info", "fetch", "prepare", "show"):
        assert name in data_help


def test_no_args_shows_help(run):
    result = run("data")
    assert "prepare" in result.output and "show" in result.output
    assert "Traceback" not in result.output


def test_python_dash_m(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "odmo_cli", "--help"], capture_output=True, text=True,
                          timeout=120, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "data" in proc.stdout and "Usage" in proc.stdout
    proc = subprocess.run([sys.executable, "-m", "odmo_cli", "data", "info", "nosuch_dataset"],
                          capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert proc.returncode == 2
    assert proc.stderr.startswith("error: unknown dataset 'nosuch_dataset'") and proc.stderr.count("\n") == 1
    assert "Traceback" not in proc.stderr and proc.stdout == ""


# ================================================================ data list / info on real data


def test_info_humanact12(run, data_dir):
    j = _json(run("data", "info", "humanact12", "--data", data_dir / "humanact12", "--json"))
    assert j["name"] == "humanact12" and j["clips"] == 1191
    assert [a["clips"] for a in j["actions"]] == HUMANACT12_COUNTS
    assert [a["expected"] for a in j["actions"]] == HUMANACT12_COUNTS
    assert [a["name"] for a in j["actions"]][:3] == ["warm_up", "walk", "run"]
    assert sum(a["modes"] for a in j["actions"]) == 34
    assert j["digest_ok"] is True and j["missing"] == j["extra"] == j["corrupt"] == []
    assert j["skeleton"] == "humanact12" and j["fps"] == 20 and j["clip_length"] == 60
    assert Path(j["root"]) == data_dir / "humanact12" / "HumanAct12"


def test_info_cmu(run, data_dir):
    j = _json(run("data", "info", "cmu_mocap", "--data", data_dir, "--json"))
    assert j["clips"] == 970
    assert {a["name"]: a["clips"] for a in j["actions"]} == CMU_COUNTS
    assert j["digest_ok"] is True and j["skeleton"] == "cmu20"


def test_info_table(run, data_dir):
    out = _ok(run("data", "info", "cmu_mocap", "--data", data_dir))
    assert "970 clips" in out and "animal_behavior" in out and "all files match" in out


def test_list_json(run, data_dir, tmp_path):
    j = _json(run("data", "list", "--data", data_dir, "--json"))
    assert Path(j["data_root"]) == data_dir
    by_name = {d["name"]: d for d in j["datasets"]}
    assert {"humanact12", "cmu_mocap", "uestc"} <= set(by_name)
    assert by_name["humanact12"]["clips"] == 1191 and by_name["humanact12"]["actions"] == 12
    assert by_name["cmu_mocap"]["clips"] == 970 and by_name["cmu_mocap"]["skeleton"] == "cmu20"
    assert Path(by_name["humanact12"]["present"]) == data_dir / "humanact12" / "HumanAct12"
    assert Path(by_name["cmu_mocap"]["present"]) == data_dir / "cmu_a2m"
    assert by_name["uestc"]["present"] is None


def test_list_json_nothing_on_disk(run, tmp_path):
    j = _json(run("data", "list", "--data", tmp_path, "--json"))
    assert all(d["present"] is None for d in j["datasets"])
    assert "humanact12" in _ok(run("data", "list", "--data", tmp_path))


# ================================================================ data info on fixtures and demo


def test_info_demo(run):
    j = _json(run("data", "info", "humanact12", "--demo", "--json"))
    assert j["clips"] == 36 and [a["clips"] for a in j["actions"]] == [3] * 12
    assert j["digest_ok"] is None
    j = _json(run("data", "info", "cmu", "--demo", "--json"))
    assert j["clips"] == 21 and j["skeleton"] == "cmu20"


def test_info_lenient_reports_problems(run, humanact12_fixture):
    (sorted(humanact12_fixture.glob("*.npy"))[0]).write_bytes(b"garbage")
    j = _json(run("data", "info", humanact12_fixture, "--no-verify", "--json"))
    assert j["clips"] == 23 and len(j["problems"]) == 1 and "unreadable npy" in j["problems"][0]
    assert j["digest_ok"] is None


# ================================================================ data show


def test_show_demo_writes_gif(run, tmp_path):
    out = tmp_path / "jump.gif"
    result = run("data", "show", "humanact12", "--demo", "--action", "jump", "--n", "1", "--out", out)
    assert "wrote" in _ok(result)
    data = out.read_bytes()
    assert data[:6] in (b"GIF89a", b"GIF87a") and len(data) > 1000
    assert _listing(tmp_path / "cwd") == []
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no temp file left


# ================================================================ data prepare


def test_prepare_then_info(run, tmp_path, humanact12_fixture):
    out = tmp_path / "prepared"
    result = run("data", "prepare", humanact12_fixture, "--format", "humanact12", "--out", out)
    assert "24 clips" in _ok(result)
    assert (out / "index.csv").is_file() and (out / "dataset.toml").is_file()
    assert len(list(out.glob("*.npy"))) == 24
    src = _json(run("data", "info", humanact12_fixture, "--no-verify", "--json"))
    dst = _json(run("data", "info", out, "--json"))
    assert dst["clips"] == src["clips"] == 24
    assert [a["clips"] for a in dst["actions"]] == [a["clips"] for a in src["actions"]] == [2] * 12
    assert [a["modes"] for a in dst["actions"]] == [2] * 12
    assert dst["problems"] == [] and dst["digest_ok"] is None
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_prepare_cmu_then_show(run, tmp_path, cmu_fixture):
    out = tmp_path / "cmu_prepared"
    _ok(run("data", "prepare", cmu_fixture, "--format", "cmu_a2m", "--out", out))
    j = _json(run("data", "info", out, "--json"))
    assert j["clips"] == 14 and j["skeleton"] == "cmu20"
    png = tmp_path / "climb.png"
    _ok(run("data", "show", out, "--action", "Climb", "--n", "1", "--out", png))
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# ================================================================ bad input: exit 2, one line, nothing written


def _bad_humanact12(folder: Path, kind: str, spoil) -> None:
    if kind == "empty_class":
        for p in folder.glob("*A12??.npy"):
            p.unlink()
    else:
        spoil(sorted(folder.glob("*.npy"))[3], kind)


@pytest.mark.parametrize("kind,fragments", [
    ("garbage", ["unreadable npy"]),
    ("nan", ["non-finite"]),
    ("joints", ["22 joints, skeleton humanact12 has 24"]),
    ("empty_class", ["empty classes", "throw"]),
])
def test_prepare_bad_source_writes_nothing(run, tmp_path, humanact12_fixture, spoil_clip, kind, fragments):
    _bad_humanact12(humanact12_fixture, kind, spoil_clip)
    before = _listing(tmp_path)
    out = tmp_path / "out"
    assert_user_error(run("data", "prepare", humanact12_fixture, "--format", "humanact12", "--out", out),
                      *fragments)
    assert not out.exists()
    assert _listing(tmp_path) == before  # no output and no temp folder


@pytest.mark.parametrize("kind,fragments", [
    ("garbage", ["unreadable npy"]), ("nan", ["non-finite"]), ("joints", ["22 joints"]),
    ("empty_class", ["empty classes", "throw"]),
])
def test_show_bad_source(run, tmp_path, humanact12_fixture, spoil_clip, kind, fragments):
    _bad_humanact12(humanact12_fixture, kind, spoil_clip)
    assert_user_error(run("data", "show", humanact12_fixture, "--action", "walk", "--n", "1",
                          "--out", tmp_path / "x.gif"), *fragments)
    assert not (tmp_path / "x.gif").exists()
    assert _listing(tmp_path / "cwd") == []


def test_missing_folder(run, tmp_path):
    assert_user_error(run("data", "info", tmp_path / "nope"), "unknown dataset", "nope")
    assert_user_error(run("data", "info", "humanact12", "--data", tmp_path / "nope"),
                      "dataset humanact12 not found under", "--data")
    out = tmp_path / "out"
    assert_user_error(run("data", "prepare", tmp_path / "nope", "--format", "humanact12", "--out", out),
                      "dataset folder not found")
    assert not out.exists()


def test_unknown_action_in_motion_folder(run, tmp_path, make_motion_folder):
    folder = make_motion_folder(tmp_path / "mf", actions=["walk", "run", "moonwalk"])
    assert_user_error(run("data", "info", folder), "'moonwalk'", "not in the manifest", "valid: warm_up")
    out = tmp_path / "out"
    assert_user_error(run("data", "prepare", folder, "--format", "folder", "--out", out), "'moonwalk'")
    assert not out.exists()


def test_bad_mode_in_motion_folder(run, tmp_path, make_motion_folder):
    folder = make_motion_folder(tmp_path / "mf")
    index = folder / "index.csv"
    lines = index.read_text().splitlines()
    lines[3] = lines[3].replace(",0,", ",fast,", 1)  # clip002's mode column
    index.write_text("\n".join(lines) + "\n")
    assert_user_error(run("data", "info", folder), "mode 'fast' of clip002 is not an integer")


def test_empty_class_motion_folder(run, tmp_path, make_motion_folder):
    folder = make_motion_folder(tmp_path / "mf", actions=["walk", "run"] * 3)
    out = tmp_path / "out"
    assert_user_error(run("data", "prepare", folder, "--format", "folder", "--out", out),
                      "empty classes", "warm_up")
    assert not out.exists()
    j = _json(run("data", "info", folder, "--json"))  # info is lenient: reports, exit 0
    assert j["clips"] == 6 and any("empty classes" in p for p in j["problems"])


def test_unknown_dataset_name(run, tmp_path):
    assert_user_error(run("data", "info", "humanact13"), "unknown dataset 'humanact13'", "humanact12",
                      "cmu_mocap")
    assert_user_error(run("data", "show", "nosuch", "--action", "walk"), "unknown dataset 'nosuch'")
    assert_user_error(run("data", "info", "nosuch", "--demo"), "no demo subset for 'nosuch'")
    assert_user_error(run("data", "prepare", tmp_path, "--format", "fbx", "--out", tmp_path / "o"),
                      "unknown format 'fbx'", "humanact12", "bvh")
    assert_user_error(run("data", "prepare", tmp_path, "--format", "bvh", "--out", tmp_path / "o"),
                      "no .bvh files in")
    assert not (tmp_path / "o").exists()
    assert_user_error(run("data", "prepare", tmp_path, "--format", "folder", "--dataset", "nosuch",
                          "--out", tmp_path / "o"), "unknown dataset 'nosuch'")
    assert _listing(tmp_path / "cwd") == []


def test_show_unknown_action(run, tmp_path):
    assert_user_error(run("data", "show", "humanact12", "--demo", "--action", "fly", "--out", tmp_path / "a.gif"),
                      "unknown action 'fly'", "valid: warm_up", "throw")
    assert_user_error(run("data", "show", "humanact12", "--demo", "--action", "fly"), "unknown action")
    assert not (tmp_path / "a.gif").exists()
    assert _listing(tmp_path / "cwd") == []


def test_show_bad_options(run, tmp_path):
    assert_user_error(run("data", "show", "humanact12", "--demo", "--action", "walk", "--n", "0"), "--n")
    assert_user_error(run("data", "show", "humanact12", "--demo", "--action", "walk", "--n", "1",
                          "--out", tmp_path / "a.avi"), "a.avi", ".gif", ".mp4")
    assert_user_error(run("data", "show", "humanact12", "--demo", "--action", "walk", "--n", "1",
                          "--out", tmp_path / "no" / "a.gif"), "does not exist")
    assert _listing(tmp_path / "cwd") == [] and not (tmp_path / "a.avi").exists()


def test_prepare_into_existing_folder(run, tmp_path, humanact12_fixture):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    before = _listing(tmp_path)
    assert_user_error(run("data", "prepare", humanact12_fixture, "--format", "humanact12", "--out", out),
                      "already exists")
    assert _listing(tmp_path) == before and (out / "keep.txt").read_text() == "mine"


def test_prepare_folder_without_manifest(run, tmp_path, make_motion_folder):
    folder = make_motion_folder(tmp_path / "mf", with_manifest=False)
    assert_user_error(run("data", "info", folder), "no dataset.toml")
    out = tmp_path / "out"
    assert_user_error(run("data", "prepare", folder, "--format", "folder", "--out", out), "no dataset.toml")
    assert not out.exists()



def test_prepare_folder_with_named_manifest(run, tmp_path, make_motion_folder):
    folder = make_motion_folder(tmp_path / "uestc", manifest_name="uestc", per_action=1, length=12,
                                with_manifest=False)
    assert_user_error(run("data", "info", folder), "no dataset.toml", "uestc --data")
    out = tmp_path / "out"
    _ok(run("data", "prepare", folder, "--format", "folder", "--dataset", "uestc", "--out", out))
    with open(out / "index.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 40 and rows[0]["action"] == "standing_gastrocnemius_calf"
    j = _json(run("data", "info", out, "--json"))
    assert j["clips"] == 40 and j["skeleton"] == "uestc18" and [a["clips"] for a in j["actions"]] == [1] * 40
    j = _json(run("data", "info", "uestc", "--data", folder, "--json"))  # by name, --data pointing at it
    assert j["clips"] == 40
