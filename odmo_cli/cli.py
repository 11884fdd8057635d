"""The `odmo` command line. Each command parses options, builds a config and calls one library
function; what it prints is a short rich summary, or JSON with `--json`."""

from __future__ import annotations

import dataclasses
import json
import sys
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.console import Console
from rich.table import Table
from typer.core import TyperGroup

from odmo_cli.errors import TrainingError, UserError

console = Console()
err_console = Console(stderr=True)


class _Group(TyperGroup):
    """Turns UserError from any command into one line on stderr and exit status 2
    (TrainingError: exit 1). `train` ends a Ctrl-C with status 130 after saving its checkpoint."""

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except (UserError, TrainingError) as exc:
            err_console.print(f"error: {exc}", markup=False, highlight=False, soft_wrap=True)
            raise typer.Exit(2 if isinstance(exc, UserError) else 1) from None


app = typer.Typer(cls=_Group, no_args_is_help=True, add_completion=False,
                  help="Action-conditioned on-demand 3D human motion generation (ODMO and baselines).",
                  pretty_exceptions_enable=False)
data_app = typer.Typer(cls=_Group, no_args_is_help=True, help="Find, check, fetch, convert and look at datasets.")
app.add_typer(data_app, name="data")

DataOpt = Annotated[Optional[Path], typer.Option(
    "--data", help="Data root (else $ODMO_DATA_DIR, else ~/.local/share/odmo).")]
JsonOpt = Annotated[bool, typer.Option("--json", help="Print machine-readable JSON.")]
SeedOpt = Annotated[int, typer.Option("--seed", help="Seed for every random choice.")]
DatasetArg = Annotated[str, typer.Argument(help="Dataset name (see `odmo data list`) or a folder.")]
DemoOpt = Annotated[bool, typer.Option("--demo", help="Use the tiny demo subset shipped in the package.")]
ModelOpt = Annotated[Optional[str], typer.Option(
    "--model", help="Checkpoint path, or a shipped model: humanact12 (default), cmu.")]
OutOpt = Annotated[Path, typer.Option("--out", help="Samples file to write (.npz).")]
EndOpt = Annotated[Optional[str], typer.Option("--end", help="End point: x,z (ground plane) or x,y,z.")]


def _print_json(payload) -> None:
    sys.stdout.write(json.dumps(payload, indent=2, default=str) + "\n")


def _resolve(spec: str, data: Optional[Path], demo: bool = False):
    from odmo_cli.data.locate import resolve
    from odmo_cli.data.demo import demo_folder

    if demo:
        return resolve(demo_folder(spec))
    return resolve(spec, data)


@data_app.command("list")
def data_list(data: DataOpt = None, as_json: JsonOpt = False):
    """Table of known datasets and whether each is on disk."""
    from odmo_cli.data.locate import data_root, find_release
    from odmo_cli.data.manifest import available_manifests, load_manifest

    rows = []
    for name in available_manifests():
        m = load_manifest(name)
        where = find_release(m, data)
        rows.append({"name": name, "title": m.title, "actions": len(m.actions),
                     "clips": sum(a.count for a in m.actions), "skeleton": m.skeleton_name,
                     "present": str(where) if where else None})
    if as_json:
        return _print_json({"data_root": str(data_root(data)), "datasets": rows})
    table = Table(title=f"datasets (data root: {data_root(data)})")
    for col in ("name", "title", "actions", "clips", "skeleton", "on disk"):
        table.add_column(col)
    for r in rows:
        table.add_row(r["name"], r["title"], str(r["actions"]), str(r["clips"]), r["skeleton"],
                      r["present"] or "[dim]no[/dim]")
    console.print(table)


