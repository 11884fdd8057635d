"""`odmo eval` (alias `evaluate`) and `odmo bench`."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.table import Table

from odmo_cli.cli.common import DataOpt, ModelOpt, SeedOpt, app, console, err_console
from odmo_cli.errors import UserError


METRIC_HEADS = {"accuracy": "Acc ↑", "fid": "FID ↓", "diversity": "Diversity →", "multimodality": "MModality →",
                "inception": "IS ↑", "n_apd": "n-APD", "bone_std": "bone std ↓", "speed": "speed →1",
                "amplitude": "amplitude →1"}


def evaluate(
    checkpoints: Annotated[Optional[list[str]], typer.Argument(help="More checkpoints for the same table (as --compare).", show_default=False)] = None,
    model: Annotated[Optional[str], typer.Option("--model", help="Checkpoint or shipped name (default humanact12 when no other model or samples are named).")] = None,
    compare: Annotated[Optional[list[str]], typer.Option("--compare", help="More checkpoints for the same table; CKPT@conventional: that row samples conventionally.")] = None,
    dataset: Annotated[Optional[str], typer.Option("--dataset", help="Dataset (default: the model's).")] = None,
    classifier: Annotated[Optional[str], typer.Option("--classifier", help="Classifier checkpoint or Action2Motion .tar.")] = None,
    repeats: Annotated[int, typer.Option("--repeats")] = 10,
    per_action: Annotated[int, typer.Option("--per-action", help="Samples per action (0: the paper's).")] = 0,
    sampling: Annotated[str, typer.Option("--sampling", help="mode-preserving | conventional")] = "mode-preserving",
    samples: Annotated[Optional[list[Path]], typer.Option("--samples", help="Evaluate a samples .npz made elsewhere.")] = None,
    customization: Annotated[bool, typer.Option("--customization", help="Also the end-point protocol (§4.4).")] = False,
    held_out: Annotated[bool, typer.Option("--held-out", help="Also a row for the real clips the classifier never trained on (odmo classifiers).")] = False,
    by_action: Annotated[bool, typer.Option("--by-action", help="Also print each row's accuracy, speed and amplitude ratios per action.")] = False,
    json_out: Annotated[Optional[Path], typer.Option("--json", help="Write the full report as JSON here.")] = None,
    data: DataOpt = None, seed: SeedOpt = 0,
):
    """The evaluation protocol: Acc, FID, Diversity, Multimodality, n-APD, bone std, and the speed and
    amplitude of the body's motion over the real motions' (mean ± 95% CI)."""
    from odmo_cli.evaluate import EvalConfig, run_evaluation
    from odmo_cli.io import atomic_path

    cfg = EvalConfig(repeats=repeats, per_action=per_action, sampling=sampling, seed=seed)
    others = list(compare or []) + list(checkpoints or [])
    # the shipped default joins only when nothing else is named: `--compare a.pt b.pt` is a table of a and b
    models = ([model] if model or not (samples or others) else []) + others
    with err_console.status("evaluating ..."):
        report = run_evaluation(models, dataset, data, classifier, cfg, list(samples or []), customization,
                                held_out=held_out)
    table = Table(title=f"{report.dataset}: {report.config['repeats']} repeats x {report.config['per_action']} "
                        f"per action, classifier {Path(report.classifier).name} ({report.seconds:.0f} s)")
    table.add_column("model")
    for key in METRIC_HEADS:
        table.add_column(METRIC_HEADS[key], justify="right")
    for row in report.rows:
        table.add_row(row["name"], *(f"{row['metrics'][k][0]:.{3 if k in ('fid', 'bone_std') else 2}f}"
                                     f" ±{row['metrics'][k][1]:.2f}" if k in row["metrics"] else "-"
                                     for k in METRIC_HEADS))
    console.print(table)
    if by_action:
        for key, title, digits in (("by_action", "accuracy", 1), ("speed_by_action", "speed ratio", 2),
                                   ("amplitude_by_action", "amplitude ratio", 2)):
            console.print(_by_action_table(report.rows, key, title, digits))
    for c in report.customization:
        m = c["metrics"]
        console.print(f"customization {c['name']}: Acc {m['accuracy'][0]:.2f} ±{m['accuracy'][1]:.2f}, "
                      f"dist_e {m['dist_e'][0]:.4f} ±{m['dist_e'][1]:.4f}")
    if json_out is not None:
        import json

        with atomic_path(json_out) as tmp:
            tmp.write_text(json.dumps(report.__dict__, indent=2, default=str))
        console.print(f"wrote {json_out}")


def _by_action_table(rows: list[dict], key: str, title: str, digits: int) -> Table:
    table = Table(title=f"{title} per action (mean ± 95% CI)")
    table.add_column("action")
    for row in rows:
        table.add_column(row["name"], justify="right")
    actions = list(dict.fromkeys(a for row in rows for a in row.get(key, {})))
    for a in actions:
        cells = [f"{row[key][a][0]:.{digits}f} ±{row[key][a][1]:.{digits}f}" if a in row.get(key, {}) else "-"
                 for row in rows]
        table.add_row(a, *cells)
    return table


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
