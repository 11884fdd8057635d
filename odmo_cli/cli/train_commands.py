"""`odmo train odmo|a2m|dvgan|classifier` (plain `odmo train` trains ODMO) and `odmo ship`.

Each subcommand takes only the options that apply to its model; any other option is refused by
the parser with one line and exit 2, before any data is read.
"""

from __future__ import annotations

import math
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, Optional

import typer

from odmo_cli.cli.common import (Command, DataOpt, DeviceOpt, JsonOpt, SeedOpt, app, console, device_for, err_console,
                                 RootOpt, print_json, resolve_spec, train_app)
from odmo_cli.errors import UserError

ABLATIONS = ("es", "traj", "cons", "end-point")

# The options every trainer shares (their defaults are each model's: None means "the model's own").
DatasetOpt = Annotated[str, typer.Option("--dataset", help="Dataset name (see `odmo data list`) or a motion folder.")]
LrFinalOpt = Annotated[Optional[float], typer.Option("--lr-final", help="Cosine decay of the rate to this value over the epochs (default: the model's; constant for odmo, a2m, dvgan).")]
CheckpointOpt = Annotated[Optional[int], typer.Option("--checkpoint-every", help="Epochs between checkpoints (one is always written at the end; default 25).")]
ValOpt = Annotated[Optional[int], typer.Option("--val-every", help="Epochs between validations on the held-out clips (0: never).")]
ResumeOpt = Annotated[Optional[Path], typer.Option("--resume", help="Checkpoint to continue from, exactly (its model and schedule are kept; its own length unless --epochs extends it).")]
ThreadsOpt = Annotated[int, typer.Option("--threads", help="CPU threads for torch (0: torch's default).")]
NprocOpt = Annotated[int, typer.Option("--nproc", help="Processes training together on this machine (data-parallel, "
                                                     "the same global batch; with --device cuda one GPU each). "
                                                     "Several machines: torchrun, see docs/training.md.")]


def _out(out: Optional[Path], kind: str) -> Path:
    return out or Path(f"{kind}.pt")


OutOpt = Annotated[Optional[Path], typer.Option("--out", help="Checkpoint to write (default: <model>.pt, e.g. odmo.pt).")]


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


def _given(**values) -> dict:
    """The options the user gave (None: not given, the config's default applies)."""
    return {k: v for k, v in values.items() if v is not None}


def _epochs(resume: Optional[Path], epochs: Optional[int]) -> Optional[int]:
    """--epochs as given; resuming without it, the checkpoint's own length (training.loop.resume_epochs)."""
    from odmo_cli.training.loop import resume_epochs

    return resume_epochs(resume, epochs)


def _clips(dataset: str, data: Optional[Path]):
    from odmo_cli.data.readers import read_dataset

    manifest, root = resolve_spec(dataset, data)
    return read_dataset(root, manifest)


