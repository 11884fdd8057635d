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
    pytest.param("humanact12", marks=pytest.mark.xfail(strict=True, reason=(
        "held-out accuracy is 86.1%: subject P12's slow walks and runs are misread by a classifier that "
        "sees speed (docs/evaluation.md)"))),
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


@pytest.mark.parametrize("name", [
    "humanact12",
    pytest.param("cmu_mocap", marks=pytest.mark.xfail(strict=True, reason=(
        "a half-speed real set reads FID 0.442 (7.6x real), under the CMU FID bar 0.6: on FID alone this "
        "classifier would pass a half-speed model; the speed-ratio bar (MOTION_BARS) is what catches it"))),
])
def test_shipped_classifier_sees_damped_motion(name, data_dir):
    """Real motions played at half speed must not pass for real: clearly lower Acc, an FID over the
    model bar (QUALITY_BARS) and at least 4x that of another real set. A classifier trained to
    ignore playback speed (the earlier x[1/2, 2] augmentation) fails this."""
    from odmo_cli.evaluation import metrics

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
    # float16, the expand layer as int8 rows (plain float16 would be 12.5 MB for HumanAct12's 6.2 M weights)
    assert path.stat().st_size < 10_000_000
    ckpt = torch.load(path, weights_only=True)
    manifest = load_manifest(dataset)
    assert ckpt["kind"] == "odmo" and ckpt["dataset"]["name"] == dataset
    assert_describes(ckpt, manifest)
    assert {"latent_bank", "modes", "train_config"} <= set(ckpt) and "optimizer" not in ckpt
    assert ckpt["int8_scales"], "the expand layer should be stored as int8 rows"
    batch = sample(load_model(short), ["all"], 2, seed=0)
    assert batch.motions.shape == (2 * len(manifest.actions), manifest.clip_length, manifest.skeleton.n_joints, 3)
    assert np.isfinite(batch.motions).all()


@pytest.mark.parametrize("short, dataset", SHIPPED_ODMO)
def test_shipped_odmo_was_trained_by_its_recipe(short, dataset):
    """A file trained by a recipe file (`odmo ship --recipe`) is a finished run of the project's
    recipes/<dataset>.toml from scratch (training.recipe.finished_run_differences). Otherwise the file's
    chain of stages (each stage's train config, newest first, in `init`) is the built-in recipe's, stage
    by stage (ship.stage_differences, as a build checks a stage file), with each stage's model values
    where recorded and always the last stage's."""
    from pathlib import Path

    from odmo_cli.checkpoint import shipped_file
    from odmo_cli.ship import RECIPES, _stages, stage_differences
    from odmo_cli.training.recipe import finished_run_differences, load_recipe

    ckpt = torch.load(shipped_file(short), weights_only=True)
    if "recipe" in ckpt:
        recipe = load_recipe(Path(__file__).resolve().parents[1] / "recipes" / f"{dataset}.toml")
        assert finished_run_differences(ckpt, recipe) == []
        return
    chain, node = [ckpt], ckpt.get("init")
    while node:
        chain.append(node)
        node = node.get("init")
    recipe = RECIPES[dataset]
    stages = _stages(recipe)
    assert len(chain) == len(stages)
    seed = chain[-1]["train_config"]["seed"]
    for entry, stage in zip(reversed(chain), stages):
        # every setting of the stage, its seed the first stage's plus the stage's offset, and its model
        # values where recorded (older entries of the init chain lack them)
        assert stage_differences(entry["train_config"], entry.get("config"), recipe[stage], seed) == [], stage
    assert "config" in ckpt, "the shipped file's own model config"


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




# The damping issue's bars for the shipped models: Acc and FID (QUALITY_BARS), every action's Acc,
# speed ratio overall (and per action), amplitude ratio, dist_e, Diversity and Multimodality near real.
MOTION_BARS = {
    "humanact12": {"action_acc": 85.0, "speed": (0.8, 1.2), "action_speed": 0.6, "amplitude": (0.85, 1.15),
                   "dist_e": 0.01},
    "cmu_mocap": {"action_acc": 70.0, "speed": (0.8, 1.2), "action_speed": 0.0, "amplitude": (0.85, 1.15),
                  "dist_e": 0.1},
}


