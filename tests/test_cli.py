"""What every command shares: `--version`, `-h`, help on every option, one meaning per option name,
options of another model refused before any work, tables that fit 80 columns."""

from __future__ import annotations

import pytest
import typer
from typer.testing import CliRunner

from odmo_cli import __version__
from odmo_cli.cli import app
from odmo_cli.data.demo import demo_folder


def commands(group=None, path=()):
    """(path, click command) of every command, subcommands included."""
    group = group or typer.main.get_command(app)
    for name, cmd in group.commands.items():
        if hasattr(cmd, "commands"):
            yield from commands(cmd, path + (name,))
        else:
            yield path + (name,), cmd


ALL = list(commands())


def test_version_and_short_help():
    res = CliRunner().invoke(app, ["--version"])
    assert res.exit_code == 0 and res.stdout.strip() == f"odmo {__version__}"
    for args in (["-h"], ["train", "-h"], ["train", "a2m", "-h"], ["data", "list", "-h"], ["eval", "-h"]):
        res = CliRunner().invoke(app, args)
        assert res.exit_code == 0 and "Usage" in res.stdout, args


@pytest.mark.parametrize("path, cmd", ALL, ids=[" ".join(p) for p, _ in ALL])
def test_every_option_has_help_and_one_meaning(path, cmd):
    options = {o: p for p in cmd.params for o in p.opts if o.startswith("--")}
    for name, param in options.items():
        if name == "--help":
            continue
        assert param.help, f"odmo {' '.join(path)} {name} has no help"
    if "--json" in options:  # a switch printing JSON on stdout, everywhere
        assert options["--json"].is_flag, path
    if "--model" in options:  # a checkpoint or a shipped model, everywhere
        assert "checkpoint" in options["--model"].help.lower(), path
    if "--out" in options:  # a file or folder to write, never a switch
        assert not options["--out"].is_flag, path


@pytest.mark.parametrize("path", [p for p, _ in ALL], ids=[" ".join(p) for p, _ in ALL])
def test_switches_show_as_switches_in_help(path):
    res = CliRunner(env={"COLUMNS": "200"}).invoke(app, [*path, "-h"])
    assert res.exit_code == 0 and "<bool>" not in res.stdout.lower()


INAPPLICABLE = {  # one option of another model for each kind
    "odmo": ["--representation", "lie"],
    "a2m": ["--ablate", "es"],
    "dvgan": ["--sigma2", "0.0025"],
    "classifier": ["--generator", "rnn"],
}