@data_app.command("info")
def data_info(dataset: DatasetArg, data: DataOpt = None, demo: DemoOpt = False,
              verify: Annotated[bool, typer.Option(help="Check files against the manifest's SHA-256.")] = True,
              as_json: JsonOpt = False):
    """Actions x clips x lengths; flags missing, extra or corrupt files against the manifest."""
    from odmo_cli.data.prepare import summarize

    manifest, root = _resolve(dataset, data, demo)
    s = summarize(manifest, root, verify=verify and not demo)
    if as_json:
        return _print_json(s.to_json())
    table = Table(title=f"{manifest.title}: {s.total} clips in {len(s.rows)} actions ({root})")
    for col in ("action", "clips", "paper", "len min", "len median", "len max", "modes"):
        table.add_column(col, justify="left" if col == "action" else "right")
    for r in s.rows:
        mark = "" if r.clips == r.expected or demo else " [yellow]≠[/yellow]"
        table.add_row(r.name, f"{r.clips}{mark}", str(r.expected), str(r.min_len), f"{r.median_len:g}",
                      str(r.max_len), str(r.modes or "-"))
    console.print(table)
    console.print(f"skeleton {s.skeleton}, {s.fps:g} fps, clips cropped to T = {s.clip_length}")
    for label, items in (("problems", s.problems), ("missing", s.missing), ("extra", s.extra),
                         ("corrupt", s.corrupt)):
        if items:
            console.print(f"[red]{len(items)} {label}[/red]: " + "; ".join(items[:5])
                          + (" ..." if len(items) > 5 else ""), highlight=False)
    if s.digest_ok is not None:
        console.print("checksums: " + ("[green]all files match the manifest[/green]" if s.digest_ok
                                       else "[red]do not match the manifest[/red]"))


@data_app.command("fetch")
def data_fetch(dataset: Annotated[str, typer.Argument(help="Dataset name or a manifest .toml path.")],
               to: Annotated[Path, typer.Option("--to", help="Folder to download into.")],
               as_json: JsonOpt = False):
    """Download a dataset's files from its manifest's sources, resuming and verifying SHA-256."""
    from rich.progress import BarColumn, DownloadColumn, Progress, TextColumn

    from odmo_cli.data.fetch import fetch_dataset
    from odmo_cli.data.manifest import load_manifest

    manifest = load_manifest(dataset)
    bar = Progress(TextColumn("{task.description}"), BarColumn(), DownloadColumn(), console=err_console,
                   transient=True)
    tasks: dict[str, int] = {}

    def report(name: str, done: int, total: int | None) -> None:
        bar.start()  # only once bytes arrive: an early error prints just its one line
        if name not in tasks:
            tasks[name] = bar.add_task(name, total=total)
        bar.update(tasks[name], completed=done, total=total)

    try:
        result = fetch_dataset(manifest, to, progress=report)
    finally:
        if bar.live.is_started:
            bar.stop()
    summary = {"dataset": manifest.name, "dest": str(result.dest), "downloaded": result.downloaded,
               "present": result.present, "extracted": len(result.extracted)}
    if as_json:
        return _print_json(summary)
    console.print(f"{manifest.name} in {result.dest}: {len(result.downloaded)} downloaded, "
                  f"{len(result.present)} already present and verified, {len(result.extracted)} extracted")


@data_app.command("prepare")
def data_prepare(source: Annotated[Path, typer.Argument(help="The release folder to convert.")],
                 fmt: Annotated[str, typer.Option("--format", help="humanact12 | cmu_a2m | folder | bvh")],
                 out: Annotated[Path, typer.Option("--out", help="New motion folder to write.")],
                 dataset: Annotated[Optional[str], typer.Option(
                     "--dataset", help="Manifest for --format folder (e.g. uestc) or bvh (actions, fps, T).")] = None,
                 labels: Annotated[Optional[Path], typer.Option(
                     "--labels", help="bvh: CSV file,action (default: the dataset's trial list).")] = None,
                 skeleton: Annotated[str, typer.Option("--skeleton", help="bvh: humanact12 | cmu20 | auto")] = "auto",
                 fps: Annotated[Optional[float], typer.Option("--fps", help="bvh: frame rate to resample to (default: the dataset's).")] = None,
                 unit: Annotated[str, typer.Option("--unit", help="bvh: the files' length unit: auto | m | cm | mm | in | cmu")] = "auto",
                 joint_map: Annotated[Optional[Path], typer.Option("--joint-map", help="bvh: TOML joint map for other hierarchies.")] = None):
    """Validate a release (or import a folder of BVH files) and write a motion folder (index.csv + npy + dataset.toml)."""
    from odmo_cli.data.locate import manifest_for_folder
    from odmo_cli.data.manifest import FORMATS, load_manifest
    from odmo_cli.data.prepare import prepare, write_folder

    by_format = {"humanact12": "humanact12", "cmu_a2m": "cmu_mocap"}
    if fmt == "bvh":
        from odmo_cli.data.bvh_import import BvhImportConfig, import_bvh_folder

        cfg = BvhImportConfig(skeleton=skeleton, dataset=dataset, fps=fps, unit=unit, labels=labels, joint_map=joint_map)
        result = import_bvh_folder(source, cfg)
        write_folder(result.clips, out)
        m = result.clips.manifest
        console.print(f"wrote {out}: {result.read} clips in {len(m.actions)} actions ({m.skeleton_name}, {m.fps:g} fps, "
                      f"units {', '.join(sorted(set(result.units.values())))}); {len(result.problems)} file(s) skipped",
                      highlight=False)
        for problem in result.problems:
            console.print(f"  skipped {problem}", highlight=False, markup=False)
        return
    if fmt not in FORMATS:
        raise UserError(f"unknown format {fmt!r}; valid: {', '.join(FORMATS)}, bvh")
    if fmt == "folder":
        manifest = load_manifest(dataset) if dataset else manifest_for_folder(source)
        # a motion folder of a named dataset: its actions and skeleton, already in its units
        manifest = dataclasses.replace(manifest, format="folder", scale=1.0)
    else:
        manifest = load_manifest(by_format[fmt])
    clips = prepare(manifest, source, out)
    console.print(f"wrote {out}: {len(clips)} clips in {len(manifest.actions)} actions "
                  f"({manifest.skeleton_name}, {manifest.fps:g} fps)")


