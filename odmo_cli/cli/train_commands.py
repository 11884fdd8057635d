"""`odmo train odmo|a2m|dvgan|classifier` (plain `odmo train` trains ODMO) and `odmo ship`.

Each subcommand takes only the options that apply to its model; any other option is refused by
the parser with one line and exit 2, before any data is read.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, Optional

import typer

from odmo_cli.cli.common import (Command, DataOpt, DeviceHelp, DeviceOpt, JsonOpt, SeedOpt, app, console, device_for, err_console,
                                 print_json, resolve_spec, train_app)
from odmo_cli.cli.settings import ConfigOpt, flag, sources, with_settings
from odmo_cli.config import ConfigError
from odmo_cli.errors import UserError
from odmo_cli.models.odmo_config import ODMOConfig
from odmo_cli.training.configs import A2MTrainConfig, ClassifierTrainConfig, DVGANTrainConfig, TrainConfig

ABLATIONS = ("es", "traj", "cons", "end-point")

# The options every trainer shares (their defaults are each model's: None means "the model's own").
DatasetOpt = Annotated[str, typer.Option("--dataset", help="Dataset name (see `odmo data list`) or a motion folder.", rich_help_panel="Data")]
ResumeHelp = "Checkpoint to continue from, exactly (its model and schedule are kept; its own length unless --epochs extends it)."
ResumeOpt = Annotated[Optional[Path], typer.Option("--resume", help=ResumeHelp, rich_help_panel="Run")]
ThreadsOpt = Annotated[int, typer.Option("--threads", help="CPU threads for torch (0: torch's default).", rich_help_panel="Run")]
NprocHelp = ("Processes training together on this machine (data-parallel, the same global batch; with --device cuda "
             "one GPU each). Several machines: torchrun, see docs/training.md.")
NprocOpt = Annotated[int, typer.Option("--nproc", help=NprocHelp, rich_help_panel="Run")]


def _out(out: Optional[Path], kind: str) -> Path:
    return out or Path(f"{kind}.pt")


OutOpt = Annotated[Optional[Path], typer.Option("--out", help="Checkpoint to write (default: <model>.pt, e.g. odmo.pt).", rich_help_panel="Run")]


def _start(device: str, nproc: int) -> bool:
    """Check --device before any work; with --nproc N > 1, run this very command as N processes
    and exit with their status. Returns whether this process prints (rank 0 of a run)."""
    from odmo_cli.training.distributed import env_rank, env_world_size, launch

    device_for(device)
    if nproc < 1:
        raise UserError(f"--nproc must be at least 1, got {nproc}")
    if nproc > 1:
        if env_world_size() > 1:
            raise UserError("--nproc does not apply inside a run of several processes (torchrun starts them)")
        from typer._click.globals import get_current_context

        raise typer.Exit(launch(nproc, _without_nproc(get_current_context().meta["odmo.train_argv"])))
    return env_rank() == 0


def _without_nproc(argv: list[str]) -> list[str]:
    out, skip = [], False
    for arg in argv:
        if skip:
            skip = False
        elif arg == "--nproc":
            skip = True
        elif not arg.startswith("--nproc="):
            out.append(arg)
    return out


TrainConfigOpt = Annotated[Optional[Path], typer.Option(
    "--config", help="TOML file with a \\[train] table setting any of the trainer's settings (options given here "
                     "win; docs/training.md).", rich_help_panel="Run")]


def _train_config(src, cls, resume: Optional[Path], seed: int, threads: int):
    """The trainer's config: the --config file's [train], then the options given; resuming without
    --epochs, the checkpoint's own length (a default would stretch a shorter run's schedules)."""
    from odmo_cli.training.loop import resume_epochs

    train = src.values("train", cls)
    if "epochs" not in train and resume is not None:
        train["epochs"] = resume_epochs(resume, None)
    return src.build(cls, {**train, "seed": seed, "threads": threads})


def _clips(dataset: str, data: Optional[Path]):
    from odmo_cli.data.readers import read_dataset

    manifest, root = resolve_spec(dataset, data)
    return read_dataset(root, manifest)


RunPanel = "Run"


@train_app.command("odmo", cls=Command)
@with_settings(TrainConfig, ODMOConfig)
def train_odmo_cmd(
    dataset: Annotated[Optional[str], typer.Option("--dataset", help="Dataset name (see `odmo data list`) or a motion folder (default: the recipe's, else humanact12).", rich_help_panel="Data")] = None,
    data: Annotated[Optional[Path], typer.Option("--data", help="Data root (else $ODMO_DATA_DIR, else ~/.local/share/odmo).", rich_help_panel="Data")] = None,
    preset: Annotated[str, typer.Option("--preset", help="Loss scales: odmo (default: the release's plus what measured better), release (the authors' code) or paper (its text); docs/training.md.", rich_help_panel="Losses")] = "odmo",
    ablate: Annotated[Optional[list[str]], typer.Option("--ablate", help="Drop a part: es, traj, cons, end-point (repeatable; the paper's ablations).", rich_help_panel="Losses")] = None,
    recipe: Annotated[Optional[Path], typer.Option("--recipe", help="Train from scratch with the phases of this recipe file (TOML; docs/training.md): every model and training setting comes from it; with it give only --dataset/--data, --out, --resume, --threads, --device and --seed.", rich_help_panel=RunPanel)] = None,
    config: ConfigOpt = None,
    init: Annotated[Optional[Path], typer.Option("--init", help="Start from this finished ODMO checkpoint's weights and model config (a new stage: this run's schedule, a fresh optimizer; loss options override).", rich_help_panel=RunPanel)] = None,
    out: Annotated[Optional[Path], typer.Option("--out", help="Checkpoint to write (default odmo.pt).", rich_help_panel=RunPanel)] = None,
    resume: Annotated[Optional[Path], typer.Option("--resume", help=ResumeHelp, rich_help_panel=RunPanel)] = None,
    threads: Annotated[int, typer.Option("--threads", help="CPU threads for torch (0: torch's default).", rich_help_panel=RunPanel)] = 0,
    device: Annotated[str, typer.Option("--device", help=DeviceHelp, rich_help_panel=RunPanel)] = "cpu",
    nproc: Annotated[int, typer.Option("--nproc", help=NprocHelp, rich_help_panel=RunPanel)] = 1,
    seed: Annotated[int, typer.Option("--seed", help="Seed for every random choice.", rich_help_panel=RunPanel)] = 0,
    as_json: Annotated[bool, typer.Option("--json", help="Print machine-readable JSON on stdout instead of tables.", metavar="", rich_help_panel=RunPanel)] = False,
    settings: dict | None = None,
):
    """Train ODMO (the default of `odmo train`); at the end the checkpoint gets its latent bank and modes.
    Every setting of its two configs is an option below, or a key of a --config file."""
    from odmo_cli.geometry.skeletons import SKELETONS
    from odmo_cli.models.odmo import PRESETS
    from odmo_cli.training.odmo import train_odmo

    settings = settings or {}
    if recipe is not None:
        given = [flag(k) for k in settings] + ["--ablate"] * bool(ablate) + ["--config"] * (config is not None)
        given += ["--preset"] * (preset != "odmo") + ["--init"] * (init is not None)
        if given:
            raise UserError(f"{given[0]} does not apply with --recipe: the recipe file sets every training setting "
                            "(give only --dataset/--data, --out, --resume, --threads, --device, --seed)")
        return _train_recipe(recipe, dataset, data, _out(out, "odmo"), resume, threads, device, nproc, seed, as_json)
    bad = [a for a in ablate or [] if a not in ABLATIONS]
    if bad:
        raise UserError(f"unknown ablation {bad[0]!r}; valid: {', '.join(ABLATIONS)}")
    if preset not in PRESETS:
        raise UserError(f"unknown preset {preset!r}; valid: {', '.join(PRESETS)}")
    if init is not None and resume is not None:
        raise UserError("give either --init (start a new stage from a model's weights) or --resume, not both")
    if init is not None and "pose_frame" in settings:
        raise UserError("--pose-frame changes what the weights mean; a stage from --init keeps its file's")
    src = sources(settings, config, {"model": ODMOConfig, "train": TrainConfig})
    overrides = {f"use_{a.replace('end-point', 'end_point')}": False for a in ablate or []}
    overrides.update(src.values("model", ODMOConfig))
    src.build(ODMOConfig, {"skeleton": next(iter(SKELETONS)), **overrides})  # the values alone; the data's shapes come later
    tc = _train_config(src, TrainConfig, resume, seed, threads)
    prints = _start(device, nproc)  # after the options' own checks, before any data is read
    clips = _clips(dataset or "humanact12", data)
    with (_epoch_bar(tc.epochs, as_json or not prints) as update, _interruptible(_out(out, "odmo"), prints, odmo=True),
          _named(src)):
        result = train_odmo(clips, tc, _out(out, "odmo"), preset=preset, init=init, overrides=overrides,
                            resume=resume, progress=_log_progress(update, tc.val_every), device=device)
    if not prints:
        return
    if as_json:
        return _print_result(result)
    console.print(f"wrote {result.out} after {result.epochs} epochs")
    _print_odmo_report(result.report)


@contextmanager
def _named(src):
    """A config's refusal of a value, raised inside training, named by where the value came from."""
    try:
        yield
    except ConfigError as e:
        raise src.error(e) from None


