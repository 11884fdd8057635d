"""`odmo compose`: a sequence of actions as one continuous motion."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.table import Table

from odmo_cli.cli.common import (Command, DeviceOpt, JsonOpt, ModelOpt, OutOpt, RootOpt, SeedOpt, app, console,
                                 device_for, print_json)
from odmo_cli.cli.settings import sources

SPEC_ARG = ("The segments in order, comma-separated, each ACTION #MODE DURATION to X,Z with all but the action "
            "optional, e.g. \"walk 4s, sit, drink#1 2s to 1.5,0.5\". DURATION: seconds (4s) or frames (80f), default "
            "one model length; #MODE: a discovered mode (odmo modes); to X,Z: where the segment ends on the ground "
            "plane, the first frame's root at the origin.")


@app.command("compose", cls=Command)
def compose_cmd(
    spec: Annotated[str, typer.Argument(help=SPEC_ARG, show_default=False)],
    out: OutOpt = Path("composition.npz"),
    model: ModelOpt = None,
    n: Annotated[int, typer.Option("--n", help="Different sequences of the same segments.")] = 1,
    start_from: Annotated[Optional[Path], typer.Option(
        "--start-from", help="Continue this motion, kept exactly as the first frames: a samples .npz (its first "
                             "motion), a (frames, joints, 3) .npy of the model's skeleton, or a .bvh.")] = None,
    method: Annotated[str, typer.Option(
        "--method", help="primed (the default: each segment continues the body the last one left) or paste "
                         "(the cut-and-paste baseline: segments sampled on their own, placed end to end).")] = "primed",
    root: RootOpt = None, device: DeviceOpt = "cpu", seed: SeedOpt = 0, as_json: JsonOpt = False,
):
    """One continuous motion of several actions (ODMO): root, heading and body carry on from segment to
    segment. The samples file holds each frame's action and the segments (docs/formats.md); `odmo render`
    shows the action changing, `odmo export --bvh` writes one BVH per sequence."""
    from odmo_cli.checkpoint import load_odmo
    from odmo_cli.generation.compose import ComposeConfig, compose, parse_spec, read_start

    cfg = sources({"method": method}, None, {}).build(ComposeConfig, {"method": method})  # checked before any work
    segments = parse_spec(spec)
    loaded = load_odmo(model, device_for(device), root)
    start = read_start(start_from, loaded) if start_from is not None else None
    result = compose(loaded, segments, n, seed, start, cfg)
    result.save(out)
    _summary(result, out, as_json)


def _summary(c, out: Path, as_json: bool) -> None:
    import numpy as np

    from odmo_cli.checkpoint import model_name

    fps = float(c.dataset["fps"])
    reached = c.reached()  # (K, S, 3)
    rows = []
    for s, (first, end) in enumerate(c.segments):
        asked = c.segment_ends[s]
        given = np.isfinite(asked)
        miss = float(np.linalg.norm(reached[:, s][:, given] - asked[given], axis=-1).max()) if given.any() else None
        rows.append({"action": str(c.segment_actions[s]), "first_frame": int(first), "end_frame": int(end),
                     "seconds": (end - first) / fps, "modes": [int(m) for m in c.segment_modes[:, s]],
                     "end_point": [float(v) for v in asked[given]] if given.any() else None, "end_miss": miss})
    if as_json:
        return print_json({"out": str(out), "sequences": len(c), "frames": int(c.motions.shape[1]), "fps": fps,
                           "seconds": c.motions.shape[1] / fps, "prefix_frames": c.prefix_frames,
                           "segments": rows, "method": c.method, "model": model_name(c.model), "seed": c.seed})
    table = Table(title=f"{out}: {len(c)} sequence(s) of {c.motions.shape[1]} frames ({c.motions.shape[1] / fps:.2f} s)")
    for col in ("segment", "action", "frames", "seconds", "modes", "end point (largest miss)"):
        table.add_column(col, justify="right" if col in ("segment", "seconds") else "left")
    for s, r in enumerate(rows):
        end = "-" if r["end_point"] is None else (
            ",".join(f"{v:g}" for v in r["end_point"]) + f" ({r['end_miss']:.3f})")
        table.add_row(str(s + 1), r["action"], f"{r['first_frame']}-{r['end_frame']}", f"{r['seconds']:.2f}",
                      " ".join(map(str, sorted(set(r["modes"])))), end)
    console.print(table)
    if c.prefix_frames:
        console.print(f"the first {c.prefix_frames} frames are the given motion", highlight=False)
    console.print(f"model {model_name(c.model)}, seed {c.seed}, {fps:g} fps, method {c.method}", highlight=False)
