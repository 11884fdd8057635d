"""`odmo eval` (alias `evaluate`) and `odmo bench`."""

from __future__ import annotations

import time
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.table import Table

from odmo_cli.cli.common import (Command, DataOpt, DeviceOpt, JsonOpt, ModelOpt, RootOpt, SeedOpt, WideOpt, app, console, device_for,
                                 err_console, print_json)
from odmo_cli.errors import UserError


METRIC_HEADS = {"accuracy": "Acc ↑", "fid": "FID ↓", "diversity": "Div →", "multimodality": "MM →",
                "inception": "IS ↑", "n_apd": "n-APD", "bone_std": "bone std ↓", "speed": "speed →1",
                "amplitude": "amplitude →1"}
NARROW = ("accuracy", "fid", "diversity", "multimodality")  # the papers' four; --wide adds the rest
# what an animator sees, with no trained network (odmo_cli.measures.plausibility; docs/evaluation.md)
PLAUSIBLE_HEADS = {"foot_skate": "skate ↓", "foot_contact": "contact", "root_up": "root up",
                   "root_ground": "root gnd", "kinetic_fd": "FD_k ↓", "coverage": "cover ↑",
                   "density": "density", "bone_var": "bone p95"}
DIGITS = {"fid": 3, "bone_std": 3, "foot_skate": 3, "foot_contact": 2, "bone_var": 3, "kinetic_fd": 1}


def evaluate(
    checkpoints: Annotated[Optional[list[str]], typer.Argument(help="More checkpoints for the same table (as --compare).", show_default=False)] = None,
    model: Annotated[Optional[str], typer.Option("--model", help="Checkpoint or shipped name (default humanact12 when no other model or samples are named).")] = None,
    compare: Annotated[Optional[list[str]], typer.Option("--compare", help="More checkpoints for the same table; CKPT@conventional: that row samples conventionally.")] = None,
    dataset: Annotated[Optional[str], typer.Option("--dataset", help="Dataset (default: the model's).")] = None,
    classifier: Annotated[Optional[str], typer.Option("--classifier", help="Classifier checkpoint or Action2Motion .tar (default: the shipped one of the dataset).")] = None,
    repeats: Annotated[int, typer.Option("--repeats", help="Sets generated per model; each metric is their mean ± 95% CI.")] = 10,
    per_action: Annotated[int, typer.Option("--per-action", help="Samples per action (0: the paper's).")] = 0,
    sampling: Annotated[str, typer.Option("--sampling", help="How ODMO draws codes: mode-preserving or conventional (one Gaussian per action).")] = "mode-preserving",
    samples: Annotated[Optional[list[Path]], typer.Option("--samples", help="Also score a samples .npz made elsewhere (repeatable; its dataset is the file's unless --dataset).")] = None,
    customization: Annotated[bool, typer.Option("--customization", help="Also the end-point protocol (§4.4).", metavar="")] = False,
    held_out: Annotated[bool, typer.Option("--held-out", help="Also a row for the real clips the classifier never trained on (odmo classifiers).", metavar="")] = False,
    by_action: Annotated[bool, typer.Option("--by-action", help="Also print each row's accuracy, speed and amplitude ratios, foot skating, root speeds and coverage per action.", metavar="")] = False,
    out: Annotated[Optional[Path], typer.Option("--out", help="Also write the full report (every repeat) as JSON here.")] = None,
    root: RootOpt = None, data: DataOpt = None, device: DeviceOpt = "cpu", seed: SeedOpt = 0, as_json: JsonOpt = False,
    wide: WideOpt = False,
):
    """The evaluation protocol: Acc, FID, Diversity, Multimodality, n-APD, bone std, and the speed and
    amplitude of the body's motion over the real motions' (mean ± 95% CI); then what an animator sees,
    with no trained network: foot skating and contact, the root's bounce and glide, a Fréchet distance
    of kinetic features, coverage of each action's variety, and bone-length variation."""
    from odmo_cli.evaluation.protocol import EvalConfig, run_evaluation
    from odmo_cli.io import atomic_path

    dev = device_for(device)
    cfg = EvalConfig(repeats=repeats, per_action=per_action, sampling=sampling, seed=seed, root=root)
    others = list(compare or []) + list(checkpoints or [])
    # the shipped default joins only when nothing else is named: `--compare a.pt b.pt` is a table of a and b
    models = ([model] if model or not (samples or others) else []) + others
    with _sets_bar(repeats * max(len(models), 0), as_json) as advance:
        report = run_evaluation(models, dataset, data, classifier, cfg, list(samples or []), customization,
                                progress=advance, held_out=held_out, device=dev)
    if out is not None:
        import json

        with atomic_path(out) as tmp:
            tmp.write_text(json.dumps(report.__dict__, indent=2, default=str))
    if as_json:
        return print_json(report.__dict__)
    table = Table(title=f"{report.dataset}: {report.config['repeats']} repeats x {report.config['per_action']} "
                        f"per action, classifier {Path(report.classifier).name} ({report.seconds:.0f} s)")
    keys = list(METRIC_HEADS) if wide else list(NARROW)
    ci = report.config["repeats"] > 1  # one set: no interval to estimate
    console.print(_metric_table(report.rows, {k: METRIC_HEADS[k] for k in keys}, table, ci))
    console.print(_metric_table(report.rows, PLAUSIBLE_HEADS, Table(
        title="what an animator sees (no network; the real row is the floor)"), ci))
    for row in report.rows:
        for why in row.get("not_available", []):
            console.print(f"{row['name']}: {why}", highlight=False, markup=False)
    if not wide:
        console.print("IS, n-APD, bone std, speed and amplitude ratios: --wide (all of it: --json)", style="dim")
    if by_action:
        for key, title, digits in (("by_action", "accuracy", 1), ("speed_by_action", "speed ratio", 2),
                                   ("amplitude_by_action", "amplitude ratio", 2),
                                   ("foot_skate_by_action", "foot skate", 3), ("root_up_by_action", "root up ratio", 2),
                                   ("root_ground_by_action", "root ground ratio", 2),
                                   ("coverage_by_action", "coverage", 2)):
            console.print(_by_action_table(report.rows, key, title, digits, ci))
    for c in report.customization:
        m = c["metrics"]
        console.print(f"customization {c['name']}: Acc {_value(m['accuracy'], 2, ci)}, dist_e {_value(m['dist_e'], 4, ci)}")
    if out is not None:
        console.print(f"wrote {out}")


