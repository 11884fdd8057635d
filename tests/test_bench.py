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
    asked = tmp_path / "asked.txt"  # the number of motions each of its runs was asked for
    peer.write_text(f"import json, sys; a = sys.argv; n = int(a[a.index('--n') + 1]); "
                    f"open({str(asked)!r}, 'a').write(f'{{n}}\\n'); "
                    "print(json.dumps({'motions_per_s': 500.0, 'n': n}))\n")
    res = CliRunner().invoke(app, ["bench", "--only", "sampling", "--runs", "2", "--peer", str(peer), "--out", str(out)])
    assert res.exit_code == 0, res.output
    report = json.loads(out.read_text())
    # model load, sampling throughput, `odmo sample` after load, the authors' networks, and ours over theirs
    load, throughput, ours, theirs, ratio = report["figures"]
    assert [f["unit"] for f in report["figures"]] == ["s", "motions/s", "motions/s", "motions/s", "x"]
    for f in report["figures"]:
        assert f["runs"] == 2 and f["min"] <= f["median"] <= f["max"] and f["min"] > 0
    for f in (load, throughput, ours):
        assert f["note"] == ""  # the shipped model, not an untrained stand-in
    assert asked.read_text().split() == ["1008", "1008"]  # as many motions as ours: 84 per action, 12 actions
    assert theirs["median"] == 500.0 and ratio["median"] == pytest.approx(ours["median"] / 500.0)
    assert report["machine"]["cores"] >= 1
    # in a log (stderr not a terminal), one line per part with the time so far
    assert [line.split(" (")[0] for line in res.stderr.splitlines()] == ["benchmarking sampling"]
    assert res.stderr.rstrip().endswith("elapsed)")


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
    assert ours.unit == "s" and len(ours.runs) == 2
    assert theirs.runs == [600 / 500.0, 600 / 500.0]  # 10 repeats x 5 per action x 12 actions, at 500 a second
    assert ratio.runs == pytest.approx([a / 1.2 for a in ours.runs])
    assert len(bench.bench_evaluation(None, None, 1, torch.device("cpu"), None)) == 1  # no peer: no reference


def test_bench_bad_part():
    res = CliRunner().invoke(app, ["bench", "--only", "gpu"])
    assert res.exit_code == 2
    assert "unknown benchmark part 'gpu'; valid: sampling, composition, end-to-end, training, evaluation" in res.stderr


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