@train_app.command("odmo", cls=Command)
def train_odmo_cmd(
    dataset: Annotated[Optional[str], typer.Option("--dataset", help="Dataset name (see `odmo data list`) or a motion folder (default: the recipe's, else humanact12).")] = None,
    data: DataOpt = None,
    epochs: Annotated[Optional[int], typer.Option("--epochs", help="Epochs to train (default 300).")] = None,
    batch_size: Annotated[Optional[int], typer.Option("--batch-size", help="Pairs per step (default 256; each step sees twice as many clips).")] = None,
    lr: Annotated[Optional[float], typer.Option("--lr", help="Adam learning rate (default 1e-3, the paper's).")] = None,
    lr_final: Annotated[Optional[float], typer.Option("--lr-final", help="Cosine decay of the rate to this value (default: constant).")] = None,
    tf_epochs: Annotated[int, typer.Option("--tf-epochs", help="Teacher forcing decays from --tf-start to --tf-end (1 -> 0.3) over these epochs (0: all).")] = 0,
    tf_start: Annotated[Optional[float], typer.Option("--tf-start", help="Teacher-forcing rate at the first epoch (default 1).")] = None,
    tf_end: Annotated[Optional[float], typer.Option("--tf-end", help="Teacher-forcing rate once decayed (default 0.3, the release's).")] = None,
    init: Annotated[Optional[Path], typer.Option("--init", help="Start from this finished ODMO checkpoint's weights and model config "
                                                               "(a new stage: this run's schedule, a fresh optimizer; loss options override).")] = None,
    tf_per: Annotated[Optional[str], typer.Option("--tf-per", help="Teacher-forcing coins: step (one per time step for the batch, the release) or clip.")] = None,
    ablate: Annotated[Optional[list[str]], typer.Option("--ablate", help="Drop a part: es, traj, cons, end-point (repeatable).")] = None,
    weight_decay: Annotated[Optional[float], typer.Option("--weight-decay", help="AdamW's decoupled weight decay (default 0: Adam, as in the paper and the release).")] = None,
    decoder_dropout: Annotated[Optional[float], typer.Option("--decoder-dropout", help="Drop each of the pose decoder's hidden units with this probability in training, the same units at every step of a clip (default 0, as in the paper and the release).")] = None,
    crops: Annotated[Optional[str], typer.Option("--crops", help="Which frames of each training clip a batch holds: random (a fresh crop each time, the default, as in the release) or first (the first T, the crops the latent bank and the mode mixtures encode).")] = None,
    code_noise: Annotated[Optional[float], typer.Option("--code-noise", help="Scale of the posterior noise on the codes the decoders see in training (default 1, the VAE's, as in the paper and the release; 0: each crop's mean code, what sampling's mixtures are fitted on).")] = None,
    mirror: Annotated[bool, typer.Option("--mirror", help="Mirror each training clip with probability 1/2 (left and right swapped; off by default, as in the paper and the release).", metavar="")] = False,
    same_class: Annotated[Optional[float], typer.Option("--same-class-fraction", help="Share of same-action pairs (default 0.5, as the authors' release; -1: independent random pairs).")] = None,
    preset: Annotated[str, typer.Option("--preset", help="Loss scales: odmo (default: the release's plus what measured better), release (the authors' code) or paper (its text); docs/training.md.")] = "odmo",
    sigma2: Annotated[Optional[float], typer.Option("--sigma2", help="Prior variance of the code posterior (eq. 1; paper 0.05, release 0.0025).")] = None,
    recon_weight: Annotated[Optional[float], typer.Option("--recon-weight", help="Weight of the reconstruction terms against L_es (paper 1: means over clips; release 2: summed over each pair).")] = None,
    vel_weight: Annotated[Optional[float], typer.Option("--vel-weight", help="Weight of the joint-velocity error L_vel (0: off, as in the paper and the release).")] = None,
    energy_weight: Annotated[Optional[float], typer.Option("--energy-weight", help="Weight of L_energy, each joint's speed and amplitude about the root against the clip's (preset odmo: 2; 0: off, as in the paper and the release).")] = None,
    free_energy_weight: Annotated[Optional[float], typer.Option("--free-energy-weight", help="Weight of L_energy on a second, free-running decode of the same codes, as sampling runs it (preset odmo: 2; 0: off).")] = None,
    height_weight: Annotated[Optional[float], typer.Option("--height-weight", help="Weight of L_height, the root height's speed and amplitude against the clip's, on the root that sampling draws (--root: the trajectory generator's, or the pose decoder's free-running decode; 0: off, the default, as in the paper and the release).")] = None,
    mix_energy_weight: Annotated[Optional[float], typer.Option("--mix-energy-weight", help="Weight of L_energy on free-running decodes of codes mixed between two training clips of one action, asked to move as much as the same mixture of the two clips (0: off, the default; in neither the paper nor the release).")] = None,
    free_from: Annotated[Optional[int], typer.Option("--free-from", help="First epoch (0-based) of the free-running L_energy (default: once teacher forcing has decayed; half the epochs when it decays over all).")] = None,
    root: RootOpt = None,
    train_parts: Annotated[Optional[str], typer.Option("--train-parts", help="Train only these networks, comma-separated: encoder, trajectory, motion (default: all); the others keep their weights, as from --init.")] = None,
    pose_frame: Annotated[Optional[str], typer.Option("--pose-frame", help="What the pose decoder draws from: world (the dataset's frame, the paper's) or path (each frame's point of the generated trajectory).")] = None,
    pose_loss: Annotated[Optional[str], typer.Option("--pose-loss", help="What the pose decoder's position error compares: world (every joint in the dataset's frame, the paper's) or body (every joint but the root about the root, the root's path once).")] = None,
    motion_hidden: Annotated[Optional[int], typer.Option("--motion-hidden", help="Hidden units of the pose decoder (default 128, the paper's); with --init, more than the file's widens its decoder, drawing the same motions at first.")] = None,
    checkpoint_every: CheckpointOpt = None, val_every: ValOpt = None,
    recipe: Annotated[Optional[Path], typer.Option("--recipe", help="Train from scratch with the phases of this recipe file (TOML; docs/training.md): every model and training setting comes from it; with it give only --dataset/--data, --out, --resume, --threads, --device and --seed.")] = None,
    out: OutOpt = None, resume: ResumeOpt = None, threads: ThreadsOpt = 0,
    device: DeviceOpt = "cpu", nproc: NprocOpt = 1, seed: SeedOpt = 0, as_json: JsonOpt = False,
):
    """Train ODMO (the default of `odmo train`); at the end the checkpoint gets its latent bank and modes."""
    from odmo_cli.models.odmo import POSE_FRAMES, POSE_LOSSES, PRESETS, ROOTS
    from odmo_cli.training.odmo import TrainConfig, train_odmo

    if recipe is not None:
        settings = dict(epochs=epochs, batch_size=batch_size, lr=lr, lr_final=lr_final, tf_start=tf_start,
                        tf_end=tf_end, init=init, tf_per=tf_per, weight_decay=weight_decay,
                        decoder_dropout=decoder_dropout, crops=crops, code_noise=code_noise,
                        same_class_fraction=same_class, sigma2=sigma2, recon_weight=recon_weight,
                        vel_weight=vel_weight, energy_weight=energy_weight, free_energy_weight=free_energy_weight,
                        height_weight=height_weight, mix_energy_weight=mix_energy_weight, free_from=free_from,
                        root=root, train_parts=train_parts, pose_frame=pose_frame, pose_loss=pose_loss,
                        motion_hidden=motion_hidden, checkpoint_every=checkpoint_every, val_every=val_every)
        given = [k for k, v in settings.items() if v is not None]
        given += ["ablate"] * bool(ablate) + ["tf_epochs"] * bool(tf_epochs) + ["mirror"] * mirror
        given += ["preset"] * (preset != "odmo")
        if given:
            raise UserError(f"--{given[0].replace('_', '-')} does not apply with --recipe: the recipe file sets "
                            "every training setting (give only --dataset/--data, --out, --resume, --threads, "
                            "--device, --seed)")
        return _train_recipe(recipe, dataset, data, _out(out, "odmo"), resume, threads, device, nproc, seed, as_json)
    dataset = dataset or "humanact12"

    out = _out(out, "odmo")
    if same_class is not None and not (0 <= same_class <= 1 or same_class == -1):
        raise UserError(f"--same-class-fraction must be in [0, 1] (or -1: independent pairs), got {same_class}")
    bad = [a for a in ablate or [] if a not in ABLATIONS]
    if bad:
        raise UserError(f"unknown ablation {bad[0]!r}; valid: {', '.join(ABLATIONS)}")
    if preset not in PRESETS:
        raise UserError(f"unknown preset {preset!r}; valid: {', '.join(PRESETS)}")
    if tf_per is not None and tf_per not in ("step", "clip"):
        raise UserError(f"--tf-per must be step or clip, got {tf_per!r}")
    if pose_frame is not None and pose_frame not in POSE_FRAMES:
        raise UserError(f"--pose-frame must be one of {', '.join(POSE_FRAMES)}, got {pose_frame!r}")
    if pose_loss is not None and pose_loss not in POSE_LOSSES:
        raise UserError(f"--pose-loss must be one of {', '.join(POSE_LOSSES)}, got {pose_loss!r}")
    if root is not None and root not in ROOTS:
        raise UserError(f"unknown --root {root!r}; valid: {', '.join(ROOTS)}")
    if pose_frame is not None and init is not None:
        raise UserError("--pose-frame changes what the weights mean; a stage from --init keeps its file's")
    if motion_hidden is not None and motion_hidden < 1:
        raise UserError(f"--motion-hidden must be a positive number of units, got {motion_hidden}")
    scales = {"sigma2": sigma2, "recon_weight": recon_weight}  # ODMOConfig fields, given as --sigma2, --recon-weight
    for key, value in scales.items():
        if value is not None and not 0 < value < math.inf:  # nan fails every comparison
            raise UserError(f"--{key.replace('_', '-')} must be a finite number > 0, got {value}")
    for flag, value in (("--vel-weight", vel_weight), ("--energy-weight", energy_weight),
                        ("--free-energy-weight", free_energy_weight), ("--height-weight", height_weight),
                        ("--mix-energy-weight", mix_energy_weight)):
        if value is not None and not 0 <= value < math.inf:
            raise UserError(f"{flag} must be a finite number >= 0, got {value}")
    scales.update(vel_weight=vel_weight, energy_weight=energy_weight, free_energy_weight=free_energy_weight,
                  height_weight=height_weight, mix_energy_weight=mix_energy_weight)
    overrides = {"use_es": "es" not in (ablate or []), "use_traj": "traj" not in (ablate or []),
                 "use_cons": "cons" not in (ablate or []), "use_end_point": "end-point" not in (ablate or [])}
    overrides.update(_given(**scales, pose_frame=pose_frame, pose_loss=pose_loss, root=root,
                            motion_hidden=motion_hidden))
    if init is not None:  # the file's config stands but for what was asked: loss weights, ablations
        if resume is not None:
            raise UserError("give either --init (start a new stage from a model's weights) or --resume, not both")
        overrides = {k: v for k, v in overrides.items() if not k.startswith("use_") or not v}
    lr = 1e-3 if lr is None else lr
    tc = TrainConfig(**_given(epochs=_epochs(resume, epochs), batch_size=batch_size, checkpoint_every=checkpoint_every,
                              val_every=val_every, same_class_fraction=same_class, tf_per=tf_per, mirror=mirror or None,
                              weight_decay=weight_decay, decoder_dropout=decoder_dropout, crops=crops,
                              code_noise=code_noise,
                              free_from=free_from, tf_start=tf_start, tf_end=tf_end, train_parts=train_parts),
                     lr=lr, lr_final=lr if lr_final is None else lr_final, tf_epochs=tf_epochs,
                     seed=seed, threads=threads)
    prints = _start(device, nproc)  # after the options' own checks, before any data is read
    clips = _clips(dataset, data)
    with _epoch_bar(tc.epochs, as_json or not prints) as update, _interruptible(out, prints, odmo=True):
        result = train_odmo(clips, tc, out, overrides, resume, _log_progress(update, tc.val_every), preset, device, init)
    if not prints:
        return
    if as_json:
        return _print_result(result)
    console.print(f"wrote {result.out} after {result.epochs} epochs")
    _print_odmo_report(result.report)


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
def train_classifier_cmd(
    dataset: DatasetOpt = "humanact12", data: DataOpt = None,
    epochs: Annotated[Optional[int], typer.Option("--epochs", help="Epochs to train (default 200: the shipped HumanAct12 classifier's recipe).")] = None,
    batch_size: Annotated[Optional[int], typer.Option("--batch-size", help="Clips per step (default 64).")] = None,
    lr: Annotated[Optional[float], typer.Option("--lr", help="Adam learning rate (default 1e-3).")] = None,
    lr_final: Annotated[Optional[float], typer.Option("--lr-final", help="Cosine decay of the rate to this value (default 1e-5; 0: constant).")] = None,
    checkpoint_every: CheckpointOpt = None,
    out: OutOpt = None, resume: ResumeOpt = None, threads: ThreadsOpt = 0,
    device: DeviceOpt = "cpu", nproc: NprocOpt = 1, seed: SeedOpt = 0, as_json: JsonOpt = False,
):
    """Train the action classifier that evaluation reads motions with, on real clips with a held-out split."""
    from odmo_cli.training.classifier import ClassifierTrainConfig, train_classifier

    out = _out(out, "classifier")
    tc = ClassifierTrainConfig(**_given(epochs=_epochs(resume, epochs), batch_size=batch_size, lr=lr, lr_final=lr_final,
                                        checkpoint_every=checkpoint_every), seed=seed, threads=threads)
    prints = _start(device, nproc)  # after the options' own checks, before any data is read
    clips = _clips(dataset, data)

    def show(log: dict) -> None:
        if prints and (log["epoch"] % 10 == 0 or log["epoch"] == tc.epochs):
            err_console.print(f"epoch {log['epoch']}/{tc.epochs} loss {log['loss']:.3f} train acc "
                              f"{100 * log['train_accuracy']:.1f}% val acc {100 * log['val_accuracy']:.1f}%",
                              highlight=False)

    with _interruptible(out, prints):
        report = train_classifier(clips, tc, out, None if as_json else show, resume, device)
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
        result = train_recipe(clips, recipe, out, seed, resume, _log_progress(update, recipe.train.get("val_every", 10)),
                              device, threads)
    if not prints:
        return
    if as_json:
        return _print_result(result)
    r = result.report
    console.print(f"wrote {result.out}: {len(recipe.phases)} phases, {result.epochs} epochs, {r['pairs']:,} pairs "
                  f"in {r['hours']:.2f} h")
    _print_odmo_report(r)


