"""`odmo bench` runs and reports its figures (speed itself is never asserted in tests)."""

from __future__ import annotations

import json

from typer.testing import CliRunner

from odmo_cli.cli import app


def test_bench_sampling_reports_median_min_max(tmp_path):
    out = tmp_path / "bench.json"
    res = CliRunner().invoke(app, ["bench", "--only", "sampling", "--runs", "2", "--json", str(out)])
    assert res.exit_code == 0, res.output
    report = json.loads(out.read_text())
    names = [f["name"] for f in report["figures"]]
    assert names == ["model load", "sampling throughput (n = 996, T = 60)"]
    for f in report["figures"]:
        assert f["runs"] == 2 and f["min"] <= f["median"] <= f["max"] and f["min"] > 0
        assert f["note"] in ("untrained network, HumanAct12 shapes", "")  # "" once a model ships
    assert report["machine"]["cores"] >= 1


def test_bench_bad_part():
    res = CliRunner().invoke(app, ["bench", "--only", "gpu"])
    assert res.exit_code == 2
    assert "unknown benchmark part 'gpu'; valid: sampling, end-to-end, training, evaluation" in res.stderr


def test_bench_unknown_model(tmp_path):
    res = CliRunner().invoke(app, ["bench", "--model", str(tmp_path / "missing.pt"), "--only", "sampling"])
    assert res.exit_code == 2
    assert "give a checkpoint file or a shipped name (humanact12, cmu)" in res.stderr