def _print_odmo_report(r: dict) -> None:
    """What the end of ODMO's training reports (training.odmo.finish), for people."""
    console.print(f"held-out reconstruction ({r['held_out_clips']} clips, no teacher forcing): "
                  f"mean joint error {r['held_out_mpjpe']:.3f}, end-point error {r['held_out_end_error']:.3f}, "
                  f"speed {r['held_out_speed']:.2f} and amplitude {r['held_out_amplitude']:.2f} of the real clips'")
    console.print(f"as an animator sees it (held out, decodes against their clips): foot skate "
                  f"{r.get('held_out_foot_skate', float('nan')):.3f} (the clips' own {r['held_out_real_foot_skate']:.3f}), "
                  f"foot contact {r['held_out_foot_contact']:.2f} ({r['held_out_real_foot_contact']:.2f}), root speed "
                  f"up {r.get('held_out_root_up', float('nan')):.2f} and on the ground "
                  f"{r.get('held_out_root_ground', float('nan')):.2f} of the clips', FD_k {r['held_out_kinetic_fd']:.1f}, "
                  f"bone variation p95 {r['held_out_bone_var']:.3f}")
    console.print(f"body about the root: error {r['held_out_body']:.3f} (each clip's action-mean body: "
                  f"{r['held_out_body_mean_pose']:.3f}); on the training clips {r['train_body']:.3f} "
                  f"({r['train_body_mean_pose']:.3f})")
    if "held_out_body_nearest_code" in r:  # absent without a validation split
        console.print(f"the held-out bodies against the training clips' own: the one with the nearest code "
                      f"{r['held_out_body_nearest_code']:.3f}, the best one {r['held_out_body_best_clip']:.3f}")
    console.print(f"noise ceiling (best squared-error output under the posterior noise): speed "
                  f"{r['ceiling_speed']:.2f}, amplitude {r['ceiling_amplitude']:.2f}, body error {r['ceiling_body']:.3f}")
    console.print(f"latent space: centroid distance {r['centroid_distance']:.2f} (min {r['min_centroid_distance']:.2f}, "
                  f"alpha {r['alpha']:g}), spread {r['spread']:.2f}, nearest-centroid accuracy "
                  f"{100 * r['nearest_centroid_acc']:.1f}%")


