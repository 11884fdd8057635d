"""`odmo data ...`: list, inspect, fetch, prepare and show datasets."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.table import Table

from odmo_cli.cli.common import (Command, DataOpt, DatasetArg, DemoOpt, JsonOpt, SeedOpt, WideOpt, console, data_app, err_console,
                                 print_json, resolve_spec)
from odmo_cli.errors import UserError


@data_app.command("list", cls=Command)
def data_list(data: DataOpt = None, as_json: JsonOpt = False, wide: WideOpt = False):
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
        return print_json({"data_root": str(data_root(data)), "datasets": rows})
    table = Table(title="datasets")
    columns = ("name", "title", "actions", "clips", "skeleton", "on disk") if wide else ("name", "actions", "clips",
                                                                                          "skeleton", "on disk")
    for col in columns:
        table.add_column(col, no_wrap=col in ("name", "on disk"))
    for r in rows:
        cells = {"name": r["name"], "title": r["title"], "actions": str(r["actions"]), "clips": str(r["clips"]),
                 "skeleton": r["skeleton"]}
        cells["on disk"] = (r["present"] if wide else "yes") if r["present"] else "[dim]no[/dim]"
        table.add_row(*(cells[c] for c in columns))
    console.print(table)
    # the root on a line of its own: a path is never wrapped, the hint would push it past 80 columns
    console.print(f"data root: {data_root(data)}", highlight=False, soft_wrap=True)
    if not wide:
        console.print("titles and folders: --wide", highlight=False)


@data_app.command("info", cls=Command)
def data_info(dataset: DatasetArg, data: DataOpt = None, demo: DemoOpt = False,
              verify: Annotated[bool, typer.Option(help="Check files against the manifest's SHA-256.", metavar="")] = True,
              as_json: JsonOpt = False):
    """Actions x clips x lengths; flags missing, extra or corrupt files against the manifest."""
    from odmo_cli.data.prepare import summarize

    manifest, root = resolve_spec(dataset, data, demo)
    s = summarize(manifest, root, verify=verify and not demo)
    if as_json:
        return print_json(s.to_json())
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


@data_app.command("fetch", cls=Command)
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
        return print_json(summary)
    console.print(f"{manifest.name} in {result.dest}: {len(result.downloaded)} downloaded, "
                  f"{len(result.present)} already present and verified, {len(result.extracted)} extracted")


@data_app.command("prepare", cls=Command)
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


@data_app.command("show", cls=Command)
def data_show(dataset: DatasetArg, action: Annotated[str, typer.Option("--action", help="Action name.")],
              out: Annotated[Optional[Path], typer.Option("--out", help=".gif or .mp4 (animated) or .png")] = None,
              n: Annotated[int, typer.Option("--n", help="How many clips.")] = 4,
              data: DataOpt = None, demo: DemoOpt = False, seed: SeedOpt = 0):
    """Render a few clips of one action as stick figures."""
    import numpy as np

    from odmo_cli.data.dataset import crop_pad_shift
    from odmo_cli.data.readers import read_dataset
    from odmo_cli.formats.viz import animate

    if n <= 0:
        raise UserError(f"--n must be a positive number of clips, got {n}")
    manifest, root = resolve_spec(dataset, data, demo)
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
