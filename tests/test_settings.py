"""Configs refuse typos, the training commands' options come from the configs, and every setting can
come from a --config file (cli.settings)."""

from __future__ import annotations

import warnings
from dataclasses import fields

import pytest
import typer
from typer.testing import CliRunner

from odmo_cli.checkpoint import load_checkpoint
from odmo_cli.cli import app
from odmo_cli.cli.settings import NOT_IN_FILES, knobs, read_config_file
from odmo_cli.config import ConfigError, IgnoredSettings
from odmo_cli.models.a2m import A2MConfig
from odmo_cli.models.classifier import ClassifierConfig
from odmo_cli.models.dvgan import DVGANConfig
from odmo_cli.models.odmo_config import ODMOConfig
from odmo_cli.training.configs import (A2MTrainConfig, ClassifierTrainConfig, DVGANTrainConfig, LoopConfig,
                                       TrainConfig)

CONFIGS = [ODMOConfig, TrainConfig, LoopConfig, A2MTrainConfig, DVGANTrainConfig, ClassifierTrainConfig, A2MConfig,
           DVGANConfig]
# the training commands and the trainer config each builds its options from
COMMANDS = {"odmo": TrainConfig, "a2m": A2MTrainConfig, "dvgan": DVGANTrainConfig, "classifier": ClassifierTrainConfig}


def _misspelt(cls) -> tuple[str, str]:
    """A field of cls with two letters swapped, and the field."""
    name = next(f.name for f in fields(cls) if len(f.name) > 5 and f.name not in NOT_IN_FILES)
    return name[:2] + name[3] + name[2] + name[4:], name


@pytest.mark.parametrize("cls", CONFIGS, ids=lambda c: c.__name__)
def test_a_misspelt_key_is_refused_with_the_nearest_valid_one(cls):
    wrong, right = _misspelt(cls)
    with pytest.raises(ConfigError, match=f"'{wrong}' is not a setting; did you mean '{right}'"):
        cls.from_dict({wrong: 1})


def test_the_classifier_config_refuses_a_misspelt_key():
    with pytest.raises(ConfigError, match="'hiden' is not a setting; did you mean 'hidden'"):
        ClassifierConfig.from_dict({"input_size": 72, "n_classes": 12, "hiden": 64})


def test_a_saved_config_drops_what_this_version_does_not_know_and_says_so():
    saved = {**ODMOConfig(motion_hidden=32).to_dict(), "retired_weight": 2.0}
    with pytest.warns(IgnoredSettings, match="retired_weight"):
        cfg = ODMOConfig.from_saved(saved)
    assert cfg.motion_hidden == 32
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a config with nothing unknown loads silently
        assert ODMOConfig.from_saved(cfg.to_dict()) == cfg


def test_a_config_names_the_field_it_refuses():
    with pytest.raises(ConfigError) as e:
        TrainConfig(same_class_fraction=2.0)
    assert e.value.field == "same_class_fraction" and "[0, 1]" in e.value.problem
    with pytest.raises(ConfigError) as e:
        ODMOConfig(foot_weight=1.0)  # no skeleton: no feet to plant
    assert e.value.field == "foot_weight"


@pytest.mark.parametrize("kind, cls", COMMANDS.items())
def test_every_option_default_is_the_configs(kind, cls):
    """The options are None unless given: the library's default is the command line's."""
    from odmo_cli.cli.settings import sources
    from odmo_cli.cli.train_commands import _train_config

    assert _train_config(sources({}, None, {"train": cls}), cls, None, 0, 0) == cls()
    command = typer.main.get_command(app).commands["train"].commands[kind]
    options = {p.name: p for p in command.params}
    for name in knobs(cls):
        assert options[name].default is None, name  # not given: the config's default