@data_app.command("show")
def data_show(dataset: DatasetArg, action: Annotated[str, typer.Option("--action", help="Action name.")],
              out: Annotated[Optional[Path], typer.Option("--out", help=".gif or .mp4 (animated) or .png")] = None,
              n: Annotated[int, typer.Option("--n", help="How many clips.")] = 4,
              data: DataOpt = None, demo: DemoOpt = False, seed: SeedOpt = 0):
    """Render a few clips of one action as stick figures."""
    import numpy as np

    from odmo_cli.data.dataset import crop_pad_shift
    from odmo_cli.data.readers import read_dataset
    from odmo_cli.viz import animate

    if n <= 0:
        raise UserError(f"--n must be a positive number of clips, got {n}")
    manifest, root = _resolve(dataset, data, demo)
    k = manifest.action_index(action)
    clips = read_dataset(root, manifest)
    idx = np.flatnonzero(clips.labels == k)
    pick = np.sort(np.random.default_rng(seed).choice(idx, size=min(n, len(idx)), replace=False))
    motions = np.stack([crop_pad_shift(clips.motions[i], manifest.clip_length) for i in pick])
    out = out or Path(f"{manifest.name}_{manifest.actions[k].name}.gif")
    out, notice = animate(motions, manifest.skeleton, out, fps=manifest.fps, titles=[clips.names[i] for i in pick])
    if notice:
        err_console.print(notice, highlight=False, markup=False)
    console.print(f"wrote {out}: {len(pick)} {manifest.actions[k].name} clips from {root}")


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
    tf_epochs: Annotated[int, typer.Option("--tf-epochs", help="Teacher forcing decays 1 -> 0.3 over these epochs (0: all).")] = 0,
    ablate: Annotated[Optional[list[str]], typer.Option("--ablate", help="Drop a part: es, traj, cons, end-point (repeatable).")] = None,
    same_class: Annotated[Optional[float], typer.Option("--same-class-fraction", help="Share of same-action pairs (default 0.5, as the authors' release; -1: independent random pairs).")] = None,
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
    if model == "classifier":
        return _train_classifier(dataset, data, epochs, batch_size, lr, out, seed, threads, as_json)
    if model == "a2m":
        odmo_only = {"--ablate": ablate, "--same-class-fraction": same_class, "--lr-final": lr_final,
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
        return _train_dvgan(dataset, data, generator or "cnn", epochs, batch_size, lr, out, resume, seed, threads, as_json)
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
    overrides = {"use_es": "es" not in (ablate or []), "use_traj": "traj" not in (ablate or []),
                 "use_cons": "cons" not in (ablate or []), "use_end_point": "end-point" not in (ablate or [])}
    tc = TrainConfig(epochs=epochs, batch_size=batch_size, lr=lr, lr_final=lr if lr_final is None else lr_final,
                     tf_epochs=tf_epochs, checkpoint_every=checkpoint_every, val_every=val_every,
                     seed=seed, threads=threads, same_class_fraction=0.5 if same_class is None else same_class)
    manifest, root = _resolve(dataset, data)
    clips = read_dataset(root, manifest)
    with _epoch_bar(epochs, as_json) as update, _interruptible(f"the last completed epoch is saved in {out}"):
        result = train_odmo(clips, tc, out, overrides, resume, _epoch_log_progress(update))
    if as_json:
        return _print_json({"out": str(result.out), "epochs": result.epochs, "report": result.report})
    r = result.report
    console.print(f"wrote {result.out} after {result.epochs} epochs")
    console.print(f"held-out reconstruction ({r['held_out_clips']} clips, no teacher forcing): "
                  f"mean joint error {r['held_out_mpjpe']:.3f}, end-point error {r['held_out_end_error']:.3f}")
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
    manifest, root = _resolve(dataset, data)
    clips = read_dataset(root, manifest)

    def show(log: dict) -> None:
        if log["epoch"] % 10 == 0 or log["epoch"] == epochs:
            err_console.print(f"epoch {log['epoch']}/{epochs} loss {log['loss']:.3f} train acc "
                              f"{100 * log['train_accuracy']:.1f}% val acc {100 * log['val_accuracy']:.1f}%",
                              highlight=False)

    report = train_classifier(clips, tc, out, None if as_json else show)
    if as_json:
        return _print_json({"out": str(out), "report": report})
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
        return _print_json(reports)
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
    manifest, root = _resolve(dataset, data)
    clips = read_dataset(root, manifest)

    with _epoch_bar(tc.epochs, as_json) as update, _interruptible(f"the last completed epoch is saved in {out}"):
        result = train_a2m(clips, tc, out, representation, resume, _epoch_log_progress(update))
    if as_json:
        return _print_json({"out": str(result.out), "epochs": result.epochs, "report": result.report})
    r = result.report
    console.print(f"wrote {result.out} (a2m-{r['representation']}) after {result.epochs} epochs; held-out "
                  f"({r['held_out_clips']} clips, teacher-forced): joint mse {r['held_out_mse']:.4g}, "
                  f"KL {r['held_out_kl']:.4g} (lambda {r['lambda_kl']:g})")


def _train_dvgan(dataset, data, generator, epochs, batch_size, lr, out, resume, seed, threads, as_json) -> None:
    """DVGAN (CNN or RNN generator) with WGAN-GP; defaults are the paper's (see train_dvgan)."""
    from odmo_cli.data.readers import read_dataset
    from odmo_cli.models.dvgan import GENERATORS
    from odmo_cli.train_dvgan import DVGANTrainConfig, train_dvgan

    if generator not in GENERATORS:
        raise UserError(f"unknown DVGAN generator {generator!r}; valid: {', '.join(GENERATORS)}")
    given = {"epochs": epochs, "batch_size": batch_size, "lr": lr}
    tc = DVGANTrainConfig.from_dict({"seed": seed, "threads": threads,
                                     **{k: v for k, v in given.items() if v is not None}})
    manifest, root = _resolve(dataset, data)
    clips = read_dataset(root, manifest)

    def show(update):
        def progress(log: dict) -> None:
            info = " ".join(f"{k} {log[k]:.3g}" for k in ("d_loss", "wasserstein", "g_loss") if k in log)
            update(log["epoch"], info, log["epoch"] % 25 == 0 or log["epoch"] == tc.epochs)
        return progress

    with _epoch_bar(tc.epochs, as_json) as update, _interruptible(f"the last completed epoch is saved in {out}"):
        result = train_dvgan(clips, tc, out, generator, resume=resume, progress=show(update))
    if as_json:
        return _print_json({"out": str(result.out), "epochs": result.epochs, "report": result.report})
    r = result.report
    console.print(f"wrote {result.out}: DVGAN-{r['generator'].upper()} after {result.epochs} epochs "
                  f"({r['generator_steps']} generator steps)")


@app.command("info")
def info(checkpoint: Annotated[Path, typer.Argument(help="A checkpoint (.pt).")], as_json: JsonOpt = False):
    """What a checkpoint holds: model kind, configs, dataset, epochs, final report."""
    from odmo_cli.io import describe_checkpoint

    desc = describe_checkpoint(checkpoint)
    if as_json:
        return _print_json(desc)
    for key, value in desc.items():
        if isinstance(value, dict):
            console.print(f"[bold]{key}[/bold]")
            for k, v in value.items():
                console.print(f"  {k}: {v}", highlight=False)
        else:
            console.print(f"[bold]{key}[/bold]: {value}", highlight=False)


def _summary(batch, out: Path, as_json: bool, extra: dict | None = None) -> None:
    import numpy as np

    per_action = {}
    for a, m in zip(batch.actions, batch.modes):
        per_action.setdefault(str(a), {}).setdefault(int(m), 0)
        per_action[str(a)][int(m)] += 1
    payload = {"out": str(out), "motions": len(batch), "model": batch.model, "seed": batch.seed,
               "frames": int(batch.loaded.model.cfg.length), "actions": per_action, "dist_e": batch.dist_e(), **(extra or {})}
    if as_json:
        return _print_json(payload)
    table = Table(title=f"{len(batch)} motions -> {out}")
    table.add_column("action")
    table.add_column("motions", justify="right")
    table.add_column("modes used (mode: count)")
    for a, counts in per_action.items():
        table.add_row(a, str(sum(counts.values())), ", ".join(
            f"n/a: {v}" if k < 0 else f"{k}: {v}" for k, v in sorted(counts.items())))
    console.print(table)
    if payload["dist_e"] is not None:
        reach = np.sqrt(np.mean(np.sum((batch.end_points - batch.reached) ** 2, axis=1)))
        console.print(f"dist_e (mean squared end-point error) {payload['dist_e']:.4f}; RMS distance {reach:.3f}")
    console.print(f"model {batch.model}, seed {batch.seed}, {batch.dataset['fps']:g} fps, skeleton {batch.dataset['skeleton']}")


@app.command("sample")
def sample_cmd(
    action: Annotated[list[str], typer.Option("--action", help="Action name (repeatable), or all.")],
    n: Annotated[int, typer.Option("--n", help="Motions per action (per end point).")] = 20,
    out: OutOpt = Path("samples.npz"),
    model: ModelOpt = None,
    mode: Annotated[Optional[int], typer.Option("--mode", help="Sample only this discovered mode.")] = None,
    mode_weights: Annotated[Optional[str], typer.Option("--mode-weights", help="Weights per mode, e.g. 0.2,0.8.")] = None,
    sampling: Annotated[str, typer.Option("--sampling", help="mode-preserving | conventional")] = "mode-preserving",
    end: EndOpt = None,
    end_from: Annotated[Optional[str], typer.Option("--end-from", help="First end point of a segment.")] = None,
    end_to: Annotated[Optional[str], typer.Option("--end-to", help="Last end point of a segment.")] = None,
    steps: Annotated[int, typer.Option("--steps", help="End points on the --end-from/--end-to segment.")] = 10,
    gif: Annotated[Optional[Path], typer.Option("--gif", help="Also render the first motions to a GIF.")] = None,
    bvh: Annotated[Optional[Path], typer.Option("--bvh", help="Also write one BVH file per motion into this folder.")] = None,
    seed: SeedOpt = 0, as_json: JsonOpt = False,
):
    """Generate motions of the given actions (npz as in DESIGN.md)."""
    from odmo_cli.generate import load_model, sample

    if mode is not None and mode_weights is not None:
        raise UserError("give either --mode or --mode-weights, not both")
    weights = _floats(mode_weights, "--mode-weights") if mode_weights is not None else None
    loaded = load_model(model)
    batch = sample(loaded, action, n, seed, mode, weights, sampling, end, end_from, end_to, steps, lazy=True)
    batch.save(out)  # decodes batch by batch while writing: memory stays flat in n
    if gif is not None:
        from odmo_cli.skeletons import get_skeleton
        from odmo_cli.viz import animate

        k = min(len(batch), 8)
        _, notice = animate(batch.head(k), get_skeleton(batch.dataset["skeleton"]), gif, fps=batch.dataset["fps"],
                            titles=[f"{a} #{i}" for i, a in enumerate(batch.actions[:k])], end_points=batch.end_points[:k])
        if notice:
            err_console.print(notice, highlight=False, markup=False)
    extra = None
    if bvh is not None:
        from odmo_cli.bvh import export_samples

        report = export_samples(out, bvh)  # from the file just written: the batch is not kept decoded
        extra = {"bvh": str(bvh), "bvh_files": len(report.files), "bvh_max_error_mm": report.max_error_mm,
                 "bvh_mean_error_mm": report.mean_error_mm,
                 "bone_stretch_mm": report.max_stretch_mm}
    _summary(batch, out, as_json, extra)
    if bvh is not None and not as_json:
        _bvh_note(report, bvh)


def _bvh_note(report, folder: Path) -> None:
    console.print(f"wrote {len(report.files)} BVH files to {folder}: joint positions within "
                  f"{report.max_error_mm:.2f} mm (mean {report.mean_error_mm:.2f} mm) of the motions (bones stretch by up to "
                  f"{report.max_stretch_mm:.2f} mm; a BVH keeps each bone's mean length)", highlight=False)


@app.command("export")
def export_cmd(
    samples: Annotated[Path, typer.Argument(help="A samples file (.npz) from odmo sample/interpolate.")],
    bvh: Annotated[Path, typer.Option("--bvh", help="Folder for the BVH files (one per motion).")],
    as_json: JsonOpt = False,
):
    """Write every motion of a samples file as a BVH file (y-up, metres, the model's fps)."""
    from odmo_cli.bvh import export_samples

    report = export_samples(samples, bvh)
    if as_json:
        return _print_json({"bvh": str(bvh), "files": [str(f) for f in report.files],
                            "max_error_mm": report.max_error_mm,
                            "mean_error_mm": report.mean_error_mm, "bone_stretch_mm": report.max_stretch_mm})
    _bvh_note(report, bvh)


@app.command("render")
def render_cmd(
    samples: Annotated[Path, typer.Argument(help="A samples file (.npz).")],
    out: Annotated[Path, typer.Option("--out", help="Animation to write: .gif or .mp4 (.png: one still).")],
    index: Annotated[Optional[int], typer.Option("--index", help="Render only this motion (default 0).")] = None,
    grid: Annotated[Optional[str], typer.Option("--grid", help="ROWSxCOLS of the first motions, e.g. 4x5.")] = None,
    trail: Annotated[bool, typer.Option("--trail", help="Draw the paths of the root, hands and feet so far.")] = False,
):
    """3-D stick-figure animation with ground plane, root trajectory and asked end point."""
    from odmo_cli.viz import render_samples

    written, notice = render_samples(samples, out, index, grid, trail)
    if notice:
        err_console.print(notice, highlight=False, markup=False)
    console.print(f"wrote {written}", highlight=False)


@app.command("complete")
def complete_cmd(
    prefix: Annotated[Path, typer.Option("--prefix", help="A (frames, joints, 3) .npy motion of the model's skeleton.")],
    model: Annotated[str, typer.Option("--model", help="A DVGAN-RNN checkpoint (the models that complete).")],
    frames: Annotated[int, typer.Option("--frames", help="How many of the prefix's first frames to keep.")] = 20,
    action: Annotated[list[str], typer.Option("--action", help="Action name (repeatable), or all.")] = ["all"],
    n: Annotated[int, typer.Option("--n", help="Completions per action.")] = 5,
    out: OutOpt = Path("completed.npz"),
    seed: SeedOpt = 0, as_json: JsonOpt = False,
):
    """Continue the first --frames frames of a motion to the model's length (DVGAN-RNN)."""
    from odmo_cli.generate import complete, load_model, read_prefix

    batch = complete(load_model(model), read_prefix(prefix), frames, action, n, seed)
    batch.save(out)
    _summary(batch, out, as_json, {"prefix_frames": frames})


def _floats(text: str, flag: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",")]
    except ValueError:
        raise UserError(f"{flag} must be comma-separated numbers, got {text!r}") from None


