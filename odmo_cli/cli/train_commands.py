"""`odmo train` (ODMO, classifier, Action2Motion, DVGAN) and `odmo ship`."""

from __future__ import annotations

from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, Optional

import typer

from odmo_cli.cli.common import DataOpt, JsonOpt, SeedOpt, print_json, resolve_spec, app, console, err_console
from odmo_cli.errors import UserError


ABLATIONS = ("es", "traj", "cons", "end-point")


@app.command("train")
def train(
    dataset: Annotated[str, typer.Option("--dataset", help="Dataset name or folder.")] = "humanact12",
    model: Annotated[str, typer.Option("--model", help="Model kind: odmo, classifier, a2m, dvgan.")] = "odmo",
    representation: Annotated[Optional[str], typer.Option("--representation", help="a2m output: lie (default) | xyz.")] = None,
    generator: Annotated[Optional[str], typer.Option("--generator", help="DVGAN generator: cnn (default) | rnn (rnn also completes motions).")] = None,
    epochs: Annotated[Optional[int], typer.Option("--epochs", help="Default: 300 (odmo), 150 (classifier), 500 (a2m), the paper's schedule (dvgan).")] = None,
    batch_size: Annotated[Optional[int], typer.Option("--batch-size", help="Pairs per step (odmo, default 256); clips (classifier, 64; a2m, 128; dvgan, 64).")] = None,
    lr: Annotated[Optional[float], typer.Option("--lr", help="Default 1e-3 (a2m: 2e-4, dvgan: 1e-4).")] = None,
    lr_final: Annotated[Optional[float], typer.Option("--lr-final", help="Cosine-decay target (default: constant lr).")] = None,
    n_critic: Annotated[Optional[int], typer.Option("--n-critic", help="DVGAN: discriminator steps per generator step (default 10, the paper's).")] = None,
    tf_epochs: Annotated[int, typer.Option("--tf-epochs", help="Teacher forcing decays 1 -> 0.3 over these epochs (0: all).")] = 0,
    ablate: Annotated[Optional[list[str]], typer.Option("--ablate", help="Drop a part: es, traj, cons, end-point (repeatable).")] = None,
    same_class: Annotated[Optional[float], typer.Option("--same-class-fraction", help="Share of same-action pairs (default 0.5, as the authors' release; -1: independent random pairs).")] = None,
    preset: Annotated[str, typer.Option("--preset", help="ODMO loss scales: odmo (default: the release's plus what measured better), release (the authors' code) or paper (its text); docs/training.md.")] = "odmo",
    sigma2: Annotated[Optional[float], typer.Option("--sigma2", help="ODMO: prior variance of the code posterior (eq. 1; paper 0.05, release 0.0025).")] = None,
    recon_weight: Annotated[Optional[float], typer.Option("--recon-weight", help="ODMO: weight of the reconstruction terms against L_es (paper 1: means over clips; release 2: summed over each pair).")] = None,
    vel_weight: Annotated[Optional[float], typer.Option("--vel-weight", help="ODMO: weight of the joint-velocity error L_vel (0: off, as in the paper and the release).")] = None,
    energy_weight: Annotated[Optional[float], typer.Option("--energy-weight", help="ODMO: weight of L_energy, each joint's speed and amplitude about the root against the clip's (0: off, as in the paper and the release).")] = None,
    tf_per: Annotated[Optional[str], typer.Option("--tf-per", help="ODMO: teacher-forcing coins per step (the release: one per time step for the batch) or per clip.")] = None,
    checkpoint_every: Annotated[int, typer.Option("--checkpoint-every", help="Epochs between checkpoints.")] = 25,
    val_every: Annotated[int, typer.Option("--val-every", help="Epochs between validation losses.")] = 10,
    out: Annotated[Optional[Path], typer.Option("--out", help="Checkpoint to write (default <model>.pt).")] = None,
    resume: Annotated[Optional[Path], typer.Option("--resume", help="Checkpoint to continue from.")] = None,
    threads: Annotated[int, typer.Option("--threads", help="CPU threads (0: torch default).")] = 0,
    device: Annotated[str, typer.Option("--device", help="cpu (cuda is not supported yet).")] = "cpu",
    data: DataOpt = None, seed: SeedOpt = 0, as_json: JsonOpt = False,
):
    """Train a model; checkpoints are written atomically, Ctrl-C keeps the last one."""
    from odmo_cli.data.readers import read_dataset
    from odmo_cli.train import TrainConfig, train_odmo

    out = out or Path(f"{model}.pt")
    if generator is not None and model != "dvgan":
        raise UserError(f"--generator applies to --model dvgan only, not {model!r}")
    if n_critic is not None and model != "dvgan":
        raise UserError(f"--n-critic applies to --model dvgan only, not {model!r}")
    if model == "classifier":
        return _train_classifier(dataset, data, epochs, batch_size, lr, out, seed, threads, as_json)
    if model == "a2m":
        odmo_only = {"--ablate": ablate, "--same-class-fraction": same_class, "--lr-final": lr_final,
                     "--sigma2": sigma2, "--recon-weight": recon_weight, "--vel-weight": vel_weight,
                     "--energy-weight": energy_weight, "--tf-per": tf_per, "--preset": None if preset == "odmo" else preset,
                     "--tf-epochs": tf_epochs or None, "--device": None if device == "cpu" else device}
        for flag, value in odmo_only.items():
            if value is not None:
                raise UserError(f"{flag} applies to --model odmo only")
        given = {"epochs": epochs, "batch_size": batch_size, "lr": lr, "checkpoint_every": checkpoint_every,
                 "val_every": val_every, "seed": seed, "threads": threads}
        return _train_a2m(dataset, data, representation, given, out, resume, as_json)
    if representation is not None:
        raise UserError("--representation applies to --model a2m only")
    if model == "dvgan":
        return _train_dvgan(dataset, data, generator or "cnn", epochs, batch_size, lr, n_critic, out, resume, seed,
                            threads, as_json)
    epochs = 300 if epochs is None else epochs
    batch_size = 256 if batch_size is None else batch_size
    lr = 1e-3 if lr is None else lr
    if model != "odmo":
        raise UserError(f"unknown model {model!r}; valid: odmo, classifier, a2m, dvgan")
    if device != "cpu":
        raise UserError(f"device {device!r} is not supported; valid: cpu")
    if same_class is not None and not (0 <= same_class <= 1 or same_class == -1):
        raise UserError(f"--same-class-fraction must be in [0, 1] (or -1: independent pairs), got {same_class}")
    bad = [a for a in ablate or [] if a not in ABLATIONS]
    if bad:
        raise UserError(f"unknown ablation {bad[0]!r}; valid: {', '.join(ABLATIONS)}")
    from odmo_cli.models.odmo import PRESETS

    if preset not in PRESETS:
        raise UserError(f"unknown preset {preset!r}; valid: {', '.join(PRESETS)}")
    if tf_per is not None and tf_per not in ("step", "clip"):
        raise UserError(f"--tf-per must be step or clip, got {tf_per!r}")
    scales = {"sigma2": sigma2, "recon_weight": recon_weight}  # ODMOConfig fields, given as --sigma2, --recon-weight
    for key, value in scales.items():
        if value is not None and not value > 0:
            raise UserError(f"--{key.replace('_', '-')} must be a positive number, got {value}")
    for flag, value in (("--vel-weight", vel_weight), ("--energy-weight", energy_weight)):
        if value is not None and value < 0:
            raise UserError(f"{flag} must not be negative, got {value}")
    scales.update(vel_weight=vel_weight, energy_weight=energy_weight)
    overrides = {"use_es": "es" not in (ablate or []), "use_traj": "traj" not in (ablate or []),
                 "use_cons": "cons" not in (ablate or []), "use_end_point": "end-point" not in (ablate or [])}
    overrides.update({k: v for k, v in scales.items() if v is not None})
    tc = TrainConfig(epochs=epochs, batch_size=batch_size, lr=lr, lr_final=lr if lr_final is None else lr_final,
                     tf_epochs=tf_epochs, checkpoint_every=checkpoint_every, val_every=val_every,
                     seed=seed, threads=threads, same_class_fraction=0.5 if same_class is None else same_class,
                     tf_per=tf_per or "step")
    manifest, root = resolve_spec(dataset, data)
    clips = read_dataset(root, manifest)
    with _epoch_bar(epochs, as_json) as update, _interruptible(f"the last completed epoch is saved in {out}"):
        result = train_odmo(clips, tc, out, overrides, resume, _epoch_log_progress(update), preset)
    if as_json:
        return print_json({"out": str(result.out), "epochs": result.epochs, "report": result.report})
    r = result.report
    console.print(f"wrote {result.out} after {result.epochs} epochs")
    console.print(f"held-out reconstruction ({r['held_out_clips']} clips, no teacher forcing): "
                  f"mean joint error {r['held_out_mpjpe']:.3f}, end-point error {r['held_out_end_error']:.3f}, "
                  f"speed {r['held_out_speed']:.2f} and amplitude {r['held_out_amplitude']:.2f} of the real clips'")
    console.print(f"noise ceiling (best squared-error output under the posterior noise): speed "
                  f"{r['ceiling_speed']:.2f}, amplitude {r['ceiling_amplitude']:.2f}")
    console.print(f"latent space: centroid distance {r['centroid_distance']:.2f} (min {r['min_centroid_distance']:.2f}, "
                  f"alpha {r['alpha']:g}), spread {r['spread']:.2f}, nearest-centroid accuracy "
                  f"{100 * r['nearest_centroid_acc']:.1f}%")