@pytest.mark.parametrize("kind", COMMANDS)
def test_the_training_commands_refuse_a_misspelt_config_key(kind, tmp_path):
    config = tmp_path / "c.toml"
    config.write_text("[train]\nbatch_sise = 8\n")
    r = CliRunner().invoke(app, ["train", kind, "--config", str(config), "--out", str(tmp_path / "m.pt")])
    assert r.exit_code == 2, r.output
    assert r.output.strip() == f"error: {config} [train]: 'batch_sise' is not a setting; did you mean 'batch_size'?"
    assert not (tmp_path / "m.pt").exists()


def test_a_refused_value_names_its_flag_or_its_file(tmp_path):
    config = tmp_path / "c.toml"
    config.write_text("[model]\ncons = \"sideways\"\n[train]\ncrops = \"first\"\n")
    r = CliRunner().invoke(app, ["train", "--config", str(config)])
    assert r.exit_code == 2 and r.output.strip() == \
        f"error: {config} [model]: cons must be one of all, ground, got 'sideways'"
    r = CliRunner().invoke(app, ["train", "--config", str(config), "--cons", "ground", "--decoder-dropout", "1.5"])
    assert r.exit_code == 2 and r.output.strip() == "error: --decoder-dropout must be in [0, 1), got 1.5"
    config.write_text("[modle]\n")
    r = CliRunner().invoke(app, ["train", "--config", str(config)])
    assert r.exit_code == 2 and "did you mean [model]?" in r.output


def test_every_setting_but_the_datas_shapes_can_come_from_a_config_file(tmp_path):
    path = tmp_path / "all.toml"
    model = {f.name: getattr(ODMOConfig(), f.name) for f in fields(ODMOConfig) if f.name not in NOT_IN_FILES}
    train = {f.name: getattr(TrainConfig(), f.name) for f in fields(TrainConfig) if f.name not in NOT_IN_FILES}
    lines = ["[model]", *(f"{k} = {_toml(v)}" for k, v in model.items()),
             "[train]", *(f"{k} = {_toml(v)}" for k, v in train.items())]
    path.write_text("\n".join(lines) + "\n")
    assert read_config_file(path, {"model": ODMOConfig, "train": TrainConfig}) == {"model": model, "train": train}
    path.write_text("[model]\nn_joints = 3\n")
    with pytest.raises(Exception, match="'n_joints' is not a setting"):
        read_config_file(path, {"model": ODMOConfig, "train": TrainConfig})


def _toml(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    return f'"{value}"' if isinstance(value, str) else repr(value)


def test_a_config_file_trains_with_its_settings_and_the_options_win(lines_folder, tmp_path):
    config = tmp_path / "small.toml"
    config.write_text("[model]\nmotion_hidden = 16\ntraj_hidden = 16\nencoder_fc = 16\nlatent_dim = 4\nalpha = 3.0\n"
                      "[train]\nepochs = 2\nbatch_size = 20\ngrad_clip = 0.5\nval_fraction = 0.2\nsplit_seed = 7\n"
                      "pairs_per_epoch = 40\n")
    out = tmp_path / "m.pt"
    r = CliRunner().invoke(app, ["train", "--dataset", str(lines_folder), "--config", str(config), "--alpha", "4",
                                 "--out", str(out), "--threads", "1"])
    assert r.exit_code == 0, r.output
    ckpt = load_checkpoint(out)
    assert ckpt["config"]["motion_hidden"] == 16 and ckpt["config"]["alpha"] == 4.0  # the option wins
    tc = ckpt["train_config"]
    assert (tc["epochs"], tc["grad_clip"], tc["val_fraction"], tc["split_seed"], tc["pairs_per_epoch"]) == \
        (2, 0.5, 0.2, 7, 40)


def test_odmo_train_help_groups_its_options_in_panels():
    r = CliRunner().invoke(app, ["train", "odmo", "-h"], terminal_width=200)
    assert r.exit_code == 0
    titles = [line.split("─")[1].strip() for line in r.output.splitlines() if line.startswith("╭─")]
    assert titles[1:] == ["Data", "Schedule", "Losses", "Architecture", "Experimental", "Run"]
