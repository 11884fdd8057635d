"""Generation commands: info, sample, export, render, complete, interpolate, modes."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.table import Table

from odmo_cli.cli.common import (Command, DataOpt, DeviceOpt, EndOpt, JsonOpt, ModelOpt, OutOpt, RootOpt, SeedOpt, UpOpt, WideOpt,
                                 app, console, device_for, err_console, print_json)
from odmo_cli.errors import UserError


@app.command("info", cls=Command)
def info(checkpoint: Annotated[Optional[str], typer.Argument(help="Checkpoint path or shipped name (as --model).", show_default=False)] = None,
         model: ModelOpt = None, as_json: JsonOpt = False):
    """What a checkpoint holds: model kind, configs, dataset, epochs, final report."""
    from odmo_cli.checkpoint import checkpoint_path, describe_checkpoint

    if checkpoint and model and checkpoint != model:
        raise UserError(f"give the checkpoint once: {checkpoint} or --model {model}")
    desc = describe_checkpoint(checkpoint_path(checkpoint or model))
    if as_json:
        return print_json(desc)
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
               "frames": int(batch.dataset["length"]), "actions": per_action, "dist_e": batch.dist_e(),
               **({"note": batch.note} if batch.note else {}), **(extra or {})}
    if as_json:
        return print_json(payload)
    if batch.note:
        console.print(batch.note, highlight=False)
    table = Table(title=f"{len(batch)} motions -> {out}")
    table.add_column("action")
    table.add_column("motions", justify="right")
    table.add_column("modes used (mode: count)")
    for a, counts in per_action.items():
        table.add_row(a, str(sum(counts.values())), ", ".join(
            f"n/a: {v}" if k < 0 else f"{k}: {v}" for k, v in sorted(counts.items())))
    console.print(table)
    if payload["dist_e"] is not None:
        axes = list(batch.end_axes)  # the ground-plane coordinates --end gave, not the height it did not
        reach = np.sqrt(np.mean(np.sum((batch.end_points[:, axes] - batch.reached[:, axes]) ** 2, axis=1)))
        console.print(f"dist_e (mean squared end-point error) {payload['dist_e']:.4f}; RMS distance on the ground "
                      f"plane {reach:.3f}")
    console.print(f"model {batch.model}, seed {batch.seed}, {batch.dataset['fps']:g} fps, skeleton {batch.dataset['skeleton']}")


UnitsOpt = Annotated[str, typer.Option("--units", help="BVH units: cm (most tools and rigs) or m.")]
FloorOpt = Annotated[bool, typer.Option("--floor/--no-floor", help="BVH: lift the motion so its lowest foot touches y = 0.", metavar="")]
HelpersOpt = Annotated[bool, typer.Option("--helper-joints", help="BVH: a zero-length joint per child of the pelvis and chest "
                                                                  "(one bone per child; exact however the torso bends).", metavar="")]


@app.command("sample", cls=Command)
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
    up: UpOpt = "dataset",
    units: UnitsOpt = "cm", floor: FloorOpt = True, helpers: HelpersOpt = False, root: RootOpt = None,
    device: DeviceOpt = "cpu", seed: SeedOpt = 0, as_json: JsonOpt = False,
):
    """Generate motions of the given actions (the samples file is described in docs/formats.md)."""
    from odmo_cli.checkpoint import load_model
    from odmo_cli.formats.bvh import BvhOptions
    from odmo_cli.generation.generate import sample

    dev = device_for(device)
    bvh_options = BvhOptions(units, floor, helpers)  # checked before any work

    if mode is not None and mode_weights is not None:
        raise UserError("give either --mode or --mode-weights, not both")
    weights = _floats(mode_weights, "--mode-weights") if mode_weights is not None else None
    loaded = load_model(model, dev, root)
    batch = sample(loaded, action, n, seed, mode, weights, sampling, end, end_from, end_to, steps, lazy=True)
    batch.save(out, up, loaded)  # decodes batch by batch while writing: memory stays flat in n
    if gif is not None:
        from odmo_cli.geometry.skeletons import get_skeleton
        from odmo_cli.formats.viz import animate

        k = min(len(batch), 8)
        _, notice = animate(batch.head(k, loaded), get_skeleton(batch.dataset["skeleton"]), gif, fps=batch.dataset["fps"],
                            titles=[f"{a} #{i}" for i, a in enumerate(batch.actions[:k])], end_points=batch.end_points[:k])
        if notice:
            err_console.print(notice, highlight=False, markup=False)
    extra = None
    if bvh is not None:
        from odmo_cli.formats.bvh import export_samples

        report = export_samples(out, bvh, bvh_options)  # from the file just written: the batch is not kept decoded
        extra = {"bvh": str(bvh), "bvh_files": len(report.files), "bvh_max_error_mm": report.max_error_mm,
                 "bvh_mean_error_mm": report.mean_error_mm,
                 "bone_stretch_mm": report.max_stretch_mm}
    _summary(batch, out, as_json, extra)
    if bvh is not None and not as_json:
        _bvh_note(report, bvh)


def _bvh_note(report, folder: Path) -> None:
    console.print(f"wrote {len(report.files)} BVH files ({report.joints} joints, y-up, {report.units}) to {folder}: "
                  f"joint positions within "
                  f"{report.max_error_mm:.2f} mm (mean {report.mean_error_mm:.2f} mm) of the motions (bones stretch by up to "
                  f"{report.max_stretch_mm:.2f} mm; a BVH keeps each bone's mean length)", highlight=False)


@app.command("export", cls=Command)
def export_cmd(
    samples: Annotated[Path, typer.Argument(help="A samples file (.npz) from odmo sample/interpolate.")],
    bvh: Annotated[Path, typer.Option("--bvh", help="Folder for the BVH files (one per motion).")],
    units: UnitsOpt = "cm", floor: FloorOpt = True, helpers: HelpersOpt = False,
    as_json: JsonOpt = False,
):
    """Write every motion of a samples file as a BVH file (y-up, the model's fps; docs/formats.md)."""
    from odmo_cli.formats.bvh import BvhOptions, export_samples

    report = export_samples(samples, bvh, BvhOptions(units, floor, helpers))
    if as_json:
        return print_json({"bvh": str(bvh), "files": [str(f) for f in report.files], "units": report.units,
                           "joints": report.joints, "max_error_mm": report.max_error_mm,
                           "mean_error_mm": report.mean_error_mm, "bone_stretch_mm": report.max_stretch_mm})
    _bvh_note(report, bvh)


@app.command("render", cls=Command)
def render_cmd(
    samples: Annotated[Path, typer.Argument(help="A samples file (.npz).")],
    out: Annotated[Optional[Path], typer.Option("--out", help="Animation to write: .gif or .mp4 (.png: one still); default: the samples file's name with .gif, beside it.")] = None,
    index: Annotated[Optional[int], typer.Option("--index", help="Render only this motion (default 0).")] = None,
    grid: Annotated[Optional[str], typer.Option("--grid", help="ROWSxCOLS of the first motions, e.g. 4x5.")] = None,
    trail: Annotated[bool, typer.Option("--trail", help="Draw the paths of the root, hands and feet so far.", metavar="")] = False,
    size: Annotated[Optional[str], typer.Option("--size", help="Output size WIDTHxHEIGHT in pixels, e.g. 640x480.")] = None,
    frame: Annotated[Optional[int], typer.Option("--frame", help="For a .png still: the frame to draw (default: the middle one).")] = None,
    compare: Annotated[Optional[str], typer.Option("--compare", help="real: real clips of the same actions under the generated ones (needs the data).")] = None,
    data: DataOpt = None, seed: SeedOpt = 0,
):
    """3-D stick-figure animation with ground plane, root trajectory and asked end point."""
    from odmo_cli.formats.viz import render_samples

    out = out or samples.with_suffix(".gif")
    written, notice = render_samples(samples, out, index, grid, trail, size, frame, compare, data, seed)
    if notice:
        err_console.print(notice, highlight=False, markup=False)
    console.print(f"wrote {written}", highlight=False)


@app.command("complete", cls=Command)
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
    from odmo_cli.checkpoint import load_model
    from odmo_cli.generation.generate import complete, read_prefix

    batch = complete(load_model(model), read_prefix(prefix), frames, action, n, seed)
    batch.save(out)
    _summary(batch, out, as_json, {"prefix_frames": frames})


def _floats(text: str, flag: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",")]
    except ValueError:
        raise UserError(f"{flag} must be comma-separated numbers, got {text!r}") from None


