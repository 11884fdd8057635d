"""The action classifier (issue: evaluation classifier): Action2Motion layout, loading checks,
features, and training on real clips (the shipped demo subset; the full releases when
ODMO_DATA_DIR is set)."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest
import torch

from odmo_cli.data.locate import resolve
from odmo_cli.data.manifest import load_manifest
from odmo_cli.data.readers import read_dataset
from odmo_cli.checkpoint import FORMAT_VERSION, save_checkpoint
from odmo_cli.errors import UserError
from odmo_cli.evaluation import classifier as clf
from odmo_cli.evaluation.classifier import check_matches, load_classifier
from odmo_cli.models.classifier import ClassifierConfig, MotionClassifier, config_for
from odmo_cli.training import classifier as train_clf
from odmo_cli.training.classifier import ClassifierTrainConfig, train_classifier


pytestmark = pytest.mark.usefixtures("one_thread")



def a2m_reference(state: dict, motion: torch.Tensor, layers: int) -> torch.Tensor:
    """Action2Motion's MotionDiscriminator.forward written out with the raw weights (zero h0)."""
    x = motion.reshape(motion.shape[0], motion.shape[1], -1).permute(1, 0, 2)  # (T, B, D)
    for layer in range(layers):
        w_ih, w_hh = state[f"recurrent.weight_ih_l{layer}"], state[f"recurrent.weight_hh_l{layer}"]
        b_ih, b_hh = state[f"recurrent.bias_ih_l{layer}"], state[f"recurrent.bias_hh_l{layer}"]
        h = torch.zeros(x.shape[1], w_hh.shape[1])
        outs = []
        for t in range(x.shape[0]):
            gi, gh = x[t] @ w_ih.T + b_ih, h @ w_hh.T + b_hh
            r = torch.sigmoid(gi[:, :h.shape[1]] + gh[:, :h.shape[1]])
            z = torch.sigmoid(gi[:, h.shape[1]:2 * h.shape[1]] + gh[:, h.shape[1]:2 * h.shape[1]])
            n = torch.tanh(gi[:, 2 * h.shape[1]:] + r * gh[:, 2 * h.shape[1]:])
            h = (1 - z) * n + z * h
            outs.append(h)
        x = torch.stack(outs)
    lin1 = torch.tanh(x[-1] @ state["linear1.weight"].T + state["linear1.bias"])
    return lin1 @ state["linear2.weight"].T + state["linear2.bias"]


def write_a2m_file(path, input_size=72, n_classes=12, hidden=16, layers=2, seed=0) -> dict:
    """An Action2Motion-layout file: a torch file with the state dict under 'model'."""
    torch.manual_seed(seed)
    gru = torch.nn.GRU(input_size, hidden, layers)
    lin1, lin2 = torch.nn.Linear(hidden, 30), torch.nn.Linear(30, n_classes)
    state = {**{f"recurrent.{k}": v for k, v in gru.state_dict().items()},
             **{f"linear1.{k}": v for k, v in lin1.state_dict().items()},
             **{f"linear2.{k}": v for k, v in lin2.state_dict().items()}}
    torch.save({"model": state, "epoch": 7}, path)  # the release also stores other entries
    return state


# -- Action2Motion layout ------------------------------------------------------------------------