@contextmanager
def _parts_progress(quiet: bool):
    """Yields part(name), called as each part of the benchmark starts: on a terminal, the part and the
    time so far on stderr; in a log, one line per part with the time so far (quiet with --json)."""
    from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

    start = time.monotonic()
    bar = Progress(SpinnerColumn(), TextColumn("benchmarking {task.description}"), TimeElapsedColumn(),
                   console=err_console, disable=quiet or not err_console.is_terminal)
    task = bar.add_task("...", total=None)

    def part(name: str) -> None:
        bar.update(task, description=name)
        if not quiet and not err_console.is_terminal:
            spent = int(time.monotonic() - start)
            err_console.print(f"benchmarking {name} ({spent // 60}:{spent % 60:02d} elapsed)", highlight=False)

    with bar:
        yield part


@contextmanager
def _sets_bar(total: int, quiet: bool):
    """Yields advance(): a bar of the generated sets with the time elapsed and left, on a terminal's
    stderr (quiet with --json); in a log, one line per set."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    bar = Progress(TextColumn("evaluating: sets"), MofNCompleteColumn(), BarColumn(), TimeElapsedColumn(),
                   TextColumn("<"), TimeRemainingColumn(), console=err_console,
                   disable=quiet or not err_console.is_terminal or total == 0)
    task = bar.add_task("sets", total=total)
    done = [0]

    def advance(_: int) -> None:
        done[0] += 1
        bar.update(task, completed=done[0])
        if not quiet and not err_console.is_terminal:
            err_console.print(f"evaluated set {done[0]}/{total}", highlight=False)

    with bar:
        yield advance


def _metric_table(rows: list[dict], heads: dict[str, str], table: Table, ci: bool = True) -> Table:
    table.add_column("model")
    for head in heads.values():
        table.add_column(head, justify="right")
    for row in rows:
        table.add_row(row["name"], *(_cell(row, k, ci) for k in heads))
    return table


def _cell(row: dict, key: str, ci: bool = True) -> str:
    if key not in row["metrics"]:
        return "-"
    if row["metrics"][key][0] != row["metrics"][key][0]:  # NaN: not available for this row (see its note)
        return "n/a"
    return _value(row["metrics"][key], DIGITS.get(key, 2), ci and len(row.get("per_repeat", [])) != 1)


def _value(mean_half: list[float], digits: int, ci: bool) -> str:
    """"mean ±half" (the 95% CI), or the mean alone where there is no interval (one set)."""
    mean, half = mean_half
    return f"{mean:.{digits}f} ±{half:.{digits}f}" if ci else f"{mean:.{digits}f}"


def _by_action_table(rows: list[dict], key: str, title: str, digits: int, ci: bool = True) -> Table:
    table = Table(title=f"{title} per action" + (" (mean ± 95% CI)" if ci else ""))
    table.add_column("action")
    for row in rows:
        table.add_column(row["name"], justify="right")
    actions = list(dict.fromkeys(a for row in rows for a in row.get(key, {})))
    for a in actions:
        cells = [_value(row[key][a], digits, ci and len(row.get("per_repeat", [])) != 1) if a in row.get(key, {})
                 else "-" for row in rows]
        table.add_row(a, *cells)
    return table


app.command("evaluate", cls=Command)(evaluate)
app.command("eval", cls=Command, help="Alias of evaluate.")(evaluate)


BENCH_PARTS = ("sampling", "composition", "end-to-end", "training", "evaluation")


@app.command("bench", cls=Command)
def bench(
    model: ModelOpt = None, data: DataOpt = None,
    runs: Annotated[int, typer.Option("--runs", help="Runs per figure (median reported).")] = 5,
    only: Annotated[Optional[list[str]], typer.Option("--only", help="A part to run (repeatable): sampling, composition, end-to-end, training, evaluation.")] = None,
    peer: Annotated[Optional[Path], typer.Option("--peer", help="The authors' networks' timer, bench_peer.py (default: ../shared/peer/bench_peer.py when it exists); its figures join the table, measured in the same run.")] = None,
    out: Annotated[Optional[Path], typer.Option("--out", help="Also write the figures as JSON here.")] = None,
    device: DeviceOpt = "cpu", as_json: JsonOpt = False, wide: WideOpt = False,
):
    """Speed and memory on this machine, on one device (median, min and max of several runs)."""
    from odmo_cli.evaluation.bench import run_bench
    from odmo_cli.io import atomic_path

    bad = [p for p in only or [] if p not in BENCH_PARTS]
    if bad:
        raise UserError(f"unknown benchmark part {bad[0]!r}; valid: {', '.join(BENCH_PARTS)}")
    if runs <= 0:
        raise UserError(f"--runs must be positive, got {runs}")
    dev = device_for(device)
    with _parts_progress(as_json) as part:
        report = run_bench(model, data, runs, tuple(only or ()), part, peer, dev)
    m = report.machine
    payload = {"machine": m, "figures": [f.to_json() for f in report.figures], "skipped": report.skipped}
    if out is not None:
        import json

        with atomic_path(out) as tmp:
            tmp.write_text(json.dumps(payload, indent=2))
    if as_json:
        return print_json(payload)
    table = Table(title=f"odmo bench on {m['device']}: {m['cpu']}, {m['cores']} cores, torch {m['torch']} "
                        f"({m['threads']} threads)")
    columns = ("figure", "median", "min", "max", "unit", "runs", "note") if wide else ("figure", "median", "range", "unit")
    for col in columns:
        table.add_column(col, justify="right" if col in ("median", "min", "max", "runs", "range") else "left")
    for f in report.figures:
        j = f.to_json()
        cells = {"figure": f.name, "median": f"{j['median']:.3g}", "min": f"{j['min']:.3g}", "max": f"{j['max']:.3g}",
                 "range": f"{j['min']:.3g}-{j['max']:.3g}", "unit": f.unit, "runs": str(j["runs"]), "note": f.note}
        table.add_row(*(cells[c] for c in columns))
    console.print(table)
    for s in report.skipped:
        console.print(f"skipped {s}", highlight=False)
    if not wide:
        console.print("runs and notes: --wide (or --json)", style="dim")