@train_app.command("classifier", cls=Command)
@with_settings(ClassifierTrainConfig)
def train_classifier_cmd(
    dataset: DatasetOpt = "humanact12", data: DataOpt = None,
    config: TrainConfigOpt = None, out: OutOpt = None, resume: ResumeOpt = None, threads: ThreadsOpt = 0,
    device: DeviceOpt = "cpu", nproc: NprocOpt = 1, seed: SeedOpt = 0, as_json: JsonOpt = False,
    settings: dict | None = None,
):
    """Train the action classifier that evaluation reads motions with, on real clips with a held-out split."""
    from odmo_cli.training.classifier import train_classifier

    out = _out(out, "classifier")
    tc = _train_config(sources(settings, config, {"train": ClassifierTrainConfig}), ClassifierTrainConfig, resume, seed, threads)
    prints = _start(device, nproc)  # after the options' own checks, before any data is read
    clips = _clips(dataset, data)

    def show(log: dict) -> None:
        if prints and (log["epoch"] % 10 == 0 or log["epoch"] == tc.epochs):
            err_console.print(f"epoch {log['epoch']}/{tc.epochs} loss {log['loss']:.3f} train acc "
                              f"{100 * log['train_accuracy']:.1f}% val acc {100 * log['val_accuracy']:.1f}%",
                              highlight=False)

    with _interruptible(out, prints):
        report = train_classifier(clips, tc, out, resume=resume, progress=None if as_json else show,
                                  device=device).report
    if not prints:
        return
    if as_json:
        return print_json({"out": str(out), "report": report})
    console.print(f"wrote {out}: validation accuracy {100 * report['val_accuracy']:.2f}% on "
                  f"{report['val_clips']} held-out clips (train {100 * report['train_accuracy']:.2f}%, "
                  f"{report['seconds']:.0f} s)")


