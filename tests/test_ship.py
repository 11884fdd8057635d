"""`odmo ship`: the recipe runner that rebuilds the shipped models, and the compact file format."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from odmo_cli import checkpoint, ship
from odmo_cli.checkpoint import describe_checkpoint, load_checkpoint, load_model, save_checkpoint
from odmo_cli.cli import app
from odmo_cli.errors import UserError
from odmo_cli.generation.generate import sample


def test_compact_keeps_what_sampling_needs_in_half_the_space(lines_model, tmp_path):
    full = load_checkpoint(lines_model)
    small = checkpoint.compact(full)
    assert {"optimizer", "rng", "split"}.isdisjoint(small)
    assert {"config", "dataset", "latent_bank", "modes", "state_dict"} <= set(small)
    assert len(small["history"]) == 1 and small["weights_dtype"] == "float16"  # no matrix of 1M values
    floats = [v for v in small["state_dict"].values() if v.is_floating_point()]
    assert floats and all(v.dtype == torch.float16 for v in floats)
    path = tmp_path / "small.pt"
    save_checkpoint(path, small)
    assert path.stat().st_size < 0.6 * lines_model.stat().st_size
    # the float16 weights load into float32 parameters and generate nearly the same motions
    a = sample(load_model(lines_model), ["glide"], 5, seed=0).motions
    b = sample(load_model(path), ["glide"], 5, seed=0).motions
    assert b.dtype == np.float32
    assert np.abs(a - b).max() < 0.02 * np.abs(a).max()


def test_compact_stores_large_matrices_as_int8_rows(lines_model, tmp_path):
    full = load_checkpoint(lines_model)
    biggest = max(v.numel() for v in full["state_dict"].values() if v.dim() == 2)
    small = checkpoint.compact(full, int8_min_values=biggest)
    (name,) = small["int8_scales"]  # only the largest matrix is rounded to int8
    assert small["state_dict"][name].dtype == torch.int8 and name in small["weights_dtype"]
    assert small["int8_scales"][name].shape == (full["state_dict"][name].shape[0], 1)
    restored = checkpoint.float_state(small)[name]
    assert restored.dtype == torch.float32
    step = small["int8_scales"][name].float()
    assert torch.all((restored - full["state_dict"][name]).abs() <= 0.5 * step + 1e-6)
    path = tmp_path / "int8.pt"
    save_checkpoint(path, small)
    assert load_checkpoint(path)["state_dict"][name].dtype == torch.int8  # weights_only loads int8
    assert describe_checkpoint(path)["weights"] == f"float16; int8 rows for {name}"  # odmo info
    a = sample(load_model(lines_model), ["glide"], 5, seed=0).motions
    b = sample(load_model(path), ["glide"], 5, seed=0).motions
    assert np.abs(a - b).max() < 0.05 * np.abs(a).max()


def test_int8_rows_known_values():
    w = torch.tensor([[127.0, -63.5, 0.2], [0.0, 0.0, 0.0], [-2.54, 1.0, 0.0]])
    q, scale = checkpoint.int8_rows(w)
    assert q.dtype == torch.int8 and scale.dtype == torch.float32
    assert q[0].tolist() == [127, -64, 0] and scale[0, 0] == 1.0  # -63.5 rounds half to even
    assert q[1].tolist() == [0, 0, 0] and bool(scale[1, 0] > 0)  # an all-zero row: zeros, no 0/0
    assert q[2, 0] == -127 and q[2, 1] == 50
    assert torch.allclose(q.float() * scale.float(), w, atol=0.5 * float(scale.max()))


def test_recipe_names():
    assert ship.recipe_name("cmu") == "cmu_mocap"
    assert ship.recipe_name("humanact12") == "humanact12"
    with pytest.raises(UserError, match="valid: humanact12, cmu_mocap"):
        ship.recipe_name("uestc")


def test_cli_refuses_a_dataset_without_recipe(tmp_path):
    res = CliRunner().invoke(app, ["ship", "uestc", "--out", str(tmp_path)])
    assert res.exit_code == 2
    assert "no shipping recipe for 'uestc'" in res.stderr and res.stderr.count("\n") == 1
    assert list(tmp_path.iterdir()) == []


def test_build_writes_both_files_deterministically(lines_folder, tmp_path, monkeypatch):
    """The whole pipeline on the tiny lines dataset with a tiny recipe, twice with the same seed."""
    tiny = {"odmo": {"epochs": 3, "batch_size": 40, "pairs_per_epoch": 80, "val_every": 0, "threads": 1},
            "odmo_stage2": {"epochs": 2, "batch_size": 40, "pairs_per_epoch": 80, "val_every": 0, "threads": 1,
                            "tf_start": 0.0, "tf_end": 0.0, "lr": 3e-4, "lr_final": 3e-4},
            "classifier": {"epochs": 2, "threads": 1, "speed": 1.0}}
    monkeypatch.setitem(ship.RECIPES, str(lines_folder), tiny)
    monkeypatch.setitem(checkpoint.SHIPPED, str(lines_folder),
                        {"short": "lines", "odmo": "odmo_lines.pt", "classifier": "classifier_lines.pt"})
    weights = []
    for run in ("a", "b/new"):  # the second folder is made by build
        out = tmp_path / run
        if run == "a":
            out.mkdir()
        logs = {"odmo": [], "classifier": []}
        reports = ship.build(str(lines_folder), None, out, seed=3, say=lambda m: None, progress=logs["odmo"].append,
                             classifier_progress=logs["classifier"].append)
        assert sorted(p.name for p in out.iterdir()) == ["classifier_lines.pt", "odmo_lines.pt"]
        assert [log["epoch"] for log in logs["classifier"]] == [1, 2] and len(logs["odmo"]) == 5  # 3 + 2 stages
        assert reports["odmo"]["epochs"] == 2 and "val_accuracy" in reports["classifier"]
        clf = torch.load(out / "classifier_lines.pt", weights_only=True)  # what --held-out and eval need, no optimizer
        assert {"split", "report", "state_dict"} <= set(clf) and {"optimizer", "rng"}.isdisjoint(clf)
        ckpt = torch.load(out / "odmo_lines.pt", weights_only=True)
        assert ckpt["kind"] == "odmo" and ckpt["train_config"]["seed"] == 3
        # the second stage started from the first stage's compact file and says so
        assert ckpt["train_config"]["tf_end"] == 0.0 and ckpt["epoch"] == 2
        assert ckpt["init"]["source"] == "odmo_lines.stage1.pt" and ckpt["init"]["epoch"] == 3
        assert ckpt["init"]["train_config"]["tf_end"] == 0.3
        weights.append(ckpt["state_dict"])
        assert len(sample(load_model(out / "odmo_lines.pt"), ["all"], 2, seed=0)) > 0
    assert all(torch.equal(weights[0][k], weights[1][k]) for k in weights[0])


def test_build_refuses_a_file_as_its_folder(lines_folder, tmp_path, monkeypatch):
    monkeypatch.setitem(ship.RECIPES, str(lines_folder), {"odmo": {"epochs": 1}, "classifier": {"epochs": 1}})
    monkeypatch.setitem(checkpoint.SHIPPED, str(lines_folder),
                        {"short": "lines", "odmo": "odmo_lines.pt", "classifier": "classifier_lines.pt"})
    (tmp_path / "f").write_text("x")
    with pytest.raises(UserError, match="--out .*f is a file; give a folder"):
        ship.build(str(lines_folder), None, tmp_path / "f", say=lambda m: None)
    assert (tmp_path / "f").read_text() == "x"


def lines_model_stage(lines_model) -> dict:
    """Recipe settings under which lines_model counts as a finished first stage."""
    return {k: load_checkpoint(lines_model)["train_config"][k] for k in ("epochs", "batch_size", "pairs_per_epoch", "lr")}


def test_build_continues_at_the_stage_it_stopped_in(lines_folder, lines_model, tmp_path, monkeypatch):
    """A first stage finished by an earlier, interrupted build is not trained again: the second
    stage starts from its file, which is removed once the shipped file is written."""
    first = lines_model_stage(lines_model)
    tiny = {"odmo": {**first, "val_every": 0, "threads": 1},  # lines_model was trained as this stage
            "odmo_stage2": {"epochs": 1, "batch_size": 40, "pairs_per_epoch": 80, "val_every": 0, "threads": 1,
                            "tf_start": 0.0, "tf_end": 0.0}}
    monkeypatch.setitem(ship.RECIPES, str(lines_folder), tiny)
    monkeypatch.setitem(checkpoint.SHIPPED, str(lines_folder),
                        {"short": "lines", "odmo": "odmo_lines.pt", "classifier": "classifier_lines.pt"})
    save_checkpoint(tmp_path / "odmo_lines.stage1.pt", checkpoint.compact(load_checkpoint(lines_model)))
    calls, train = [], ship.train_odmo
    monkeypatch.setattr(ship, "train_odmo", lambda *a, **kw: calls.append(a[1].epochs) or train(*a, **kw))
    epochs = []
    ship.build(str(lines_folder), None, tmp_path, skip_classifier=True, say=lambda m: None,
               progress=lambda log: epochs.append(log["epoch"]))
    assert calls == [1] and epochs == [151]  # stage 2 only, counted after stage 1's 150 epochs
    assert sorted(p.name for p in tmp_path.iterdir()) == ["odmo_lines.pt"]
    assert load_checkpoint(tmp_path / "odmo_lines.pt")["init"]["epoch"] == 150  # lines_model's length
    assert ship.total_epochs(str(lines_folder)) == 151


@pytest.mark.parametrize("change, named", [({"epochs": 7}, "epochs 150, not 7"), ({"seed_offset": 1}, "seed 0, not 1")])
def test_build_refuses_a_finished_stage_trained_otherwise(lines_folder, lines_model, tmp_path, monkeypatch, change, named):
    """A stage file left by a build under another recipe (or --seed) is not taken as finished: one
    line naming the file and the setting, and nothing trained or removed."""
    first = lines_model_stage(lines_model)
    tiny = {"odmo": {**first, "val_every": 0, "threads": 1, **change},
            "odmo_stage2": {"epochs": 1, "batch_size": 40, "pairs_per_epoch": 80, "val_every": 0, "threads": 1}}
    monkeypatch.setitem(ship.RECIPES, str(lines_folder), tiny)
    monkeypatch.setitem(checkpoint.SHIPPED, str(lines_folder),
                        {"short": "lines", "odmo": "odmo_lines.pt", "classifier": "classifier_lines.pt"})
    save_checkpoint(tmp_path / "odmo_lines.stage1.pt", checkpoint.compact(load_checkpoint(lines_model)))
    monkeypatch.setattr(ship, "train_odmo", lambda *a, **kw: pytest.fail("trained"))
    with pytest.raises(UserError, match=f"odmo_lines.stage1.pt was trained with other settings.*{named}"):
        ship.build(str(lines_folder), None, tmp_path, skip_classifier=True, say=lambda m: None)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["odmo_lines.stage1.pt"]


@pytest.mark.parametrize("change, named", [({"epochs": 7}, "epochs 150, not 7"),
                                           ({"model": {"motion_hidden": 64}}, "motion_hidden 32, not 64")])
def test_build_refuses_to_resume_a_stage_started_otherwise(lines_folder, lines_model, tmp_path, monkeypatch,
                                                           change, named):
    """A stage's training checkpoint left by a build under another recipe is not resumed: resume
    would keep the checkpoint's own length and model and quietly train another stage than the recipe's."""
    first = lines_model_stage(lines_model)
    tiny = {"odmo": {**first, "val_every": 0, "threads": 1, **change}}
    monkeypatch.setitem(ship.RECIPES, str(lines_folder), tiny)
    monkeypatch.setitem(checkpoint.SHIPPED, str(lines_folder),
                        {"short": "lines", "odmo": "odmo_lines.pt", "classifier": "classifier_lines.pt"})
    save_checkpoint(tmp_path / "odmo_lines.training.pt", load_checkpoint(lines_model))  # has its training state
    monkeypatch.setattr(ship, "train_odmo", lambda *a, **kw: pytest.fail("trained"))
    with pytest.raises(UserError, match=f"odmo_lines.training.pt was trained with other settings.*{named}"):
        ship.build(str(lines_folder), None, tmp_path, skip_classifier=True, say=lambda m: None)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["odmo_lines.training.pt"]


def test_stage_differences_names_each_setting_and_skips_unrecorded_model_values():
    stage = {"epochs": 2, "lr": 1e-3, "threads": 2, "seed_offset": 1, "model": {"pose_loss": "body"}}
    recorded = {"epochs": 2, "lr": 1e-3, "seed": 1, "threads": 1}  # threads differ: not compared
    assert ship.stage_differences(recorded, {"pose_loss": "body"}, stage, 0) == []
    assert ship.stage_differences(recorded, None, stage, 0) == []  # model values not recorded
    assert ship.stage_differences(recorded, {"pose_loss": "world"}, stage, 0) == ["pose_loss 'world', not 'body'"]
    assert ship.stage_differences({**recorded, "seed": 0}, {}, stage, 0) == ["seed 0, not 1", "pose_loss None, not 'body'"]


def test_build_chains_a_third_stage(lines_folder, tmp_path, monkeypatch):
    """Each later stage starts from the previous stage's compact file; the shipped file's init names
    the chain and the stage files are removed at the end."""
    one = {"epochs": 1, "batch_size": 40, "pairs_per_epoch": 80, "val_every": 0, "threads": 1,
           "tf_start": 0.0, "tf_end": 0.0}
    tiny = {"odmo": {**one, "epochs": 2, "tf_start": 1.0, "tf_end": 0.3}, "odmo_stage2": one,
            "odmo_stage3": {**one, "lr": 1e-4, "lr_final": 1e-5, "seed_offset": 2, "model": {"energy_weight": 0.3}}}
    monkeypatch.setitem(ship.RECIPES, str(lines_folder), tiny)
    monkeypatch.setitem(checkpoint.SHIPPED, str(lines_folder),
                        {"short": "lines", "odmo": "odmo_lines.pt", "classifier": "classifier_lines.pt"})
    ship.build(str(lines_folder), None, tmp_path, skip_classifier=True, say=lambda m: None)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["odmo_lines.pt"]
    ckpt = load_checkpoint(tmp_path / "odmo_lines.pt")
    assert ckpt["train_config"]["lr_final"] == 1e-5 and ckpt["epoch"] == 1
    # a stage's "model" entry changes those config values only, on top of the file it started from
    assert ckpt["config"]["energy_weight"] == 0.3 and ckpt["config"]["free_energy_weight"] == 2.0  # the preset's
    assert ckpt["init"]["source"] == "odmo_lines.stage2.pt" and ckpt["init"]["train_config"]["lr_final"] == 0.0  # constant
    # a stage's seed_offset moves that stage's seed only
    assert ckpt["train_config"]["seed"] == 2 and ckpt["init"]["train_config"]["seed"] == 0
    assert ckpt["init"]["init"]["source"] == "odmo_lines.stage1.pt" and ckpt["init"]["init"]["epoch"] == 2
    # each earlier stage's model config is kept beside its training config (stage 2's: the preset's)
    assert ckpt["init"]["config"]["energy_weight"] == 2.0 and ckpt["init"]["init"]["config"] == ckpt["init"]["config"]
    assert ship.total_epochs(str(lines_folder)) == 4


def test_stages_must_be_numbered_in_order():
    assert ship._stages({"odmo_stage3": {}, "odmo": {}, "odmo_stage2": {}, "classifier": {}}) == \
        ["odmo", "odmo_stage2", "odmo_stage3"]
    with pytest.raises(ValueError, match="odmo_stage2, odmo_stage3"):
        ship._stages({"odmo": {}, "odmo_stage3": {}})


def test_build_with_a_recipe_file_trains_one_run_and_keeps_the_recipe(lines_folder, tmp_path, monkeypatch):
    from test_recipe import RECIPE  # tests/ is on the path (pytest's rootdir-less prepend import mode)

    monkeypatch.setitem(ship.RECIPES, str(lines_folder), {"classifier": {"epochs": 1, "threads": 1, "speed": 1.0}})
    monkeypatch.setitem(checkpoint.SHIPPED, str(lines_folder),
                        {"short": "lines", "odmo": "odmo_lines.pt", "classifier": "classifier_lines.pt"})
    path = tmp_path / "lines.toml"
    path.write_text(RECIPE)
    out = tmp_path / "out"
    out.mkdir()
    reports = ship.build(str(lines_folder), None, out, seed=2, skip_classifier=True, say=lambda m: None, recipe_file=path)
    assert sorted(p.name for p in out.iterdir()) == ["odmo_lines.pt"]  # the training file removed
    ckpt = torch.load(out / "odmo_lines.pt", weights_only=True)
    assert ckpt["recipe_phase"] == 1 and ckpt["recipe"]["phases"][1]["name"] == "the pose decoder, planted feet"
    assert {"optimizer", "rng"}.isdisjoint(ckpt) and ckpt["train_config"]["seed"] == 2
    assert reports["odmo"]["epochs"] == 5 and reports["odmo"]["pairs"] == 200
    assert len(sample(load_model(out / "odmo_lines.pt"), ["all"], 2, seed=0)) > 0