@app.command("interpolate")
def interpolate_cmd(
    action: Annotated[str, typer.Option("--action", help="Action name.")],
    from_mode: Annotated[Optional[int], typer.Option("--from-mode")] = None,
    to_mode: Annotated[Optional[int], typer.Option("--to-mode")] = None,
    from_code: Annotated[Optional[int], typer.Option("--from-code", help="Index into the latent bank.")] = None,
    to_code: Annotated[Optional[int], typer.Option("--to-code", help="Index into the latent bank.")] = None,
    steps: Annotated[int, typer.Option("--steps")] = 8,
    end: EndOpt = None, out: OutOpt = Path("interpolation.npz"), model: ModelOpt = None,
    seed: SeedOpt = 0, as_json: JsonOpt = False,
):
    """Blend two modes (or two codes) of an action: one motion per step on the line between them."""
    from odmo_cli.generate import interpolate, load_odmo

    batch = interpolate(load_odmo(model), action, steps, from_mode, to_mode, from_code, to_code, end, seed)
    batch.save(out)
    _summary(batch, out, as_json)


@app.command("modes")
def modes_cmd(
    model: Annotated[Optional[str], typer.Argument(help="Checkpoint path or shipped name (default humanact12).")] = None,
    refit: Annotated[bool, typer.Option("--refit", help="Refit the mixtures and save them into the checkpoint.")] = False,
    plot: Annotated[Optional[Path], typer.Option("--plot", help="Write a 2-D plot of the codes (.png).")] = None,
    projection: Annotated[str, typer.Option("--projection", help="pca | tsne")] = "pca",
    colour: Annotated[str, typer.Option("--colour", help="action | mode")] = "action",
    action: Annotated[Optional[str], typer.Option("--action", help="Plot only this action.")] = None,
    seed: SeedOpt = 0, as_json: JsonOpt = False,
):
    """Discovered modes per action: counts, silhouettes, agreement with ground-truth modes."""
    from odmo_cli.latent import mode_report

    from odmo_cli.generate import load_odmo, refit_modes

    if colour not in ("action", "mode"):
        raise UserError(f"unknown --colour {colour!r}; valid: action, mode")
    loaded = load_odmo(model)
    if refit:
        refit_modes(loaded, seed)
    rows = mode_report(loaded.bank, loaded.modes, loaded.actions)
    if plot is not None:
        _plot_modes(loaded, plot, projection, colour, action, seed)
    if as_json:
        return _print_json({"model": loaded.source, "actions": rows, "plot": str(plot) if plot else None})
    table = Table(title=f"modes of {loaded.source}")
    for col in ("action", "clips", "modes", "members", "silhouette by k", "true modes", "ARI"):
        table.add_column(col)
    for r in rows:
        sil = " ".join(f"{k}:{v:.2f}" for k, v in r["silhouettes"].items()) or r["note"]
        table.add_row(r["action"], str(r["clips"]), str(r["modes"]), " ".join(map(str, r["members"])), sil,
                      "-" if r["true_modes"] is None else str(r["true_modes"]),
                      "-" if r["ari"] is None else f"{r['ari']:.2f}")
    console.print(table)
    if plot is not None:
        console.print(f"wrote {plot}")


