"""The files shipped in odmo_cli/assets: they load safely and describe what they were trained on."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from odmo_cli.data.locate import resolve
from odmo_cli.data.manifest import load_manifest
from odmo_cli.data.readers import read_dataset
from odmo_cli.evaluation.classifier import check_matches, load_classifier
from odmo_cli.evaluation.protocol import shipped_classifier
from odmo_cli.training.classifier import crop_batch

def assert_describes(ckpt: dict, manifest) -> None:
    """The checkpoint names the dataset's actions, skeleton, clip length and fps."""
    assert ckpt["dataset"]["actions"] == list(manifest.action_names)
    assert ckpt["dataset"]["skeleton"] == manifest.skeleton_name
    assert ckpt["dataset"]["length"] == manifest.clip_length and ckpt["dataset"]["fps"] == manifest.fps


CLASSIFIERS = {"humanact12": 0.95, "cmu_mocap": 0.90}  # the evaluation issue's bars
QUALITY_BARS = {"humanact12": (95.0, 0.25), "cmu_mocap": (88.0, 0.6)}  # Acc >=, FID <= (the damping issue's bars)


@pytest.mark.parametrize("name", CLASSIFIERS)
def test_shipped_classifier_loads_safely_and_fits_its_dataset(name):
    path = shipped_classifier(name)
    assert path is not None and path.stat().st_size < 2_000_000
    ckpt = torch.load(path, weights_only=True)
    manifest = load_manifest(name)
    assert ckpt["kind"] == "classifier" and ckpt["dataset"]["name"] == name
    assert_describes(ckpt, manifest)
    check_matches(load_classifier(path), manifest)


@pytest.mark.slow
@pytest.mark.parametrize("name", [
    "cmu_mocap",
    pytest.param("humanact12", marks=pytest.mark.xfail(
        strict=True, reason="held-out accuracy is 90.3%: subject P12's slow walks and runs are misread")),
])
def test_shipped_classifier_accuracy_on_held_out_real_clips(name, data_dir):
    path = shipped_classifier(name)
    ckpt = torch.load(path, weights_only=True)
    manifest, root = resolve(name, data_dir)
    clips = read_dataset(root, manifest)
    val = ckpt["split"]["val"].numpy()
    motions = crop_batch(clips, val, manifest.clip_length)
    logits, _ = load_classifier(path).predict(motions)
    acc = float(np.mean(logits.argmax(1) == clips.labels[val]))
    assert acc == pytest.approx(ckpt["report"]["val_accuracy"], abs=1e-6)
    assert acc >= CLASSIFIERS[name]


def _real_set(clips, manifest, seed: int, rate: float = 1.0, n: int = 100):
    """n random crops per action (first root at the origin), each clip first replayed at `rate`."""
    from odmo_cli.data.dataset import crop_pad_shift, random_start
    from odmo_cli.training.classifier import _resample

    rng = np.random.default_rng(seed)
    motions, labels = [], []
    for c in range(len(manifest.actions)):
        for i in rng.choice(np.flatnonzero(clips.labels == c), n):
            m = _resample(clips.motions[i], rate) if rate != 1.0 else clips.motions[i]
            motions.append(crop_pad_shift(m, manifest.clip_length, random_start(len(m), manifest.clip_length, rng)))
            labels.append(c)
    return np.stack(motions), np.asarray(labels)


@pytest.mark.parametrize("name", CLASSIFIERS)
def test_shipped_classifier_sees_damped_motion(name, data_dir):
    """Real motions played at half speed must not pass for real: clearly lower Acc, an FID over the
    model bar (QUALITY_BARS) and at least 4x that of another real set. A classifier trained to
    ignore playback speed (the earlier x[1/2, 2] augmentation) fails this."""
    from odmo_cli import metrics

    manifest, root = resolve(name, data_dir)
    clips = read_dataset(root, manifest)
    clf = load_classifier(shipped_classifier(name))
    _, ref = clf.predict(_real_set(clips, manifest, seed=1)[0])
    scores = {}
    for rate in (1.0, 0.5):
        motions, labels = _real_set(clips, manifest, seed=2, rate=rate)
        logits, feats = clf.predict(motions)
        scores[rate] = (100 * metrics.accuracy(logits, labels), metrics.fid_from_features(ref, feats))
    (acc, fid), (slow_acc, slow_fid) = scores[1.0], scores[0.5]
    assert slow_acc <= acc - 5, scores
    assert slow_fid > QUALITY_BARS[name][1] and slow_fid >= 4 * fid, scores


# -- shipped ODMO models ------------------------------------------------------------------------

SHIPPED_ODMO = [
    ("humanact12", "humanact12"),
    ("cmu", "cmu_mocap"),
]


@pytest.mark.parametrize("short, dataset", SHIPPED_ODMO)
def test_shipped_odmo_loads_safely_and_describes_its_data(short, dataset):
    from odmo_cli.checkpoint import load_model, shipped_file
    from odmo_cli.generation.generate import sample

    path = shipped_file(short)
    assert path is not None, f"no shipped {short} model"
    assert path.stat().st_size < 6_500_000  # float16, the expand layer as int8 rows
    ckpt = torch.load(path, weights_only=True)
    manifest = load_manifest(dataset)
    assert ckpt["kind"] == "odmo" and ckpt["dataset"]["name"] == dataset
    assert_describes(ckpt, manifest)
    assert {"latent_bank", "modes", "train_config"} <= set(ckpt) and "optimizer" not in ckpt
    batch = sample(load_model(short), ["all"], 2, seed=0)
    assert batch.motions.shape == (2 * len(manifest.actions), manifest.clip_length, manifest.skeleton.n_joints, 3)
    assert np.isfinite(batch.motions).all()


@pytest.mark.parametrize("model, action, shape", [
    ([], "jump", (60, 24, 3)),                      # the default model: the README's first command
    (["--model", "cmu"], "dance", (100, 20, 3)),
])
def test_sample_command_on_a_shipped_model(model, action, shape, tmp_path):
    from typer.testing import CliRunner

    from odmo_cli.cli import app

    out = tmp_path / "out.npz"
    res = CliRunner().invoke(app, ["sample", *model, "--action", action, "--n", "3", "--out", str(out)])
    assert res.exit_code == 0, res.output
    with np.load(out) as d:
        assert d["motions"].shape == (3, *shape) and list(d["actions"]) == [action] * 3
        assert np.isfinite(d["motions"]).all()
        assert str(d["model"]) == (model[1] if model else "humanact12")  # the short name, not a path




@pytest.mark.slow
@pytest.mark.parametrize("short, dataset", [
    pytest.param("humanact12", "humanact12", marks=pytest.mark.xfail(strict=True, reason=(
        "measured Acc 90.06 +- 0.28, FID 0.592 +- 0.016 (10 x 250, shipped classifier): below the bar"))),
    pytest.param("cmu", "cmu_mocap", marks=pytest.mark.xfail(strict=True, reason=(
        "measured Acc 76.20 +- 0.25, FID 2.563 +- 0.042 (10 x 400, shipped classifier): below the bar"))),
])
def test_shipped_odmo_meets_its_quality_bar(short, dataset, data_dir):
    """The default protocol (10 repeats, the paper's samples per action, the shipped classifier)."""
    from odmo_cli.evaluation.protocol import EvalConfig, run_evaluation

    report = run_evaluation([short], dataset, data_dir, None, EvalConfig())
    metrics = report.rows[1]["metrics"]
    acc_bar, fid_bar = QUALITY_BARS[dataset]
    assert metrics["accuracy"][0] >= acc_bar and metrics["fid"][0] <= fid_bar, metrics