@train_app.command("a2m", cls=Command)
def train_a2m_cmd(
    dataset: DatasetOpt = "humanact12", data: DataOpt = None,
    representation: Annotated[Optional[str], typer.Option("--representation", help="Output: lie (the paper's model, default) or xyz (its 'w/o Lie' variant).")] = None,
    epochs: Annotated[Optional[int], typer.Option("--epochs", help="Epochs to train (default 500; one epoch visits every training clip once).")] = None,
    batch_size: Annotated[Optional[int], typer.Option("--batch-size", help="Clips per step (default 128, the paper's).")] = None,
    lr: Annotated[Optional[float], typer.Option("--lr", help="Adam learning rate (default 2e-4, the paper's).")] = None,
    lr_final: LrFinalOpt = None, checkpoint_every: CheckpointOpt = None, val_every: ValOpt = None,
    out: OutOpt = None, resume: ResumeOpt = None, threads: ThreadsOpt = 0,
    device: DeviceOpt = "cpu", nproc: NprocOpt = 1, seed: SeedOpt = 0, as_json: JsonOpt = False,
):
    """Train the Action2Motion baseline (conditional temporal VAE, xyz or Lie output)."""
    from odmo_cli.models.a2m import REPRESENTATIONS
    from odmo_cli.training.a2m import A2MTrainConfig, train_a2m

    out = _out(out, "a2m")
    if representation is not None and representation not in REPRESENTATIONS:
        raise UserError(f"unknown representation {representation!r}; valid: {', '.join(REPRESENTATIONS)}")
    tc = A2MTrainConfig(**_given(epochs=_epochs(resume, epochs), batch_size=batch_size, lr=lr, lr_final=lr_final,
                                 checkpoint_every=checkpoint_every, val_every=val_every), seed=seed, threads=threads)
    prints = _start(device, nproc)  # after the options' own checks, before any data is read
    clips = _clips(dataset, data)
    with _epoch_bar(tc.epochs, as_json or not prints) as update, _interruptible(out, prints):
        result = train_a2m(clips, tc, out, representation, resume, _log_progress(update, tc.val_every), device=device)
    if not prints:
        return
    if as_json:
        return _print_result(result)
    r = result.report
    console.print(f"wrote {result.out} (a2m-{r['representation']}) after {result.epochs} epochs; held-out "
                  f"({r['held_out_clips']} clips, teacher-forced): joint mse {r['held_out_mse']:.4g}, "
                  f"KL {r['held_out_kl']:.4g} (lambda {r['lambda_kl']:g})")