def _plot_modes(loaded, plot: Path, projection: str, colour: str, action: Optional[str], seed: int) -> None:
    import numpy as np

    from odmo_cli.latent import ActionModes, assign
    from odmo_cli.viz import latent_plot

    codes, labels = loaded.bank["codes"].numpy(), loaded.bank["labels"].numpy()
    chosen = [loaded.action_index(action)] if action else list(range(len(loaded.actions)))
    sel = np.isin(labels, chosen)
    groups, names, gaussians = np.zeros(len(codes), dtype=int), [], []
    if colour == "action":
        groups, names = labels, loaded.actions
    for a in chosen:
        m = ActionModes.from_plain(loaded.modes["actions"][a])
        gaussians += list(zip(m.means, m.covariances))
        if colour == "mode":
            own = labels == a
            groups[own] = len(names) + assign(m, codes[own].astype(np.float64))
            names += [f"{loaded.actions[a]} mode {k}" for k in range(len(m.means))]
    latent_plot(codes[sel], groups[sel], names, plot, projection, gaussians, seed,
                title=f"{loaded.dataset['name']} latent codes ({projection})")


METRIC_HEADS = {"accuracy": "Acc ↑", "fid": "FID ↓", "diversity": "Diversity →", "multimodality": "MModality →",
                "inception": "IS ↑", "n_apd": "n-APD", "bone_std": "bone std ↓"}


