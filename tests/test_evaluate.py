"""The evaluation protocol end to end on a tiny trained model and classifier (issue: evaluation)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from odmo_cli.cli import app
from odmo_cli.data.dataset import split_indices
from odmo_cli.data.demo import demo_folder
from odmo_cli.data.locate import resolve
from odmo_cli.data.readers import read_dataset
from odmo_cli.errors import UserError
from odmo_cli.evaluation.classifier import load_classifier
from odmo_cli.evaluation.protocol import (EvalConfig, evaluate_held_out, evaluate_real, held_out_clips, real_sets,
                                         run_evaluation)
from odmo_cli.training.classifier import ClassifierTrainConfig, train_classifier


@pytest.fixture(scope="module")
def lines_classifier(lines_folder, tmp_path_factory):
    manifest, root = resolve(lines_folder)
    out = tmp_path_factory.mktemp("clf") / "clf.pt"
    train_classifier(read_dataset(root, manifest), ClassifierTrainConfig(
        epochs=15, batch_size=16, val_fraction=0.25, threads=1, seed=0), out)
    return out


def evaluate(lines_model, lines_folder, lines_classifier, **kw):
    cfg = EvalConfig(repeats=kw.pop("repeats", 3), per_action=kw.pop("per_action", 20), seed=kw.pop("seed", 0))
    return run_evaluation([str(lines_model)], str(lines_folder), None, str(lines_classifier), cfg, **kw)


def test_protocol_reports_every_metric_with_ci(lines_model, lines_folder, lines_classifier):
    report = evaluate(lines_model, lines_folder, lines_classifier, with_customization=True)
    assert [r["name"] for r in report.rows] == ["Real motions", "lines.pt"]
    real, model = report.rows
    for row in report.rows:
        # rigid bodies: no motion about the root to compare with, so no speed or amplitude ratio; roots on
        # the ground plane, so no vertical root speed either
        assert set(row["metrics"]) == {"accuracy", "fid", "diversity", "multimodality", "inception", "n_apd", "bone_std",
                                       "foot_skate", "foot_contact", "kinetic_fd", "bone_var", "bone_var_median",
                                       "root_ground", "coverage", "density"}
        assert row["speed_by_action"] == {} and row["amplitude_by_action"] == {}
        assert len(row["per_repeat"]) == 3
        for mean, half in row["metrics"].values():
            assert np.isfinite(mean) and half >= 0
    assert model["seeds"] == [0, 1, 2] and model["per_action"] == 20
    # the classifier separates the two real actions (they differ in body size)
    assert real["metrics"]["accuracy"][0] > 90
    assert real["metrics"]["n_apd"][0] == 1.0
    # rigid synthetic bodies: real bone lengths never change
    assert real["metrics"]["bone_std"][0] == pytest.approx(0.0, abs=1e-6)
    # per action: every action's accuracy, averaging (equal counts) to the overall figure
    for row in report.rows:
        assert list(row["by_action"]) == ["glide", "crouch"]
        per_action = [row["by_action"][a][0] for a in ("glide", "crouch")]
        assert np.mean(per_action) == pytest.approx(row["metrics"]["accuracy"][0])
        for rep in row["per_repeat"]:  # each repeat carries its own, keyed by name too
            assert not any(k.startswith("accuracy/") for k in rep)
            assert np.mean([rep["by_action"][a] for a in ("glide", "crouch")]) == pytest.approx(rep["accuracy"])
    cust = report.customization[0]["metrics"]
    assert cust["dist_e"][0] < 0.05


def test_a_compared_model_can_sample_conventionally(lines_model, lines_folder, lines_classifier):
    report = run_evaluation([str(lines_model), f"{lines_model}@conventional"], str(lines_folder), None,
                            str(lines_classifier), EvalConfig(repeats=2, per_action=10), with_customization=True)
    names = [r["name"] for r in report.rows]
    assert names == ["Real motions", "lines.pt", "lines.pt (conventional)"]
    assert report.rows[1]["metrics"] != report.rows[2]["metrics"]
    assert [c["name"] for c in report.customization] == names[1:]
    with pytest.raises(UserError, match="unknown sampling 'sideways'"):
        run_evaluation([f"{lines_model}@sideways"], str(lines_folder), None, str(lines_classifier), EvalConfig())


def test_root_readout_applies_to_every_odmo_row(lines_model, lines_folder, lines_classifier):
    """--root decoder reads the same codes with the pose decoder's own root: the end points move
    (dist_e changes), the body about the root does not (bone lengths stay; these toy lines do not
    move about their root, so they have no speed or amplitude ratios)."""
    runs = {root: run_evaluation([str(lines_model)], str(lines_folder), None, str(lines_classifier),
                                 EvalConfig(repeats=2, per_action=10, root=root), with_customization=True)
            for root in (None, "trajectory", "decoder")}
    dist = {root: r.customization[0]["metrics"]["dist_e"][0] for root, r in runs.items()}
    assert dist[None] == dist["trajectory"] != dist["decoder"]
    rows = {root: r.rows[1]["metrics"] for root, r in runs.items()}
    assert rows["decoder"]["bone_std"][0] == pytest.approx(rows["trajectory"]["bone_std"][0], abs=1e-6)
    assert runs["decoder"].config["root"] == "decoder"


def test_same_seed_same_numbers(lines_model, lines_folder, lines_classifier):
    a = evaluate(lines_model, lines_folder, lines_classifier, repeats=2)
    b = evaluate(lines_model, lines_folder, lines_classifier, repeats=2)
    c = evaluate(lines_model, lines_folder, lines_classifier, repeats=2, seed=5)
    assert a.rows[1]["metrics"] == b.rows[1]["metrics"]
    assert a.rows[1]["metrics"] != c.rows[1]["metrics"]


def test_samples_file_is_scored_like_the_model(lines_model, lines_folder, lines_classifier, tmp_path):
    out = tmp_path / "s.npz"
    res = CliRunner().invoke(app, ["sample", "--model", str(lines_model), "--action", "all", "--n", "20",
                                   "--out", str(out)])
    assert res.exit_code == 0, res.output
    report = run_evaluation([], str(lines_folder), None, str(lines_classifier), EvalConfig(repeats=1, per_action=20),
                            samples=[out])
    row = report.rows[-1]
    data = np.load(out)
    logits, _ = load_classifier(lines_classifier).predict(data["motions"])
    expected = 100 * np.mean(logits.argmax(1) == np.array([["glide", "crouch"].index(a) for a in data["actions"]]))
    assert row["metrics"]["accuracy"][0] == pytest.approx(expected)
    assert set(row["metrics"]) == set(report.rows[0]["metrics"])  # every column of the table
    res = CliRunner().invoke(app, ["eval", "--samples", str(out), "--dataset", str(lines_folder),
                                   "--classifier", str(lines_classifier), "--repeats", "1", "--per-action", "20"])
    assert res.exit_code == 0, res.output


def test_cli_eval_table_and_json(lines_model, lines_folder, lines_classifier, tmp_path):
    out = tmp_path / "report.json"
    res = CliRunner().invoke(app, ["eval", "--model", str(lines_model), "--dataset", str(lines_folder),
                                   "--classifier", str(lines_classifier), "--repeats", "2", "--per-action", "10",
                                   "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "Real" in res.stdout and "Acc" in res.stdout
    report = json.loads(out.read_text())
    assert report["config"] == {"repeats": 2, "per_action": 10, "sampling": "mode-preserving", "seed": 0, "root": None}
    assert [r["name"] for r in report["rows"]] == ["Real motions", "lines.pt"]


@pytest.mark.parametrize("extra, message", [
    ([], "no classifier for lines"),
    (["--classifier", "missing.pt"], "checkpoint not found"),
    (["--repeats", "0"], "--repeats must be positive"),
    (["--sampling", "nope"], "unknown sampling 'nope'"),
    (["--root", "hips"], "unknown --root 'hips'; valid: trajectory, decoder"),
])
def test_cli_eval_bad_input(lines_model, lines_folder, tmp_path, extra, message):
    res = CliRunner().invoke(app, ["eval", "--model", str(lines_model), "--dataset", str(lines_folder),
                                   "--out", str(tmp_path / "r.json"), *extra])
    assert res.exit_code == 2, res.output
    assert message in res.stderr and "Traceback" not in res.stderr
    assert not (tmp_path / "r.json").exists()


def test_classifier_for_another_skeleton_is_refused(lines_model, lines_folder, tmp_path):
    manifest, root = resolve(demo_folder("humanact12"))
    clf = tmp_path / "h12.pt"
    train_classifier(read_dataset(root, manifest), ClassifierTrainConfig(epochs=1, threads=1, val_fraction=0.0), clf)
    res = CliRunner().invoke(app, ["eval", "--model", str(lines_model), "--dataset", str(lines_folder),
                                   "--classifier", str(clf)])
    assert res.exit_code == 2
    assert "classifier expects 72 inputs (24 joints), the dataset has 20 joints" in res.stderr


class MarkedClassifier:
    """Reads the action from a marker only the held-out clips carry (joint 1 at root + (10 + action, 0, 0));
    every other motion is called action 0. Features come from a real classifier."""

    def __init__(self, inner):
        self.inner, self.info = inner, inner.info

    def predict(self, motions, batch: int = 1024):
        _, feats = self.inner.predict(motions)
        d = motions[:, 0, 1, 0] - motions[:, 0, 0, 0]  # (N,)
        pred = np.where(d > 5, np.rint(d - 10), 0).astype(int)
        return np.eye(2)[pred] * 5.0, feats


def test_held_out_row_draws_only_the_classifiers_validation_clips(lines_folder, lines_classifier):
    manifest, root = resolve(lines_folder)
    clips = read_dataset(root, manifest)
    clf = MarkedClassifier(load_classifier(lines_classifier))
    val = held_out_clips(clf, clips)
    assert np.array_equal(val, split_indices(clips, 0.25, 0)[1])  # the split the classifier was trained with
    motions = [m.copy() for m in clips.motions]
    for i in val:
        motions[i][:, 1] = motions[i][:, 0] + np.array([10.0 + clips.labels[i], 0, 0], dtype=np.float32)
    clips = replace(clips, motions=motions)
    cfg = EvalConfig(repeats=2, per_action=30)
    real = real_sets(clips, clf, cfg)
    row = evaluate_held_out(clips, val, clf, real, cfg)
    assert row["metrics"]["accuracy"][0] == 100.0 and row["clips"] == len(val)
    # all clips: the unmarked training clips of action 1 are misread, so the real row scores less
    assert evaluate_real(real, cfg)["metrics"]["accuracy"][0] < 90


def test_cli_eval_held_out_row(lines_model, lines_folder, lines_classifier, tmp_path):
    out = tmp_path / "report.json"
    args = ["eval", "--model", str(lines_model), "--dataset", str(lines_folder), "--classifier",
            str(lines_classifier), "--repeats", "2", "--per-action", "10", "--held-out", "--out", str(out)]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 0, res.output
    rows = json.loads(out.read_text())["rows"]
    assert [r["name"] for r in rows] == ["Real motions", "Real, classifier's held-out clips", "lines.pt"]
    assert set(rows[1]["metrics"]) == set(rows[0]["metrics"])


def test_cli_eval_by_action_table(lines_model, lines_folder, lines_classifier):
    args = ["eval", "--model", str(lines_model), "--dataset", str(lines_folder), "--classifier",
            str(lines_classifier), "--repeats", "2", "--per-action", "10", "--by-action"]
    res = CliRunner(env={"COLUMNS": "200"}).invoke(app, args)
    assert res.exit_code == 0, res.output
    assert "accuracy per action" in res.stdout
    assert any(line.split()[1:2] == ["glide"] for line in res.stdout.splitlines())
    assert any(line.split()[1:2] == ["crouch"] for line in res.stdout.splitlines())


def test_held_out_needs_a_split_that_fits(lines_folder, lines_classifier, tmp_path):
    manifest, root = resolve(lines_folder)
    clips = read_dataset(root, manifest)
    bare = tmp_path / "bare.pt"  # a bare state dict, as other projects' classifiers come: no split
    torch.save(torch.load(lines_classifier, weights_only=True)["state_dict"], bare)
    with pytest.raises(UserError, match="needs an odmo classifier checkpoint with a validation split; bare.pt"):
        held_out_clips(load_classifier(bare), clips)
    fewer = replace(clips, motions=clips.motions[:-1], labels=clips.labels[:-1])
    with pytest.raises(UserError, match=f"split over {len(clips)} clips, the dataset has {len(clips) - 1}"):
        held_out_clips(load_classifier(lines_classifier), fewer)


def test_damping_metrics_against_a_real_set():
    from odmo_cli.evaluation.protocol import RealSets, damping_metrics, split_by_action

    labels = np.array([0, 0, 1, 1])
    real = RealSets(features=[], labels=labels, logits=[], apd=np.ones(2), bone_std=[],
                    speed=[np.array([1.0, 1.0, 2.0, 2.0])], amplitude=[np.array([0.2, 0.4, 1.0, 1.0])])
    out = damping_metrics(np.array([0.5, 0.5, 2.0, 2.0]), np.array([0.3, 0.3, 0.5, 0.5]), labels, real)
    assert out["speed/0"] == pytest.approx(0.5) and out["speed/1"] == pytest.approx(1.0)
    assert out["speed"] == pytest.approx(0.75)
    assert out["amplitude/0"] == pytest.approx(1.0) and out["amplitude/1"] == pytest.approx(0.5)
    row = {"metrics": {k: [v, 0.0] for k, v in out.items()}, "per_repeat": [dict(out)]}
    split_by_action(row, ["kick", "wave"])
    assert row["speed_by_action"] == {"kick": [0.5, 0.0], "wave": [1.0, 0.0]}
    assert row["per_repeat"][0]["amplitude_by_action"] == {"kick": pytest.approx(1.0), "wave": pytest.approx(0.5)}
    assert set(row["metrics"]) == {"speed", "amplitude"}
    # an action whose real motions stand still has no ratio
    still = RealSets([], labels, [], np.ones(2), [], [np.array([1.0, 1.0, 0.0, 0.0])], [np.ones(4)])
    out = damping_metrics(np.ones(4), np.ones(4), labels, still)
    assert "speed/1" not in out and out["speed"] == pytest.approx(1.0)
    # a generated set r is read against real set r + 1, as its FID and plausibility measures are
    two = RealSets([], labels, [], np.ones(2), [], [np.ones(4), np.full(4, 2.0)], [np.ones(4), np.full(4, 4.0)])
    out = damping_metrics(np.ones(4), np.ones(4), labels, two, ref=1)
    assert out["speed"] == pytest.approx(0.5) and out["amplitude"] == pytest.approx(0.25)
    assert damping_metrics(np.ones(4), np.ones(4), labels, two)["speed"] == pytest.approx(1.0)


# -- samples files made elsewhere: small sets, files that do not fit ------------------------------

FIXTURES = Path(__file__).parent / "fixtures"


def subset(path: Path, rows: list[int], out: Path, **changes) -> Path:
    """A copy of a samples file with only `rows` (and any key replaced)."""
    from odmo_cli.formats.samples import ROW_KEYS

    with np.load(path) as f:
        data = {k: f[k][rows] if k in ROW_KEYS else f[k] for k in f.files}
    data.update(changes)
    np.savez(out, **data)
    return out


@pytest.fixture(scope="module")
def six_samples(lines_model, tmp_path_factory):
    """Three glides then three crouches from the lines model."""
    from odmo_cli.checkpoint import load_model
    from odmo_cli.generation.generate import sample

    out = tmp_path_factory.mktemp("samples") / "six.npz"
    sample(load_model(lines_model), ["all"], 3, seed=0).save(out)
    return out


def test_a_small_samples_set_is_scored_for_what_it_can_be(six_samples, lines_folder, lines_classifier, tmp_path):
    cfg = EvalConfig(repeats=1, per_action=20)

    def row(rows):
        path = subset(six_samples, rows, tmp_path / f"{len(rows)}.npz")
        return run_evaluation([], str(lines_folder), None, str(lines_classifier), cfg, samples=[path]).rows[-1]

    four = row([0, 1, 2, 3])  # three glides, one crouch
    assert set(four["by_action"]) == {"glide", "crouch"}
    assert np.isfinite(four["metrics"]["n_apd"][0]) and np.isfinite(four["metrics"]["multimodality"][0])
    assert four["not_available"] == ["one motion of crouch: n-APD and Multimodality need two, so these actions "
                                     "are left out of them"]
    three = row([0, 1, 2])  # glides only
    assert set(three["by_action"]) == {"glide"} and np.isfinite(three["metrics"]["fid"][0])
    assert three["not_available"][0].startswith("no motions of crouch: no accuracy, speed or amplitude")
    two = row([0, 3])  # one of each: no action has two
    assert np.isnan(two["metrics"]["n_apd"][0]) and np.isnan(two["metrics"]["multimodality"][0])
    assert np.isfinite(two["metrics"]["accuracy"][0])
    assert "no action has two motions: n-APD and Multimodality are not available" in two["not_available"]
    res = CliRunner(env={"COLUMNS": "80"}).invoke(app, [
        "eval", "--samples", str(tmp_path / "2.npz"), "--dataset", str(lines_folder), "--classifier",
        str(lines_classifier), "--repeats", "1", "--per-action", "20"])
    assert res.exit_code == 0, res.output
    assert "n/a" in res.stdout and "no action has two motions" in res.stdout


@pytest.mark.parametrize("change, message", [
    (lambda d: {"motions": d["motions"][:, :, :18]}, "have 18 joints; the classifier reads 20"),
    (lambda d: {"motions": d["motions"][:, :8]}, "have 8 frames; lines's protocol (and its classifier) reads 12-frame"),
    (lambda d: {"skeleton": np.str_("humanact12")}, "have skeleton humanact12; lines has cmu20"),
    (lambda d: {"motions": np.where(np.arange(6)[:, None, None, None] == 4, np.nan, d["motions"])},
     "hold NaN or infinite values (1 motions, the first: 4)"),
])
def test_samples_that_do_not_fit_are_refused_in_one_line(six_samples, lines_folder, lines_classifier, tmp_path,
                                                         change, message):
    with np.load(six_samples) as f:
        spoilt = subset(six_samples, list(range(6)), tmp_path / "bad.npz", **change(dict(f)))
    res = CliRunner().invoke(app, ["eval", "--samples", str(spoilt), "--dataset", str(lines_folder), "--classifier",
                                   str(lines_classifier), "--out", str(tmp_path / "r.json")])
    assert res.exit_code == 2, res.output
    assert message in res.stderr and res.stderr.count("\n") == 1 and "Traceback" not in res.stderr
    assert not (tmp_path / "r.json").exists()


def test_the_dataset_of_a_samples_file(six_samples, tmp_path):
    from odmo_cli.evaluation.protocol import samples_dataset

    assert samples_dataset(six_samples) == "lines"  # its `dataset` entry
    a2m = FIXTURES / "a2m_humanact12_lie_samples.npz"  # no `dataset` entry: the dataset of its skeleton
    assert samples_dataset(a2m) == "humanact12"
    with np.load(six_samples) as f:
        data = {k: f[k] for k in f.files if k != "dataset"}
    np.savez(tmp_path / "uestc.npz", **{**data, "skeleton": np.str_("uestc18")})
    assert samples_dataset(tmp_path / "uestc.npz") == "uestc"


def test_action2motion_released_samples_evaluate(data_dir, tmp_path):
    """The 20 samples Action2Motion released (0-4 per action): every metric that can be computed is,
    the rest is said to be not available, exit 0; the dataset comes from the file's skeleton."""
    out = tmp_path / "a2m.json"
    res = CliRunner(env={"COLUMNS": "80"}).invoke(app, [
        "eval", "--samples", str(FIXTURES / "a2m_humanact12_lie_samples.npz"), "--data", str(data_dir),
        "--repeats", "1", "--per-action", "50", "--out", str(out)])
    assert res.exit_code == 0, res.output
    row = json.loads(out.read_text())["rows"][-1]
    assert row["name"] == "a2m_humanact12_lie_samples.npz"
    assert all(np.isfinite(row["metrics"][k][0]) for k in ("accuracy", "fid", "diversity", "multimodality", "n_apd"))
    assert sorted(row["by_action"]) == sorted(["warm_up", "walk", "run", "jump", "drink", "lift_dumbbell", "eat",
                                               "turn_steering_wheel", "boxing", "throw"])
    assert row["not_available"][0].startswith("no motions of sit, phone")
    assert "warm_up, drink, lift_dumbbell, turn_steering_wheel" in row["not_available"][1]


def test_one_repeat_prints_no_interval(lines_model, lines_folder, lines_classifier):
    args = ["eval", "--model", str(lines_model), "--dataset", str(lines_folder), "--classifier", str(lines_classifier),
            "--per-action", "10", "--by-action"]
    one = CliRunner().invoke(app, args + ["--repeats", "1"])
    assert one.exit_code == 0, one.output
    assert "±" not in one.output and "95% CI" not in one.output
    two = CliRunner().invoke(app, args + ["--repeats", "2"])
    assert two.exit_code == 0 and "±" in two.output