@app.command("interpolate", cls=Command)
def interpolate_cmd(
    action: Annotated[str, typer.Option("--action", help="Action name (see `odmo modes`).")],
    from_mode: Annotated[Optional[int], typer.Option("--from-mode", help="Start at this discovered mode's mean (default: mode 0).")] = None,
    to_mode: Annotated[Optional[int], typer.Option("--to-mode", help="End at this discovered mode's mean (default: mode 1).")] = None,
    from_code: Annotated[Optional[int], typer.Option("--from-code", help="Start at this latent-bank code (an index; instead of --from-mode).")] = None,
    to_code: Annotated[Optional[int], typer.Option("--to-code", help="End at this latent-bank code (an index; instead of --to-mode).")] = None,
    steps: Annotated[int, typer.Option("--steps", help="Motions on the line between the two ends, both included.")] = 8,
    end: EndOpt = None, out: OutOpt = Path("interpolation.npz"), model: ModelOpt = None, up: UpOpt = "dataset",
    root: RootOpt = None, device: DeviceOpt = "cpu", seed: SeedOpt = 0, as_json: JsonOpt = False,
):
    """Blend two modes (or two codes) of an action: one motion per step on the line between them.
    Without --from/--to: the action's first two modes (an action with one mode: its first and last codes)."""
    from odmo_cli.checkpoint import load_odmo
    from odmo_cli.generation.generate import interpolate

    loaded = load_odmo(model, device_for(device), root)
    batch = interpolate(loaded, action, steps, from_mode, to_mode, from_code, to_code, end, seed)
    batch.save(out, up)
    _summary(batch, out, as_json)