def evaluate(
    model: Annotated[Optional[str], typer.Option("--model", help="Checkpoint or shipped name (default humanact12).")] = None,
    compare: Annotated[Optional[list[str]], typer.Option("--compare", help="More checkpoints for the same table.")] = None,
    dataset: Annotated[Optional[str], typer.Option("--dataset", help="Dataset (default: the model's).")] = None,
    classifier: Annotated[Optional[str], typer.Option("--classifier", help="Classifier checkpoint or Action2Motion .tar.")] = None,
    repeats: Annotated[int, typer.Option("--repeats")] = 10,
    per_action: Annotated[int, typer.Option("--per-action", help="Samples per action (0: the paper's).")] = 0,
    sampling: Annotated[str, typer.Option("--sampling", help="mode-preserving | conventional")] = "mode-preserving",
    samples: Annotated[Optional[list[Path]], typer.Option("--samples", help="Evaluate a samples .npz made elsewhere.")] = None,
    customization: Annotated[bool, typer.Option("--customization", help="Also the end-point protocol (§4.4).")] = False,
    json_out: Annotated[Optional[Path], typer.Option("--json", help="Write the full report as JSON here.")] = None,
    data: DataOpt = None, seed: SeedOpt = 0,
):
    """The evaluation protocol: Acc, FID, Diversity, Multimodality, n-APD, bone std (mean ± 95% CI)."""
    from odmo_cli.evaluate import EvalConfig, run_evaluation
    from odmo_cli.io import atomic_path

    cfg = EvalConfig(repeats=repeats, per_action=per_action, sampling=sampling, seed=seed)
    models = ([model] if model or not samples else []) + list(compare or [])
    with err_console.status("evaluating ..."):
        report = run_evaluation(models, dataset, data, classifier, cfg, list(samples or []), customization)
    table = Table(title=f"{report.dataset}: {report.config['repeats']} repeats x {report.config['per_action']} "
                        f"per action, classifier {Path(report.classifier).name} ({report.seconds:.0f} s)")
    table.add_column("model")
    for key in METRIC_HEADS:
        table.add_column(METRIC_HEADS[key], justify="right")
    for row in report.rows:
        table.add_row(row["name"], *(f"{row['metrics'][k][0]:.{3 if k in ('fid', 'bone_std') else 2}f}"
                                     f" ±{row['metrics'][k][1]:.2f}" for k in METRIC_HEADS))
    console.print(table)
    for c in report.customization:
        m = c["metrics"]
        console.print(f"customization {c['name']}: Acc {m['accuracy'][0]:.2f} ±{m['accuracy'][1]:.2f}, "
                      f"dist_e {m['dist_e'][0]:.4f} ±{m['dist_e'][1]:.4f}")
    if json_out is not None:
        import json

        with atomic_path(json_out) as tmp:
            tmp.write_text(json.dumps(report.__dict__, indent=2, default=str))
        console.print(f"wrote {json_out}")