@contextmanager
def _interruptible(kept: str):
    """Ctrl-C during training: say what was kept, exit 130 without a traceback."""
    try:
        yield
    except KeyboardInterrupt:
        err_console.print(f"interrupted: {kept}")
        raise typer.Exit(130) from None


@contextmanager
def _epoch_bar(total: int, quiet: bool):
    """Yields update(epoch, info, line): a rich bar on a terminal; in a log file, one line per `line`."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    # the bar starts with the first finished epoch, so an early error prints only its one line
    bar = Progress(TextColumn("epoch"), MofNCompleteColumn(), BarColumn(), TimeRemainingColumn(),
                   TextColumn("{task.fields[info]}"), console=err_console, disable=quiet)
    task = bar.add_task("train", total=total, info="")

    def update(epoch: int, info: str, line: bool) -> None:
        if not err_console.is_terminal:
            if line and not quiet:
                err_console.print(f"epoch {epoch}/{total} {info}", highlight=False)
            return
        bar.start()
        bar.update(task, completed=epoch, info=info)

    try:
        yield update
    finally:
        if bar.live.is_started:
            bar.stop()


def _epoch_log_progress(update):
    """ODMO's and A2M's EpochLog -> the bar: every loss term, validation, throughput."""
    def show(log) -> None:
        info = " ".join(f"{k} {v:.3g}" for k, v in log.terms.items() if k != "vae")
        info += "".join(f" | val {k} {v:.3g}" for k, v in log.val.items())
        update(log.epoch, info + f" | {log.clips_per_s:.0f} clips/s", bool(log.val))
    return show


def _train_classifier(dataset, data, epochs, batch_size, lr, out, seed, threads, as_json) -> None:
    """The action classifier for evaluation, trained on real motion with a held-out split."""
    from odmo_cli.data.readers import read_dataset
    from odmo_cli.models.classifier import ClassifierTrainConfig, train_classifier

    given = {"epochs": epochs, "batch_size": batch_size, "lr": lr}
    tc = ClassifierTrainConfig.from_dict({"seed": seed, "threads": threads,
                                          **{k: v for k, v in given.items() if v is not None}})
    epochs = tc.epochs
    manifest, root = resolve_spec(dataset, data)
    clips = read_dataset(root, manifest)

    def show(log: dict) -> None:
        if log["epoch"] % 10 == 0 or log["epoch"] == epochs:
            err_console.print(f"epoch {log['epoch']}/{epochs} loss {log['loss']:.3f} train acc "
                              f"{100 * log['train_accuracy']:.1f}% val acc {100 * log['val_accuracy']:.1f}%",
                              highlight=False)

    report = train_classifier(clips, tc, out, None if as_json else show)
    if as_json:
        return print_json({"out": str(out), "report": report})
    console.print(f"wrote {out}: validation accuracy {100 * report['val_accuracy']:.2f}% on "
                  f"{report['val_clips']} held-out clips (train {100 * report['train_accuracy']:.2f}%, "
                  f"{report['seconds']:.0f} s)")


@app.command("ship")
def ship_cmd(
    dataset: Annotated[str, typer.Argument(help="humanact12 or cmu_mocap (cmu).")],
    out: Annotated[Path, typer.Option("--out", help="Folder for the files (odmo_<name>.pt, classifier_<name>.pt).")],
    skip_classifier: Annotated[bool, typer.Option("--skip-classifier", help="Train ODMO only.")] = False,
    data: DataOpt = None, seed: SeedOpt = 0, as_json: JsonOpt = False,
):
    """Rebuild the shipped models of a dataset from scratch with its recipe (see odmo_cli/ship.py)."""
    from odmo_cli.ship import RECIPES, build, recipe_name

    with (_epoch_bar(RECIPES[recipe_name(dataset)]["odmo"]["epochs"], as_json) as update,
          _interruptible("run the same command again to continue the ODMO training")):
        reports = build(dataset, data, out, seed, skip_classifier, _epoch_log_progress(update),
                        say=lambda m: None if as_json else err_console.print(m, highlight=False))
    if as_json:
        return print_json(reports)
    if "classifier" in reports:
        console.print(f"classifier: held-out accuracy {100 * reports['classifier']['val_accuracy']:.1f}%")
    r = reports["odmo"]
    console.print(f"ODMO: {r['epochs']} epochs, held-out joint error {r['held_out_mpjpe']:.3f}, "
                  f"nearest-centroid accuracy {100 * r['nearest_centroid_acc']:.1f}%; files in {out}")


def _train_a2m(dataset, data, representation, given: dict, out, resume, as_json) -> None:
    """The Action2Motion baseline (xyz or Lie output); Ctrl-C keeps the last completed epoch."""
    from odmo_cli.data.readers import read_dataset
    from odmo_cli.models.a2m import REPRESENTATIONS
    from odmo_cli.train_a2m import A2MTrainConfig, train_a2m

    if representation is not None and representation not in REPRESENTATIONS:
        raise UserError(f"unknown representation {representation!r}; valid: {', '.join(REPRESENTATIONS)}")
    tc = A2MTrainConfig.from_dict({k: v for k, v in given.items() if v is not None})
    manifest, root = resolve_spec(dataset, data)
    clips = read_dataset(root, manifest)

    with _epoch_bar(tc.epochs, as_json) as update, _interruptible(f"the last completed epoch is saved in {out}"):
        result = train_a2m(clips, tc, out, representation, resume, _epoch_log_progress(update))
    if as_json:
        return print_json({"out": str(result.out), "epochs": result.epochs, "report": result.report})
    r = result.report
    console.print(f"wrote {result.out} (a2m-{r['representation']}) after {result.epochs} epochs; held-out "
                  f"({r['held_out_clips']} clips, teacher-forced): joint mse {r['held_out_mse']:.4g}, "
                  f"KL {r['held_out_kl']:.4g} (lambda {r['lambda_kl']:g})")


def _train_dvgan(dataset, data, generator, epochs, batch_size, lr, n_critic, out, resume, seed, threads,
                 as_json) -> None:
    """DVGAN (CNN or RNN generator) with WGAN-GP; defaults are the paper's (see train_dvgan)."""
    from odmo_cli.data.readers import read_dataset
    from odmo_cli.models.dvgan import GENERATORS
    from odmo_cli.train_dvgan import DVGANTrainConfig, train_dvgan

    if generator not in GENERATORS:
        raise UserError(f"unknown DVGAN generator {generator!r}; valid: {', '.join(GENERATORS)}")
    given = {"epochs": epochs, "batch_size": batch_size, "lr": lr, "n_critic": n_critic}
    tc = DVGANTrainConfig.from_dict({"seed": seed, "threads": threads,
                                     **{k: v for k, v in given.items() if v is not None}})
    manifest, root = resolve_spec(dataset, data)
    clips = read_dataset(root, manifest)

    def show(update):
        def progress(log: dict) -> None:
            info = " ".join(f"{k} {log[k]:.3g}" for k in ("d_loss", "wasserstein", "g_loss") if k in log)
            update(log["epoch"], info, log["epoch"] % 25 == 0 or log["epoch"] == tc.epochs)
        return progress

    with _epoch_bar(tc.epochs, as_json) as update, _interruptible(f"the last completed epoch is saved in {out}"):
        result = train_dvgan(clips, tc, out, generator, resume=resume, progress=show(update))
    if as_json:
        return print_json({"out": str(result.out), "epochs": result.epochs, "report": result.report})
    r = result.report
    console.print(f"wrote {result.out}: DVGAN-{r['generator'].upper()} after {result.epochs} epochs "
                  f"({r['generator_steps']} generator steps)")