@train_app.command("dvgan", cls=Command)
def train_dvgan_cmd(
    dataset: DatasetOpt = "humanact12", data: DataOpt = None,
    generator: Annotated[str, typer.Option("--generator", help="cnn (default) or rnn (rnn also completes motions: `odmo complete`).")] = "cnn",
    epochs: Annotated[Optional[int], typer.Option("--epochs", help="Epochs to train, one discriminator pass over the clips each (default 10500: the paper's schedule).")] = None,
    batch_size: Annotated[Optional[int], typer.Option("--batch-size", help="Clips per step (default 64).")] = None,
    lr: Annotated[Optional[float], typer.Option("--lr", help="Adam learning rate of both networks (default 1e-4, the paper's).")] = None,
    lr_final: LrFinalOpt = None,
    n_critic: Annotated[Optional[int], typer.Option("--n-critic", help="Discriminator steps per generator step (default 10, the paper's).")] = None,
    checkpoint_every: CheckpointOpt = None,
    out: OutOpt = None, resume: ResumeOpt = None, threads: ThreadsOpt = 0,
    device: DeviceOpt = "cpu", nproc: NprocOpt = 1, seed: SeedOpt = 0, as_json: JsonOpt = False,
):
    """Train the DVGAN baseline (WGAN-GP conditioned on the action name, CNN or RNN generator)."""
    from odmo_cli.models.dvgan import GENERATORS
    from odmo_cli.training.dvgan import DVGANTrainConfig, train_dvgan

    out = _out(out, "dvgan")
    if generator not in GENERATORS:
        raise UserError(f"unknown DVGAN generator {generator!r}; valid: {', '.join(GENERATORS)}")
    tc = DVGANTrainConfig(**_given(epochs=_epochs(resume, epochs), batch_size=batch_size, lr=lr, lr_final=lr_final, n_critic=n_critic,
                                   checkpoint_every=checkpoint_every), seed=seed, threads=threads)
    prints = _start(device, nproc)  # after the options' own checks, before any data is read
    clips = _clips(dataset, data)

    def show(update):
        def progress(log: dict) -> None:
            info = " ".join(f"{k} {log[k]:.3g}" for k in ("d_loss", "wasserstein", "g_loss") if k in log)
            update(log["epoch"], info, log["epoch"] % 25 == 0 or log["epoch"] == tc.epochs)
        return progress

    with _epoch_bar(tc.epochs, as_json or not prints) as update, _interruptible(out, prints):
        result = train_dvgan(clips, tc, out, generator, resume=resume, progress=show(update), device=device)
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
def _epoch_bar(total: int, quiet: bool):
    """Yields update(epoch, info, line): a rich bar on a terminal; in a log file, one line per `line`."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    # the bar starts with the first finished epoch, so an early error prints only its one line
    bar = Progress(TextColumn("epoch"), MofNCompleteColumn(), BarColumn(), TimeElapsedColumn(), TextColumn("<"),
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
                err_console.print(f"epoch {epoch}/{total} ({_clock(spent)} elapsed, {_clock(left)} left) {info}",
                                  highlight=False)
            return
        bar.start()
        bar.update(task, completed=epoch, info=info)

    try:
        yield update
    finally:
        if bar.live.is_started:
            bar.stop()


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
    out: Annotated[Path, typer.Option("--out", help="Folder for the files (odmo_<name>.pt, classifier_<name>.pt).")],
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
    from odmo_cli.ship import build, recipe_name, total_epochs
    from odmo_cli.training.recipe import load_recipe

    epochs = load_recipe(recipe).epochs if recipe is not None else total_epochs(recipe_name(dataset))
    with (_epoch_bar(epochs, as_json) as update,
          _interruptible("run the same command again to continue the training")):
        reports = build(dataset, data, out, seed, skip_classifier, _log_progress(update, 10),
                        say=lambda m: None if as_json else err_console.print(m, highlight=False), recipe_file=recipe)
    if as_json:
        return print_json(reports)
    if "classifier" in reports:
        console.print(f"classifier: held-out accuracy {100 * reports['classifier']['val_accuracy']:.1f}%")
    r = reports["odmo"]
    console.print(f"ODMO: {r['epochs']} epochs, held-out joint error {r['held_out_mpjpe']:.3f}, "
                  f"nearest-centroid accuracy {100 * r['nearest_centroid_acc']:.1f}%; files in {out}")