app.command("evaluate")(evaluate)
app.command("eval", help="Alias of evaluate.")(evaluate)


BENCH_PARTS = ("sampling", "end-to-end", "training", "evaluation")


@app.command("bench")
def bench(
    model: ModelOpt = None, data: DataOpt = None,
    runs: Annotated[int, typer.Option("--runs", help="Runs per figure (median reported).")] = 5,
    only: Annotated[Optional[list[str]], typer.Option("--only", help="sampling, end-to-end, training, evaluation")] = None,
    json_out: Annotated[Optional[Path], typer.Option("--json", help="Also write the figures as JSON here.")] = None,
):
    """Speed and memory on this machine (median, min and max of several runs)."""
    from odmo_cli.bench import run_bench
    from odmo_cli.io import atomic_path

    bad = [p for p in only or [] if p not in BENCH_PARTS]
    if bad:
        raise UserError(f"unknown benchmark part {bad[0]!r}; valid: {', '.join(BENCH_PARTS)}")
    if runs <= 0:
        raise UserError(f"--runs must be positive, got {runs}")
    with err_console.status("benchmarking ...") as status:
        report = run_bench(model, data, runs, tuple(only or ()), lambda part: status.update(f"benchmarking {part} ..."))
    m = report.machine
    table = Table(title=f"odmo bench: {m['cpu']}, {m['cores']} cores, torch {m['torch']} ({m['threads']} threads)")
    for col in ("figure", "median", "min", "max", "unit", "runs", "note"):
        table.add_column(col, justify="right" if col in ("median", "min", "max", "runs") else "left")
    for f in report.figures:
        j = f.to_json()
        table.add_row(f.name, f"{j['median']:.3g}", f"{j['min']:.3g}", f"{j['max']:.3g}", f.unit, str(j["runs"]), f.note)
    console.print(table)
    for s in report.skipped:
        console.print(f"skipped {s}", highlight=False)
    if json_out is not None:
        import json

        with atomic_path(json_out) as tmp:
            tmp.write_text(json.dumps({"machine": m, "figures": [f.to_json() for f in report.figures],
                                       "skipped": report.skipped}, indent=2))


def main() -> None:
    app()