def unmet_bars(dataset: str, real: dict, model: dict, custom: dict) -> list[str]:
    """Every bar the model row misses, each with its measured value (empty: all met)."""
    m, bars = model["metrics"], MOTION_BARS[dataset]
    acc_bar, fid_bar = QUALITY_BARS[dataset]
    out = []
    if m["accuracy"][0] < acc_bar:
        out.append(f"Acc {m['accuracy'][0]:.2f} < {acc_bar}")
    if m["fid"][0] > fid_bar:
        out.append(f"FID {m['fid'][0]:.3f} > {fid_bar}")
    out += [f"{a} Acc {v[0]:.1f} < {bars['action_acc']}" for a, v in model["by_action"].items() if v[0] < bars["action_acc"]]
    lo, hi = bars["speed"]
    if not lo <= m["speed"][0] <= hi:
        out.append(f"speed ratio {m['speed'][0]:.2f} outside [{lo}, {hi}]")
    out += [f"{a} speed {v[0]:.2f} < {bars['action_speed']}" for a, v in model["speed_by_action"].items()
            if v[0] < bars["action_speed"]]
    lo, hi = bars["amplitude"]
    if not lo <= m["amplitude"][0] <= hi:
        out.append(f"amplitude ratio {m['amplitude'][0]:.2f} outside [{lo}, {hi}]")
    for key, tol in (("diversity", 0.05), ("multimodality", 0.15)):
        ours, theirs = m[key][0], real["metrics"][key][0]
        if abs(ours - theirs) > tol * theirs:
            out.append(f"{key} {ours:.2f} not within {tol:.0%} of real {theirs:.2f}")
    if custom["metrics"]["dist_e"][0] > bars["dist_e"]:
        out.append(f"dist_e {custom['metrics']['dist_e'][0]:.4f} > {bars['dist_e']}")
    return out


def test_unmet_bars_names_each_miss():
    real = {"metrics": {"diversity": [10.0, 0], "multimodality": [2.0, 0]}}
    model = {"metrics": {"accuracy": [96.0, 0], "fid": [0.2, 0], "speed": [0.9, 0], "amplitude": [0.7, 0],
                         "diversity": [9.0, 0], "multimodality": [2.1, 0]},
             "by_action": {"jump": [80.0, 0], "walk": [99.0, 0]}, "speed_by_action": {"jump": [0.5, 0], "walk": [1.0, 0]}}
    custom = {"metrics": {"dist_e": [0.005, 0]}}
    assert unmet_bars("humanact12", real, model, custom) == [
        "jump Acc 80.0 < 85.0", "jump speed 0.50 < 0.6", "amplitude ratio 0.70 outside [0.85, 1.15]",
        "diversity 9.00 not within 5% of real 10.00"]


@pytest.mark.slow
@pytest.mark.parametrize("short, dataset", [
    ("humanact12", "humanact12"),
    pytest.param("cmu", "cmu_mocap", marks=pytest.mark.xfail(strict=True, reason=(
        "Acc 85.25 (bar 88) and dance 44.2 (bar 70) miss their bars; FID 0.514, speed 0.91, amplitude 0.90, "
        "Diversity, Multimodality 2.35 (real 2.29), dist_e 0.070 and jump 81.1 meet theirs (docs/results.md)"))),
])
def test_shipped_odmo_meets_its_quality_bar(short, dataset, data_dir):
    """The default protocol (10 repeats, the paper's samples per action, the shipped classifier),
    with the end-point protocol (§4.4) for dist_e."""
    from odmo_cli.evaluation.protocol import EvalConfig, run_evaluation

    report = run_evaluation([short], dataset, data_dir, None, EvalConfig(), with_customization=True)
    real, model = report.rows
    missed = unmet_bars(dataset, real, model, report.customization[0])
    assert not missed, "; ".join(missed)


# What an animator sees (odmo_cli.measures.plausibility), against the "Real motions" row as the floor, and the
# actions whose root must bounce as real motion's does.
PLAUSIBLE_BARS = {"skate": 1.2, "contact": 0.10, "root_up": 0.8, "coverage": 0.85, "kinetic_fd": 3.0,
                  "bone_var": 0.01}
