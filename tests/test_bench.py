"""`odmo bench` runs and reports its figures (speed itself is never asserted in tests)."""

from __future__ import annotations

import json

import pytest
import torch
from typer.testing import CliRunner

from odmo_cli.evaluation.bench import count_flops, matmul_rate
from odmo_cli.cli import app


def test_bench_sampling_reports_median_min_max(tmp_path):
    out = tmp_path / "bench.json"
    peer = tmp_path / "peer.py"  # stands in for ../shared/peer/bench_peer.py: one JSON line, as it prints
    peer.write_text("import json, sys; a = sys.argv; "
                    "print(json.dumps({'motions_per_s': 500.0, 'n': int(a[a.index('--n') + 1])}))\n")
    res = CliRunner().invoke(app, ["bench", "--only", "sampling", "--runs", "2", "--peer", str(peer), "--out", str(out)])
    assert res.exit_code == 0, res.output
    report = json.loads(out.read_text())
    names = [f["name"] for f in report["figures"]]
    assert names == ["model load", "sampling throughput (n = 996, T = 60)",
                     "`odmo sample --action all --n 84` after load: codes, end points, networks, file",
                     "the authors' networks alone, 1008 motions (bench_peer.py, same run)",
                     "`odmo sample` over the authors' networks"]
    figures = {f["name"]: f for f in report["figures"]}
    for f in report["figures"]:
        assert f["runs"] == 2 and f["min"] <= f["median"] <= f["max"] and f["min"] > 0
    for name in names[:3]:
        assert figures[name]["note"] == ""  # the shipped model, not an untrained stand-in
    ours, theirs, ratio = (figures[n] for n in names[2:])
    assert theirs["median"] == 500.0 and ratio["median"] == pytest.approx(ours["median"] / 500.0)
    assert report["machine"]["cores"] >= 1


def test_bench_evaluation_beside_the_authors_networks(tmp_path, monkeypatch):
    """The protocol's seconds and, from the peer's motions/s in the same run, the seconds their
    networks take to generate the protocol's motions (10 repeats x per_action x actions)."""
    from odmo_cli.evaluation import bench, protocol

    peer = tmp_path / "peer.py"
    peer.write_text("import json; print(json.dumps({'motions_per_s': 500.0}))\n")
    calls = []

    def fake_run(models, dataset, data, classifier, cfg, device=None):
        calls.append(cfg.repeats)
        row = {"per_action": 5, "by_action": {f"a{i}": 100.0 for i in range(12)}}
        return protocol.Report("humanact12", "clf.pt", {}, rows=[{"name": "Real"}, row])

    monkeypatch.setattr(protocol, "run_evaluation", fake_run)
    figures = bench.bench_evaluation(None, None, 2, torch.device("cpu"), peer)
    assert calls == [10, 10]
    ours, theirs, ratio = figures
    assert ours.name.startswith("evaluation protocol, humanact12") and ours.unit == "s"
    assert "600 motions" in theirs.name and theirs.runs == [600 / 500.0, 600 / 500.0]
    assert ratio.runs == pytest.approx([a / 1.2 for a in ours.runs])
    assert len(bench.bench_evaluation(None, None, 1, torch.device("cpu"), None)) == 1  # no peer: no reference


def test_bench_bad_part():
    res = CliRunner().invoke(app, ["bench", "--only", "gpu"])
    assert res.exit_code == 2
    assert "unknown benchmark part 'gpu'; valid: sampling, end-to-end, training, evaluation" in res.stderr


def test_bench_unknown_model(tmp_path):
    res = CliRunner().invoke(app, ["bench", "--model", str(tmp_path / "missing.pt"), "--only", "sampling"])
    assert res.exit_code == 2
    assert "give a checkpoint file or a shipped name (humanact12, cmu)" in res.stderr


def test_count_flops_known_values():
    """An LSTM (2 layers) and a linear head, forward and backward, against the count by hand."""
    torch.manual_seed(0)
    B, T, I, H, O = 5, 7, 4, 8, 3
    lstm, head = torch.nn.LSTM(I, H, num_layers=2, batch_first=True), torch.nn.Linear(H, O)
    root = torch.nn.ModuleList([lstm, head])
    x = torch.randn(B, T, I)

    def step():
        y, _ = lstm(x)
        head(y).sum().backward()

    per_step = 2 * 4 * H * (I + H) + 2 * 4 * H * (H + H)  # both layers' gate products
    expected = 3 * B * T * (per_step + 2 * H * O)  # forward, and backward's two products per layer
    assert count_flops(step, root) == expected
    # a linear layer alone: the counter's own count, nothing added; x needs no gradient, so the
    # backward is the weight's product only
    lin = torch.nn.Linear(I, O)
    assert count_flops(lambda: lin(x).sum().backward(), lin) == 2 * 2 * B * T * I * O


def test_matmul_rate_is_positive_per_run():
    rates = matmul_rate(2, n=64)
    assert len(rates) == 2 and all(r > 0 for r in rates)