def _train_recipe(path: Path, dataset: str, data, out: Path, resume, threads: int, device: str, nproc: int,
                  seed: int, as_json: bool) -> None:
    from odmo_cli.training.recipe import load_recipe, train_recipe

    recipe = load_recipe(path)
    prints = _start(device, nproc)
    clips = _clips(dataset or recipe.dataset or "humanact12", data)
    with _epoch_bar(recipe.epochs, as_json or not prints) as update, _interruptible(out, prints, odmo=True):
        result = train_recipe(clips, recipe, out, seed=seed, threads=threads, resume=resume,
                              progress=_log_progress(update, recipe.train.get("val_every", 10)), device=device)
    if not prints:
        return
    if as_json:
        return _print_result(result)
    r = result.report
    console.print(f"wrote {result.out}: {len(recipe.phases)} phases, {result.epochs} epochs, {r['pairs']:,} pairs "
                  f"in {r['hours']:.2f} h")
    _print_odmo_report(r)


@train_app.command("a2m", cls=Command)
@with_settings(A2MTrainConfig)
def train_a2m_cmd(
    dataset: DatasetOpt = "humanact12", data: DataOpt = None,
    representation: Annotated[Optional[str], typer.Option("--representation", help="Output: lie (the paper's model, default) or xyz (its 'w/o Lie' variant).", rich_help_panel="Architecture")] = None,
    config: TrainConfigOpt = None, out: OutOpt = None, resume: ResumeOpt = None, threads: ThreadsOpt = 0,
    device: DeviceOpt = "cpu", nproc: NprocOpt = 1, seed: SeedOpt = 0, as_json: JsonOpt = False,
    settings: dict | None = None,
):
    """Train the Action2Motion baseline (conditional temporal VAE, xyz or Lie output)."""
    from odmo_cli.models.a2m import REPRESENTATIONS
    from odmo_cli.training.a2m import train_a2m

    out = _out(out, "a2m")
    if representation is not None and representation not in REPRESENTATIONS:
        raise UserError(f"unknown representation {representation!r}; valid: {', '.join(REPRESENTATIONS)}")
    tc = _train_config(sources(settings, config, {"train": A2MTrainConfig}), A2MTrainConfig, resume, seed, threads)
    prints = _start(device, nproc)  # after the options' own checks, before any data is read
    clips = _clips(dataset, data)
    with _epoch_bar(tc.epochs, as_json or not prints) as update, _interruptible(out, prints):
        result = train_a2m(clips, tc, out, representation=representation, resume=resume,
                           progress=_log_progress(update, tc.val_every), device=device)
    if not prints:
        return
    if as_json:
        return _print_result(result)
    r = result.report
    console.print(f"wrote {result.out} (a2m-{r['representation']}) after {result.epochs} epochs; held-out "
                  f"({r['held_out_clips']} clips, teacher-forced): joint mse {r['held_out_mse']:.4g}, "
                  f"KL {r['held_out_kl']:.4g} (lambda {r['lambda_kl']:g})")