BOUNCING = {"humanact12": ("walk", "run", "jump"), "cmu_mocap": ("walk", "run", "jump", "step")}


def unmet_plausibility_bars(dataset: str, real: dict, model: dict) -> list[str]:
    """Every plausibility bar the model row misses, each with its value and the real floor."""
    m, r, bars = model["metrics"], real["metrics"], PLAUSIBLE_BARS
    out = []
    if m["foot_skate"][0] > bars["skate"] * r["foot_skate"][0]:
        out.append(f"foot skate {m['foot_skate'][0]:.3f} > {bars['skate']} x real {r['foot_skate'][0]:.3f}")
    if abs(m["foot_contact"][0] / r["foot_contact"][0] - 1) > bars["contact"]:
        out.append(f"foot contact {m['foot_contact'][0]:.2f} not within {bars['contact']:.0%} of real {r['foot_contact'][0]:.2f}")
    out += [f"{a} root up {model['root_up_by_action'][a][0]:.2f} < {bars['root_up']}" for a in BOUNCING[dataset]
            if model["root_up_by_action"][a][0] < bars["root_up"]]
    if m["coverage"][0] < bars["coverage"]:
        out.append(f"coverage {m['coverage'][0]:.2f} < {bars['coverage']}")
    if m["kinetic_fd"][0] > bars["kinetic_fd"] * r["kinetic_fd"][0]:
        out.append(f"FD_k {m['kinetic_fd'][0]:.1f} > {bars['kinetic_fd']} x real {r['kinetic_fd'][0]:.1f}")
    if m["bone_var"][0] > bars["bone_var"]:
        out.append(f"bone variation p95 {m['bone_var'][0]:.3f} > {bars['bone_var']}")
    return out


def test_unmet_plausibility_bars_names_each_miss():
    real = {"metrics": {"foot_skate": [0.03, 0], "foot_contact": [0.8, 0], "kinetic_fd": [2.0, 0]}}
    model = {"metrics": {"foot_skate": [0.036, 0], "foot_contact": [0.7, 0], "coverage": [0.9, 0],
                         "kinetic_fd": [7.0, 0], "bone_var": [0.002, 0]},
             "root_up_by_action": {"walk": [0.9, 0], "run": [0.5, 0], "jump": [0.8, 0]}}
    assert unmet_plausibility_bars("humanact12", real, model) == [
        "foot contact 0.70 not within 10% of real 0.80", "run root up 0.50 < 0.8", "FD_k 7.0 > 3.0 x real 2.0"]


@pytest.mark.slow
@pytest.mark.parametrize("short, dataset", [
    pytest.param("humanact12", "humanact12", marks=pytest.mark.xfail(strict=True, reason=(
        "no term of its recipe asks for planted feet or a bouncing root: feet skate (0.108 against 0.042), "
        "the root glides (run 0.17), coverage 0.73, FD_k 46.7 against 2.5 (docs/results.md)"))),
    pytest.param("cmu", "cmu_mocap", marks=pytest.mark.xfail(strict=True, reason=(
        "no term of its recipe asks for planted feet, and its bones stretch (p95 0.35; made rigid, its speed "
        "falls under its bar): docs/results.md"))),
])
def test_shipped_odmo_is_plausible(short, dataset, data_dir, tmp_path):
    """What an animator sees, by the default protocol, and a BVH export within 2 cm of the motions."""
    from odmo_cli.checkpoint import load_model
    from odmo_cli.evaluation.protocol import EvalConfig, run_evaluation
    from odmo_cli.formats.bvh import export_motions
    from odmo_cli.generation.generate import sample
    from odmo_cli.geometry.skeletons import get_skeleton

    report = run_evaluation([short], dataset, data_dir, None, EvalConfig())
    real, model = report.rows
    loaded = load_model(short)
    batch = sample(loaded, ["all"], 5, seed=0)
    bvh = export_motions(batch.motions, batch.actions, get_skeleton(loaded.dataset["skeleton"]),
                         loaded.dataset["fps"], tmp_path)
    missed = unmet_plausibility_bars(dataset, real, model)
    missed += [f"BVH export {bvh.max_error_mm:.1f} mm from the motions"] * (bvh.max_error_mm > 20)
    assert not missed, "; ".join(missed)