def test_a2m_layout_loads_and_gives_identical_logits(tmp_path):
    path = tmp_path / "a2m_classifier.tar"
    state = write_a2m_file(path, hidden=16, layers=2)
    model = load_classifier(path, expect_classes=12, expect_input=72)
    assert model.cfg == ClassifierConfig(input_size=72, n_classes=12, hidden=16, layers=2, feature=30)
    assert not model.training
    motion = torch.randn(5, 9, 24, 3, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        got = model(motion)
    expected = a2m_reference(state, motion, layers=2)
    assert got.shape == (5, 12)
    assert torch.allclose(got, expected, atol=1e-5)
    assert model.info["source"] == "a2m"
    assert model.info["sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
    assert model.info["verified"] is False and model.info["release"] is None


def test_release_hashes_recorded():
    h12 = clf.A2M_RELEASES["action_recognition_model_humanact12.tar"]
    mocap = clf.A2M_RELEASES["action_recognition_model_mocap_new.tar"]
    assert h12["sha256"] == "e2d231fd8a425bc642d4c342466d5eaae2ae16e8a67e8dd253820ef5512d7bca"
    assert (h12["n_classes"], h12["input_size"]) == (12, 72)
    assert mocap["sha256"] == "7ef619637e61934a57254642021d065adf8afd59f56be7c39f205eea064aa154"
    assert (mocap["n_classes"], mocap["input_size"]) == (8, 60)


def test_a2m_file_matching_a_release_hash_is_verified(tmp_path, monkeypatch):
    path = tmp_path / "renamed.tar"
    write_a2m_file(path, input_size=60, n_classes=8)
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    releases = {"action_recognition_model_mocap_new.tar":
                {**clf.A2M_RELEASES["action_recognition_model_mocap_new.tar"], "sha256": digest}}
    monkeypatch.setattr(clf, "A2M_RELEASES", releases)
    model = load_classifier(path)
    assert model.info["verified"] is True
    assert model.info["release"] == "action_recognition_model_mocap_new.tar"
    assert model.info["dataset"] == {"name": "cmu_mocap"}


def test_a2m_release_name_with_wrong_hash_warns(tmp_path):
    path = tmp_path / "action_recognition_model_humanact12.tar"
    write_a2m_file(path)
    with pytest.warns(UserWarning, match="does not match the Action2Motion release"):
        model = load_classifier(path)
    assert model.info["verified"] is False


def test_wrong_input_size_is_a_clear_user_error(tmp_path):
    path = tmp_path / "mocap.tar"
    write_a2m_file(path, input_size=60, n_classes=8)
    with pytest.raises(UserError, match=r"classifier expects 60 inputs \(20 joints\), the dataset has 24 joints"):
        load_classifier(path, expect_input=72)


def test_wrong_class_count_is_a_clear_user_error(tmp_path):
    path = tmp_path / "mocap.tar"
    write_a2m_file(path, input_size=60, n_classes=8)
    with pytest.raises(UserError, match="classifier has 8 classes, the dataset has 7 actions"):
        load_classifier(path, expect_classes=7, expect_input=60)
    model = load_classifier(path, expect_classes=8, expect_input=60)
    with pytest.raises(UserError, match="8 classes, the dataset has 7"):
        check_matches(model, load_manifest("cmu_mocap"))


def test_wrong_frame_width_in_forward_is_a_user_error():
    model = MotionClassifier(ClassifierConfig(input_size=60, n_classes=7, hidden=8))
    with pytest.raises(UserError, match=r"expects 60 inputs per frame \(20 joints\), got 72 \(24 joints\)"):
        model(torch.zeros(2, 5, 24, 3))


def test_files_that_are_not_classifiers_are_user_errors(tmp_path):
    odmo = tmp_path / "odmo.pt"
    save_checkpoint(odmo, {"format_version": 1, "kind": "odmo", "config": {}, "state_dict": {}})
    with pytest.raises(UserError, match="'odmo' checkpoint, not a classifier"):
        load_classifier(odmo)
    other = tmp_path / "other.pt"
    torch.save({"model": {"encoder.weight": torch.zeros(3, 3)}}, other)
    with pytest.raises(UserError, match="not a motion classifier: missing recurrent.weight_ih_l0"):
        load_classifier(other)
    with pytest.raises(UserError, match="checkpoint not found"):
        load_classifier(tmp_path / "missing.tar")


# -- the model -----------------------------------------------------------------------------------

def test_features_are_30d_and_bounded():
    torch.manual_seed(0)
    model = MotionClassifier(ClassifierConfig(input_size=72, n_classes=12))
    motion = 50 * torch.randn(6, 20, 24, 3)  # large inputs saturate tanh: bounds must still hold
    with torch.no_grad():
        logits, feats = model.logits_and_features(motion)
    assert feats.shape == (6, 30) and logits.shape == (6, 12)
    assert float(feats.abs().max()) <= 1.0
    with torch.no_grad():
        assert torch.equal(model.features(motion), feats)
        assert torch.equal(model(motion), logits)


def test_forward_on_joints_equals_forward_on_flat_frames():
    torch.manual_seed(0)
    model = MotionClassifier(ClassifierConfig(input_size=60, n_classes=7))
    motion = torch.randn(4, 11, 20, 3)
    assert torch.equal(model(motion), model(motion.reshape(4, 11, 60)))


def test_predict_batches_and_matches_forward():
    torch.manual_seed(0)
    model = MotionClassifier(ClassifierConfig(input_size=60, n_classes=7, hidden=32))
    motions = np.random.default_rng(0).normal(size=(10, 8, 20, 3)).astype(np.float32)
    logits, feats = model.predict(motions, batch=3)
    assert logits.shape == (10, 7) and feats.shape == (10, 30)
    assert isinstance(logits, np.ndarray) and logits.dtype == np.float32
    with torch.no_grad():
        ref_logits, ref_feats = model.logits_and_features(torch.from_numpy(motions))
    np.testing.assert_allclose(logits, ref_logits.numpy(), atol=1e-5)
    np.testing.assert_allclose(feats, ref_feats.numpy(), atol=1e-5)


def test_presets_by_dataset():
    h12, cmu, uestc = (config_for(load_manifest(n)) for n in ("humanact12", "cmu_mocap", "uestc"))
    assert (h12.input_size, h12.n_classes, h12.layers, h12.hidden, h12.feature) == (72, 12, 2, 128, 30)
    assert (cmu.input_size, cmu.n_classes, cmu.layers, cmu.hidden) == (60, 7, 2, 128)
    assert (uestc.layers, uestc.hidden) == (3, 256)
    assert ClassifierConfig.from_dict(h12.to_dict()) == h12


# -- training ------------------------------------------------------------------------------------

def tiny_tc(**kw) -> ClassifierTrainConfig:
    base = dict(epochs=25, batch_size=12, lr=3e-3, val_fraction=0.0, hidden=32, threads=1, seed=3,
                sampling="shuffle", mirror=False, speed=1.0)
    base.update(kw)
    return ClassifierTrainConfig(**base)


@pytest.fixture(scope="module")
def tiny_run(demo_clips, tmp_path_factory):
    out = tmp_path_factory.mktemp("clf") / "demo_classifier.pt"
    logs = []
    report = train_classifier(demo_clips, tiny_tc(), out, progress=logs.append).report
    return out, report, logs


def test_tiny_training_learns_and_writes_a_safe_checkpoint(demo_clips, tiny_run):
    out, report, logs = tiny_run
    chance = 1 / len(demo_clips.manifest.actions)
    assert report["train_accuracy"] > 3 * chance
    assert report["epochs"] == 25 and len(logs) == 25 and report["seconds"] > 0
    assert logs[-1]["loss"] < logs[0]["loss"]
    ckpt = torch.load(out, map_location="cpu", weights_only=True)
    assert ckpt["kind"] == "classifier" and ckpt["format_version"] == FORMAT_VERSION
    assert ckpt["dataset"]["actions"] == list(demo_clips.manifest.action_names)
    assert ckpt["dataset"]["length"] == 60 and ckpt["dataset"]["skeleton"] == "humanact12"
    assert ckpt["config"] == {"input_size": 72, "n_classes": 12, "hidden": 32, "layers": 2, "feature": 30}
    assert ckpt["report"]["train_accuracy"] == report["train_accuracy"]
    model = load_classifier(out, expect_classes=12, expect_input=72,
                            expect_actions=demo_clips.manifest.action_names)
    assert model.info["source"] == "odmo"
    crops = train_clf.crop_batch(demo_clips, np.arange(len(demo_clips)), 60)
    acc = float((model.predict(crops)[0].argmax(1) == demo_clips.labels).mean())
    assert acc == pytest.approx(report["train_accuracy"])
    with pytest.raises(UserError, match="trained on actions"):
        load_classifier(out, expect_actions=["a"] * 12)


def test_training_is_deterministic(demo_clips, tiny_run, tmp_path):
    out, _, _ = tiny_run
    short = tiny_tc(epochs=3)
    train_classifier(demo_clips, short, tmp_path / "a.pt")
    train_classifier(demo_clips, short, tmp_path / "b.pt")
    train_classifier(demo_clips, tiny_tc(epochs=3, seed=4), tmp_path / "c.pt")
    a, b, c = (torch.load(tmp_path / f"{k}.pt", weights_only=True)["state_dict"] for k in "abc")
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert not all(torch.equal(a[k], c[k]) for k in a)


@pytest.mark.parametrize("options", [
    dict(sampling="balanced", rotate=10.0),
    dict(sampling="length", mirror=True, speed=2.0, noise=0.01, dropout=0.2, lr_final=1e-4),
])
def test_training_with_validation_split_and_options(demo_clips, tmp_path, options):
    logs = []
    report = train_classifier(demo_clips, tiny_tc(epochs=2, val_fraction=0.34, **options), tmp_path / "v.pt",
                              progress=logs.append).report
    assert report["val_clips"] == 12 and report["train_clips"] == 24
    assert set(report["val_per_class"]) == set(demo_clips.manifest.action_names)
    assert all(np.isfinite(log["loss"]) for log in logs)


def test_learning_rate_schedule():
    assert ClassifierTrainConfig(epochs=5, lr=1e-3, lr_final=0.0).learning_rate(4) == 1e-3  # constant
    tc = ClassifierTrainConfig(epochs=5, lr=1e-3, lr_final=1e-5)
    assert tc.learning_rate(0) == pytest.approx(1e-3) and tc.learning_rate(4) == pytest.approx(1e-5)


def test_mirror_swaps_sides_and_negates_one_axis():
    names = load_manifest("humanact12").skeleton.joint_names
    perm = train_clf.mirror_map(names)
    assert names[perm[names.index("left_wrist")]] == "right_wrist" and perm[0] == 0
    assert [perm[j] for j in perm] == list(range(len(names)))  # an involution
    motions = np.random.default_rng(0).normal(size=(40, 3, 24, 3)).astype(np.float32)
    out = train_clf.mirror_half(motions, perm, 0, np.random.default_rng(1))
    flipped = ~np.all(out == motions, axis=(1, 2, 3))
    assert 5 < flipped.sum() < 35
    expected = motions[flipped][:, :, perm] * np.array([-1, 1, 1], np.float32)
    np.testing.assert_array_equal(out[flipped], expected)


def test_resample_changes_playback_speed():
    motion = np.arange(10, dtype=np.float32)[:, None, None] * np.ones((1, 2, 3), np.float32)
    np.testing.assert_array_equal(train_clf._resample(motion, 1.0), motion)
    np.testing.assert_array_equal(train_clf._resample(motion, 2.0)[:, 0, 0], [0, 2, 4, 6, 8])
    np.testing.assert_allclose(train_clf._resample(motion, 0.5)[:4, 0, 0], [0, 0.5, 1, 1.5])
    assert len(train_clf._resample(motion, 0.5)) == 19


@pytest.mark.parametrize("kw, message", [
    ({"epochs": 0}, "epochs must be positive"),
    ({"batch_size": -1}, "batch_size must be positive"),
    ({"lr": 0.0}, "lr must be positive"),
    ({"val_fraction": 1.0}, r"val_fraction must be in \[0, 1\)"),
    ({"sampling": "weighted"}, "sampling must be one of shuffle, balanced, length, got 'weighted'"),
    ({"dropout": 1.5}, "dropout must be in"),
    ({"speed": 0.5}, r"speed must be in \[1, 4\]"),
    ({"noise": -1.0}, "noise must not be negative"),
])
def test_bad_training_configs_are_user_errors(kw, message):
    with pytest.raises(UserError, match=message):
        ClassifierTrainConfig(**kw)


def test_failed_training_writes_nothing(demo_clips, tmp_path):
    with pytest.raises(UserError, match="does not exist"):
        train_classifier(demo_clips, tiny_tc(epochs=1), tmp_path / "no_such_dir" / "x.pt")
    assert not (tmp_path / "no_such_dir").exists()


# -- real data (ODMO_DATA_DIR) -------------------------------------------------------------------

def test_real_datasets_fit_their_classifier_presets(data_dir):
    for name, joints, classes in (("humanact12", 24, 12), ("cmu_mocap", 20, 7)):
        manifest, root = resolve(name, data_dir)
        clips = read_dataset(root, manifest)
        cfg = config_for(manifest)
        assert (cfg.input_size, cfg.n_classes) == (3 * joints, classes)
        assert clips.motions[0].shape[1:] == (joints, 3)
        model = MotionClassifier(cfg)
        logits, feats = model.predict(train_clf.crop_batch(clips, np.arange(8), manifest.clip_length))
        assert logits.shape == (8, classes) and feats.shape == (8, 30)


def test_a2m_release_with_extra_classes_scores_the_datasets_actions(tmp_path, monkeypatch):
    """Action2Motion's MoCap classifier has 8 classes (with Wash); ODMO's CMU MoCap has 7: the
    release is scored on those 7, by name, its Wash logit left out."""
    from odmo_cli.data.manifest import load_manifest

    manifest = load_manifest("cmu_mocap")
    torch.manual_seed(0)
    full = clf.MotionClassifier(clf.ClassifierConfig(input_size=60, n_classes=8, hidden=16, layers=2))
    path = tmp_path / "mocap8.tar"
    torch.save({"model": full.state_dict()}, path)
    classes = ["walk", "wash", "run", "jump", "animal_behavior", "dance", "step", "climb"]
    monkeypatch.setitem(clf.A2M_RELEASES, "mocap8.tar", {"sha256": clf.file_sha256(path), "dataset": "cmu_mocap",
                                                         "classes": classes})
    model = clf.load_classifier(path)
    clf.check_matches(model, manifest)
    motions = np.random.default_rng(0).normal(size=(5, 100, 20, 3)).astype(np.float32)
    logits, feats = model.predict(motions)
    all_logits, all_feats = full.eval().predict(motions)
    np.testing.assert_allclose(logits, all_logits[:, [0, 2, 3, 4, 5, 6, 7]], rtol=1e-6)
    np.testing.assert_allclose(feats, all_feats, rtol=1e-6)
    # a file that is not that release (other weights, other hash) keeps the strict check
    torch.save({"model": {k: v + 1 for k, v in full.state_dict().items()}}, tmp_path / "other.tar")
    other = clf.load_classifier(tmp_path / "other.tar")
    with pytest.raises(UserError, match="8 classes, the dataset has 7 actions"):
        clf.check_matches(other, manifest)