@train_app.command("dvgan", cls=Command)
@with_settings(DVGANTrainConfig)
def train_dvgan_cmd(
    dataset: DatasetOpt = "humanact12", data: DataOpt = None,
    generator: Annotated[str, typer.Option("--generator", help="cnn (default) or rnn (rnn also completes motions: `odmo complete`).", rich_help_panel="Architecture")] = "cnn",
    config: TrainConfigOpt = None, out: OutOpt = None, resume: ResumeOpt = None, threads: ThreadsOpt = 0,
    device: DeviceOpt = "cpu", nproc: NprocOpt = 1, seed: SeedOpt = 0, as_json: JsonOpt = False,
    settings: dict | None = None,
):
    """Train the DVGAN baseline (WGAN-GP conditioned on the action name, CNN or RNN generator)."""
    from odmo_cli.models.dvgan import GENERATORS
    from odmo_cli.training.dvgan import train_dvgan

    out = _out(out, "dvgan")
    if generator not in GENERATORS:
        raise UserError(f"unknown DVGAN generator {generator!r}; valid: {', '.join(GENERATORS)}")
    tc = _train_config(sources(settings, config, {"train": DVGANTrainConfig}), DVGANTrainConfig, resume, seed, threads)
    prints = _start(device, nproc)  # after the options' own checks, before any data is read
    clips = _clips(dataset, data)

    def show(update):
        def progress(log: dict) -> None:
            info = " ".join(f"{k} {log[k]:.3g}" for k in ("d_loss", "wasserstein", "g_loss") if k in log)
            update(log["epoch"], info, log["epoch"] % 25 == 0 or log["epoch"] == tc.epochs)
        return progress

    with _epoch_bar(tc.epochs, as_json or not prints) as update, _interruptible(out, prints):
        result = train_dvgan(clips, tc, out, generator=generator, resume=resume, progress=show(update), device=device)
    if not prints:
        return
    if as_json:
        return _print_result(result)
    r = result.report
    console.print(f"wrote {result.out}: DVGAN-{r['generator'].upper()} after {result.epochs} epochs "
                  f"({r['generator_steps']} generator steps)")


def _print_result(result) -> None:
    print_json({"out": str(result.out), "epochs": result.epochs, "report": result.report})


@contextmanager
def _interruptible(kept: str | Path, prints: bool = True, odmo: bool = False):
    """Ctrl-C during training: say what was kept (a checkpoint path: its last completed epoch; only
    rank 0 of several processes says it), exit 130 without a traceback."""
    if isinstance(kept, Path):
        kept = f"the last completed epoch is saved in {kept}"
        if odmo:
            kept += " with its latent bank and modes: it samples as it is, and --resume goes on exactly"
    try:
        yield
    except KeyboardInterrupt:
        if prints:
            err_console.print(f"interrupted: {kept}")
        raise typer.Exit(130) from None


