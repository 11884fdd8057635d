"""Recipes as files (`odmo train --recipe FILE`): strict keys, phases in one run under one seed, and
exact resume across a phase boundary."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from odmo_cli.checkpoint import load_checkpoint, load_model
from odmo_cli.cli import app
from odmo_cli.data.locate import resolve
from odmo_cli.data.readers import read_dataset
from odmo_cli.errors import UserError
from odmo_cli.generation.generate import sample
from odmo_cli.training.recipe import finished_run_differences, load_recipe, train_recipe

RECIPE = """
dataset = "lines"
preset = "paper"
[model]
motion_hidden = 16    # small: a test
traj_hidden = 16
encoder_fc = 16
latent_dim = 4
[train]
batch_size = 20
pairs_per_epoch = 40
val_fraction = 0.1
val_every = 2
checkpoint_every = 1
threads = 1
[[phases]]
name = "all networks"
epochs = 3
lr = 1e-2
lr_final = 1e-3
[[phases]]
name = "the pose decoder, planted feet"
epochs = 2
lr = 1e-3
tf_start = 0.0
tf_end = 0.0
train_parts = "motion"
[phases.model]
foot_weight = 5.0
"""


@pytest.fixture
def recipe_file(tmp_path):
    path = tmp_path / "lines.toml"
    path.write_text(RECIPE)
    return path


@pytest.fixture(scope="module")
def lines_clips(lines_folder):
    manifest, root = resolve(lines_folder)
    return read_dataset(root, manifest)


@pytest.mark.parametrize("edit, message", [
    (("[model]\n", "[model]\nenergy_wieght = 1.0\n"), "lines.toml \\[model\\]: 'energy_wieght' is not a setting; did you mean 'energy_weight'"),
    (("lr_final = 1e-3", "lr_fnal = 1e-3"), "phase 1: 'lr_fnal' is not a setting; did you mean 'lr_final'"),
    (("foot_weight = 5.0", "motion_hidden = 32"), "phase 2 \\[phases.model\\]: 'motion_hidden' is not a setting"),
    (("epochs = 3\n", ""), "phase 1: give its epochs"),
    (("lr = 1e-2", "lr = -1.0"), "phase 1: lr must be positive"),
    (("preset = \"paper\"", "preset = \"paper\"\nseed = 3"), "'seed' is not a setting"),
    (("[train]", "[train"), "not valid TOML"),
])
def test_a_recipe_with_a_mistake_is_refused_in_one_line(recipe_file, edit, message):
    recipe_file.write_text(RECIPE.replace(*edit))
    with pytest.raises(UserError, match=message):
        load_recipe(recipe_file)


def test_phases_train_in_one_run_and_the_file_records_them(recipe_file, lines_clips, tmp_path):
    recipe = load_recipe(recipe_file)
    assert recipe.epochs == 5 and recipe.model_values(0) == {"motion_hidden": 16, "traj_hidden": 16,
                                                             "encoder_fc": 16, "latent_dim": 4}
    out = tmp_path / "odmo.pt"
    result = train_recipe(lines_clips, recipe, out, seed=3)
    ckpt = load_checkpoint(out)
    assert ckpt["recipe_phase"] == 1 and ckpt["recipe"]["phases"][1]["model"] == {"foot_weight": 5.0}
    assert [h["phase"] for h in ckpt["history"]] == [0, 0, 0, 1, 1]
    assert ckpt["config"]["foot_weight"] == 5.0 and ckpt["train_config"]["train_parts"] == "motion"
    assert ckpt["train_config"]["seed"] == 3
    assert result.report["pairs"] == 200 and result.report["hours"] > 0
    assert "held_out_foot_skate" in result.report
    assert load_model(out).model.cfg.bones == "rigid"  # a new file decodes rigid bodies
    # what test_shipped asks of a shipped file trained by a recipe
    assert finished_run_differences(ckpt, recipe) == []
    assert finished_run_differences({**ckpt, "config": {**ckpt["config"], "foot_weight": 1.0}}, recipe) == [
        "model value foot_weight = 1.0, the recipe's 5.0"]
    assert finished_run_differences({**ckpt, "init": {"kind": "odmo"}}, recipe) == [
        "started from another file (--init), not from scratch"]
    other = load_recipe(recipe_file)
    other.phases[1].train["epochs"] = 3
    assert finished_run_differences(ckpt, other) == ["trained by another recipe than lines.toml",
                                                     "stopped at epoch 2 of the last phase's 3"]
    assert finished_run_differences({"kind": "odmo"}, recipe) == ["not a recipe run (no recipe in the file)"]
    # a setting the file predates reads as this version's default; the preset's loss scales count too
    older = {k: v for k, v in ckpt["config"].items() if k != "energy_on"}
    assert finished_run_differences({**ckpt, "config": older}, recipe) == []
    released = load_recipe(recipe_file)
    released.preset = "release"
    assert finished_run_differences(ckpt, released) == [
        "trained by another recipe than lines.toml", "model value sigma2 = 0.05, the recipe's 0.0025",
        "model value recon_weight = 1.0, the recipe's 2.0"]


def test_resume_across_a_phase_boundary_is_exact(recipe_file, lines_clips, tmp_path):
    recipe = load_recipe(recipe_file)
    whole = tmp_path / "whole.pt"
    train_recipe(lines_clips, recipe, whole, seed=1)
    cut = tmp_path / "cut.pt"

    def stop_after_4(log):
        if log["epoch"] == 4:  # the first epoch of the second phase
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        train_recipe(lines_clips, recipe, cut, seed=1, progress=stop_after_4)
    assert load_checkpoint(cut)["recipe_phase"] == 1 and load_checkpoint(cut)["epoch"] == 1
    assert finished_run_differences(load_checkpoint(cut), recipe) == ["stopped at epoch 1 of the last phase's 2"]
    # a stopped run samples as it is (its latent bank and modes were built when it stopped)
    stopped = sample(load_model(cut), ["all"], 2, seed=0)
    assert stopped.motions.shape[0] == 4 and np.isfinite(stopped.motions).all()
    train_recipe(lines_clips, recipe, cut, seed=1, resume=cut)
    a, b = load_checkpoint(whole)["state_dict"], load_checkpoint(cut)["state_dict"]
    assert all(torch.equal(a[k], b[k]) for k in a)
    with pytest.raises(UserError, match="--seed 1, not 2"):
        train_recipe(lines_clips, recipe, cut, seed=2, resume=cut)


def test_odmo_train_recipe_on_the_command_line(recipe_file, lines_folder, tmp_path):
    out = tmp_path / "cli.pt"
    r = CliRunner().invoke(app, ["train", "--recipe", str(recipe_file), "--dataset", str(lines_folder),
                                 "--out", str(out), "--seed", "2"])
    assert r.exit_code == 0, r.output
    assert load_checkpoint(out)["recipe"]["phases"][0]["name"] == "all networks"
    r = CliRunner().invoke(app, ["train", "--recipe", str(recipe_file), "--dataset", str(lines_folder),
                                 "--lr", "0.1", "--out", str(out)])
    assert r.exit_code == 2 and "--lr" in r.output and "recipe" in r.output


@pytest.mark.parametrize("name", ["humanact12", "cmu_mocap"])
def test_the_projects_recipes_read(name):
    from pathlib import Path

    recipe = load_recipe(Path(__file__).resolve().parents[1] / "recipes" / f"{name}.toml")
    assert recipe.dataset == name and recipe.phases and recipe.budget_hours == 6.0
    for i in range(len(recipe.phases)):
        recipe.train_config(i)  # every phase is a valid TrainConfig


def test_one_default_rate_schedule_for_the_library_and_the_command_line():
    from odmo_cli.training.odmo import TrainConfig

    tc = TrainConfig(lr=3e-3, epochs=10)  # as `odmo train --lr 3e-3`: constant
    assert [tc.learning_rate(e) for e in (0, 9)] == [3e-3, 3e-3]
    decayed = TrainConfig(lr=3e-3, lr_final=1e-4, epochs=10)
    assert decayed.learning_rate(9) == pytest.approx(1e-4)
    with pytest.raises(UserError, match="lr_final must be >= 0"):
        TrainConfig(lr_final=-1.0)


def test_a_recipe_leaves_the_datas_shapes_to_the_data(recipe_file):
    recipe_file.write_text(RECIPE.replace("[model]\n", "[model]\nup_axis = 2\n"))
    with pytest.raises(UserError, match="'up_axis' is not a setting"):
        load_recipe(recipe_file)
    recipe_file.write_text(RECIPE.replace('preset = "paper"', 'preset = "papr"'))
    with pytest.raises(UserError, match="unknown preset 'papr'; valid: paper, release, odmo"):
        load_recipe(recipe_file)


def test_a_recipe_run_resumes_only_with_its_recipe(recipe_file, lines_clips, tmp_path):
    from odmo_cli.training.odmo import TrainConfig, train_odmo

    recipe = load_recipe(recipe_file)
    cut = tmp_path / "cut.pt"

    def stop(log):
        if log["epoch"] == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        train_recipe(lines_clips, recipe, cut, progress=stop)
    with pytest.raises(UserError, match="resume it with --recipe"):
        train_odmo(lines_clips, TrainConfig(epochs=3), tmp_path / "x.pt", resume=cut)
    recipe_file.write_text(RECIPE.replace('preset = "paper"', 'preset = "paper"\nbudget_hours = 2.0'))  # a stated budget changes no training
    train_recipe(lines_clips, load_recipe(recipe_file), cut, resume=cut)