@app.command("modes", cls=Command)
def modes_cmd(
    model: ModelOpt = None,
    refit: Annotated[bool, typer.Option("--refit", help="Refit the mixtures and save them into the checkpoint.", metavar="")] = False,
    mixture_data: Annotated[Optional[str], typer.Option("--mixture-data", help="With --refit: fit on crops (codes of random crops of the training clips, as the authors' release; needs the data) or clips (one code per clip). Default: the file's own.")] = None,
    k_rule: Annotated[Optional[str], typer.Option("--k-rule", help="With --refit: how the number of modes k is chosen from the silhouette curve: paper (the supplement's text: k 3..11, the first i with S_i > 0.95 S_(i+1)) or release (the authors' code: k 3..9, raised while S_(k+1) >= 0.95 S_k). Default: the file's own.")] = None,
    data: DataOpt = None,
    plot: Annotated[Optional[Path], typer.Option("--plot", help="Write a 2-D plot of the codes (.png).")] = None,
    projection: Annotated[str, typer.Option("--projection", help="The plot's 2-D projection: pca or tsne.")] = "pca",
    colour: Annotated[str, typer.Option("--colour", help="Colour the plot's points by action or by mode.")] = "action",
    action: Annotated[Optional[str], typer.Option("--action", help="Plot only this action.")] = None,
    seed: SeedOpt = 0, as_json: JsonOpt = False, wide: WideOpt = False,
):
    """Discovered modes per action: counts, silhouettes, agreement with ground-truth modes."""
    from odmo_cli.checkpoint import load_odmo
    from odmo_cli.generation.generate import mixture_data as crops_for, refit_modes
    from odmo_cli.models.latent import mode_report

    if colour not in ("action", "mode"):
        raise UserError(f"unknown --colour {colour!r}; valid: action, mode")
    if mixture_data is not None and not refit:
        raise UserError("--mixture-data chooses what --refit fits on; give --refit too")
    if k_rule is not None and not refit:
        raise UserError("--k-rule chooses how --refit picks the number of modes; give --refit too")
    loaded = load_odmo(model)
    if refit:
        refit_modes(loaded, seed, False if mixture_data is None else crops_for(loaded, mixture_data, data, seed), k_rule)
    rows = mode_report(loaded.bank, loaded.modes, loaded.actions)
    if plot is not None:
        _plot_modes(loaded, plot, projection, colour, action, seed)
    if as_json:
        return print_json({"model": loaded.source, "k_rule": loaded.k_rule, "actions": rows,
                           "plot": str(plot) if plot else None})
    table = Table(title=f"modes of {Path(loaded.source).name} (k rule: {loaded.k_rule})")
    columns = ["action", "clips", "modes", "members", "true modes", "ARI"] + (["silhouette by k"] if wide else [])
    for col in columns:
        table.add_column(col, no_wrap=col == "action", justify="left" if col in ("action", "members") else "right")
    for r in rows:
        cells = [r["action"], str(r["clips"]), str(r["modes"]), " ".join(map(str, r["members"])),
                 "-" if r["true_modes"] is None else str(r["true_modes"]), "-" if r["ari"] is None else f"{r['ari']:.2f}"]
        if wide:
            cells.append(" ".join(f"{k}:{v:.2f}" for k, v in r["silhouettes"].items()) or r["note"])
        table.add_row(*cells)
    console.print(table)
    if not wide:
        console.print("silhouettes by k: --wide or --json", style="dim")
    if plot is not None:
        console.print(f"wrote {plot}")


def _plot_modes(loaded, plot: Path, projection: str, colour: str, action: Optional[str], seed: int) -> None:
    import numpy as np

    from odmo_cli.models.latent import assign
    from odmo_cli.formats.viz import latent_plot

    codes, labels = loaded.bank["codes"].numpy(), loaded.bank["labels"].numpy()
    chosen = [loaded.action_index(action)] if action else list(range(len(loaded.actions)))
    sel = np.isin(labels, chosen)
    groups, names, gaussians = np.zeros(len(codes), dtype=int), [], []
    if colour == "action":
        groups, names = labels, loaded.actions
    for a in chosen:
        m = loaded.action_modes(a)
        gaussians += list(zip(m.means, m.covariances))
        if colour == "mode":
            own = labels == a
            groups[own] = len(names) + assign(m, codes[own].astype(np.float64))
            names += [f"{loaded.actions[a]} mode {k}" for k in range(len(m.means))]
    latent_plot(codes[sel], groups[sel], names, plot, projection, gaussians, seed,
                title=f"{loaded.dataset['name']} latent codes ({projection})")