@contextmanager
def _epoch_bar(total: int, quiet: bool, label: str = "epoch"):
    """Yields update(epoch, info, line): a rich bar on a terminal; in a log file, one line per epoch.
    update.stop() ends the bar early (before another one starts)."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    # the bar starts with the first finished epoch, so an early error prints only its one line
    bar = Progress(TextColumn(label), MofNCompleteColumn(), BarColumn(), TimeElapsedColumn(), TextColumn("<"),
                   TimeRemainingColumn(), TextColumn("{task.fields[info]}"), console=err_console, disable=quiet)
    task = bar.add_task("train", total=total, info="")
    start = time.monotonic()
    first = [None]  # the epoch this process began at (a resumed run starts past 0)

    def update(epoch: int, info: str, line: bool) -> None:
        if not err_console.is_terminal:  # a log: one line per epoch, with the time so far and an estimate of the rest
            if not quiet:
                first[0] = epoch - 1 if first[0] is None else first[0]
                spent = time.monotonic() - start
                left = spent / max(epoch - first[0], 1) * (total - epoch)
                err_console.print(f"{label} {epoch}/{total} ({_clock(spent)} elapsed, {_clock(left)} left) {info}",
                                  highlight=False)
            return
        bar.start()
        bar.update(task, completed=epoch, info=info)

    def stop() -> None:
        if bar.live.is_started:
            bar.stop()

    update.stop = stop
    try:
        yield update
    finally:
        stop()


def _clock(seconds: float) -> str:
    s = int(seconds)
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}"


SKIP = {"epoch", "seconds", "lr", "clips_per_s", "teacher", "vae"}


def _log_progress(update, val_every: int):
    """An epoch's log dict -> the bar: every loss term, validation, throughput."""
    def show(log: dict) -> None:
        terms = " ".join(f"{k} {v:.3g}" for k, v in log.items() if k not in SKIP and not k.startswith("val_"))
        val = "".join(f" | {k.replace('_', ' ', 1)} {v:.3g}" for k, v in log.items() if k.startswith("val_"))
        rate = f" | {log['clips_per_s']:.0f} clips/s" if "clips_per_s" in log else ""
        update(log["epoch"], terms + val + rate, bool(val))
    return show


@app.command("ship", cls=Command)
def ship_cmd(
    dataset: Annotated[str, typer.Argument(help="humanact12 or cmu_mocap (cmu).")],
    out: Annotated[Path, typer.Option("--out", help="Folder for the files (odmo_<name>.pt, classifier_<name>.pt); made if missing.")],
    skip_classifier: Annotated[bool, typer.Option("--skip-classifier", help="Train ODMO only.", metavar="")] = False,
    recipe: Annotated[Optional[Path], typer.Option("--recipe", help="Train ODMO in one run of this recipe file's phases (e.g. recipes/humanact12.toml) instead of the built-in stages.")] = None,
    data: DataOpt = None, seed: SeedOpt = 0, as_json: JsonOpt = False,
):
    """Rebuild the shipped models of a dataset from scratch with its recipe: the evaluation classifier
    (real clips, cosine-decayed Adam), then ODMO (Adam from 3x the paper's rate, cosine decay, teacher
    forcing decayed over the first half of the epochs, 2 threads; on HumanAct12 then eight stages without
    teacher forcing, the last two the pose decoder alone, widened), then compact files (float16, the
    largest layer as int8 rows). Run it again after an interruption to continue where it stopped. The
    recipes' numbers: docs/training.md."""
    from odmo_cli.ship import build, classifier_epochs, recipe_name, total_epochs
    from odmo_cli.training.recipe import load_recipe

    epochs = load_recipe(recipe).epochs if recipe is not None else total_epochs(recipe_name(dataset))
    with (_epoch_bar(0 if skip_classifier else classifier_epochs(recipe_name(dataset)), as_json,
                     "classifier epoch") as classifier_update,
          _epoch_bar(epochs, as_json) as update,
          _interruptible("run the same command again to continue the training")):
        show = _log_progress(update, 10)

        def odmo_progress(log: dict) -> None:
            classifier_update.stop()  # one live bar at a time
            show(log)

        reports = build(dataset, data, out, seed, skip_classifier, odmo_progress,
                        say=lambda m: None if as_json else err_console.print(m, highlight=False), recipe_file=recipe,
                        classifier_progress=_log_progress(classifier_update, 1))
    if as_json:
        return print_json(reports)
    if "classifier" in reports:
        console.print(f"classifier: held-out accuracy {100 * reports['classifier']['val_accuracy']:.1f}%")
    r = reports["odmo"]
    console.print(f"ODMO: {r['epochs']} epochs, held-out joint error {r['held_out_mpjpe']:.3f}, "
                  f"nearest-centroid accuracy {100 * r['nearest_centroid_acc']:.1f}%; files in {out}")
