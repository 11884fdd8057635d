"""`odmo ship`: the recipe runner that rebuilds the shipped models, and the compact file format."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from odmo_cli import ship
from odmo_cli.cli import app
from odmo_cli.errors import UserError
from odmo_cli.generate import load_model, sample
from odmo_cli.io import load_checkpoint, save_checkpoint


def test_compact_keeps_what_sampling_needs_in_half_the_space(lines_model, tmp_path):
    full = load_checkpoint(lines_model)
    small = ship.compact(full)
    assert {"optimizer", "rng", "split"}.isdisjoint(small)
    assert {"config", "dataset", "latent_bank", "modes", "state_dict"} <= set(small)
    assert len(small["history"]) == 1 and small["weights_dtype"] == "float16"
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
            "classifier": {"epochs": 2, "threads": 1, "speed": 1.0},
            "file": "odmo_lines.pt", "classifier_file": "classifier_lines.pt"}
    monkeypatch.setitem(ship.RECIPES, str(lines_folder), tiny)
    weights = []
    for run in ("a", "b"):
        out = tmp_path / run
        out.mkdir()
        reports = ship.build(str(lines_folder), None, out, seed=3, say=lambda m: None)
        assert sorted(p.name for p in out.iterdir()) == ["classifier_lines.pt", "odmo_lines.pt"]
        assert reports["odmo"]["epochs"] == 3 and "val_accuracy" in reports["classifier"]
        ckpt = torch.load(out / "odmo_lines.pt", weights_only=True)
        assert ckpt["kind"] == "odmo" and ckpt["train_config"]["seed"] == 3
        weights.append(ckpt["state_dict"])
        assert len(sample(load_model(out / "odmo_lines.pt"), ["all"], 2, seed=0)) > 0
    assert all(torch.equal(weights[0][k], weights[1][k]) for k in weights[0])