@pytest.mark.parametrize("kind", INAPPLICABLE)
def test_an_option_of_another_model_is_refused_before_any_work(kind, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "m.pt"
    args = ["train", kind, "--dataset", str(demo_folder("humanact12")), "--epochs", "1", "--out", str(out),
            *INAPPLICABLE[kind]]
    res = CliRunner().invoke(app, args)
    assert res.exit_code == 2, res.output
    assert res.stderr.startswith(f"error: {INAPPLICABLE[kind][0]} does not apply to `odmo train {kind}`; its options: ")
    assert res.stderr.count("\n") == 1 and "Traceback" not in res.output
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("kind", ["odmo", "classifier"])
def test_resume_without_epochs_keeps_the_runs_own_length(kind, tmp_path, monkeypatch):
    """A 1-epoch run resumed without --epochs stays 1 epoch (not the command's default of 300 or 200,
    which would also stretch its schedules); --epochs 2 extends it."""
    import torch

    monkeypatch.chdir(tmp_path)
    base = ["train", kind, "--dataset", str(demo_folder("humanact12")), "--threads", "1"]
    assert CliRunner().invoke(app, [*base, "--epochs", "1", "--out", "m.pt"]).exit_code == 0
    res = CliRunner().invoke(app, [*base, "--resume", "m.pt", "--out", "same.pt"])
    assert res.exit_code == 0, res.output
    saved = torch.load(tmp_path / "same.pt", weights_only=True)
    assert saved["epoch"] == 1 and saved["train_config"]["epochs"] == 1
    res = CliRunner().invoke(app, [*base, "--resume", "m.pt", "--epochs", "2", "--out", "longer.pt"])
    assert res.exit_code == 0, res.output
    assert torch.load(tmp_path / "longer.pt", weights_only=True)["epoch"] == 2


@pytest.mark.parametrize("kind, args, message", [
    # ODMO (`odmo train` without a kind is ODMO)
    (None, ["--ablate", "nope"], "unknown ablation 'nope'; valid: es, traj, cons, end-point"),
    (None, ["--epochs", "0"], "--epochs must be positive, got 0"),
    (None, ["--resume", "missing.pt"], "checkpoint not found"),
    (None, ["--sigma2", "0"], "--sigma2 must be a number > 0, got 0.0"),
    (None, ["--recon-weight", "-1"], "--recon-weight must be a number > 0, got -1.0"),
    (None, ["--energy-weight", "-1"], "--energy-weight must be a number >= 0, got -1.0"),
    # nan and inf fail no `x < bound` test: each is refused by name
    (None, ["--sigma2", "inf"], "--sigma2 must be a finite number, got inf"),
    (None, ["--energy-weight", "nan"], "--energy-weight must be a finite number, got nan"),
    (None, ["--lr", "nan"], "--lr must be a finite number, got nan"),
    (None, ["--weight-decay", "inf"], "--weight-decay must be a finite number, got inf"),
    ("a2m", ["--lr", "nan"], "--lr must be a finite number, got nan"),
    ("dvgan", ["--lr", "inf"], "--lr must be a finite number, got inf"),
    ("classifier", ["--lr", "inf"], "--lr must be a finite number, got inf"),
    (None, ["--same-class-fraction", "1.5"], "--same-class-fraction must be in [0, 1] (or -1: independent pairs), got 1.5"),
    ("odmo", ["--representation", "lie"], "--representation does not apply to `odmo train odmo`"),
    ("odmo", ["--generator", "rnn"], "--generator does not apply to `odmo train odmo`"),
    # Action2Motion
    ("a2m", ["--representation", "quat"], "unknown representation 'quat'; valid: xyz, lie"),
    ("a2m", ["--ablate", "es"], "--ablate does not apply to `odmo train a2m`"),
    ("a2m", ["--epochs", "0"], "--epochs must be positive, got 0"),
    ("a2m", ["--n-critic", "5"], "--n-critic does not apply to `odmo train a2m`"),
    # DVGAN
    ("dvgan", ["--generator", "transformer"], "unknown DVGAN generator 'transformer'; valid: cnn, rnn"),
    ("dvgan", ["--epochs", "0"], "--epochs must be positive, got 0"),
    ("dvgan", ["--resume", "missing.pt"], "checkpoint not found"),
    ("dvgan", ["--n-critic", "0"], "--n-critic must be positive, got 0"),
    # the classifier
    ("classifier", ["--epochs", "0"], "--epochs must be positive, got 0"),
    ("classifier", ["--resume", "missing.pt"], "checkpoint not found"),
    # no such model
    ("gan", [], "unknown model 'gan'; valid: odmo, classifier, a2m, dvgan"),
])
def test_cli_train_bad_input(tmp_path, kind, args, message):
    """One line on stderr, exit 2, nothing written."""
    out = tmp_path / "m.pt"
    res = CliRunner().invoke(app, ["train", *([kind] if kind else []), "--dataset", str(demo_folder("humanact12")),
                                   "--out", str(out), *args])
    assert res.exit_code == 2
    assert message in res.stderr and res.stderr.count("\n") == 1 and "Traceback" not in res.output
    assert list(tmp_path.iterdir()) == []


def test_plain_train_is_odmo(tmp_path):
    res = CliRunner().invoke(app, ["train", "--dataset", str(demo_folder("humanact12")), "--representation", "lie",
                                   "--out", str(tmp_path / "m.pt")])
    assert res.exit_code == 2 and "does not apply to `odmo train odmo`" in res.stderr


def test_data_list_fits_80_columns(tmp_path):
    res = CliRunner(env={"COLUMNS": "80"}).invoke(app, ["data", "list", "--data", str(tmp_path)])
    assert res.exit_code == 0, res.output
    assert all(len(line) <= 80 for line in res.stdout.splitlines())
    assert "humanact12" in res.stdout and "cmu_mocap" in res.stdout
