"""`odmo bench`: speed and memory on this machine, each figure the median of several runs.

Figures: sampling throughput (motions/s for n = 1000 after load), what `odmo sample --action all`
does after load beside the authors' bare networks making as many motions in the same run
(../shared/peer/bench_peer.py, when present), `odmo compose` of 30-second motions in frames/s beside
single-clip sampling making as many frames, model load time, end-to-end
`odmo sample --n 20` wall time (a fresh process), peak RSS of `odmo sample --n 10000`, training
s/epoch and clips/s on HumanAct12 and CMU MoCap with the arithmetic they imply (GFLOP per clip,
GFLOP/s) beside this machine's float32 matrix-multiply rate, and the evaluation protocol's wall time.
Without a trained model the generator figures use a randomly initialised network of the same
shapes (speed does not depend on the weights) and say so. The networks run on one device
(`--device`; the report's machine names it): sampling, end to end, training, the matrix-multiply
rate and the evaluation all use it.
"""

from __future__ import annotations

import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from odmo_cli.device import describe, synchronize
from odmo_cli.errors import UserError


@dataclass
class Figure:
    name: str
    unit: str
    runs: list[float]
    note: str = ""

    def to_json(self) -> dict:
        return {"name": self.name, "unit": self.unit, "median": statistics.median(self.runs),
                "min": min(self.runs), "max": max(self.runs), "runs": len(self.runs), "note": self.note}


@dataclass
class BenchReport:
    machine: dict
    figures: list[Figure] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)


def machine(device: torch.device = torch.device("cpu")) -> dict:
    return {"device": describe(device), "cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(),
            "torch": torch.__version__, "threads": torch.get_num_threads(), "python": platform.python_version()}


def _timed(fn: Callable[[], object], runs: int, warmup: int = 1) -> list[float]:
    for _ in range(warmup):
        fn()
    out = []
    for _ in range(runs):
        t = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t)
    return out


def random_checkpoint(dataset: str, folder: Path) -> Path:
    """An untrained ODMO checkpoint with the dataset's shapes and a random latent bank."""
    from odmo_cli.data.manifest import load_manifest
    from odmo_cli.checkpoint import save_checkpoint
    from odmo_cli.models.latent import fit_modes
    from odmo_cli.models.odmo import ODMO, ODMOConfig

    m = load_manifest(dataset)
    cfg = ODMOConfig(n_joints=m.skeleton.n_joints, n_classes=len(m.actions), length=m.clip_length,
                     up_axis=m.skeleton.up_index)
    torch.manual_seed(0)
    model = ODMO(cfg)
    rng = np.random.default_rng(0)
    n = 40 * cfg.n_classes
    bank = {"codes": torch.from_numpy(rng.normal(size=(n, cfg.latent_dim)).astype(np.float32)),
            "labels": torch.arange(n) % cfg.n_classes, "end_points": torch.zeros(n, 3),
            "modes": torch.full((n,), -1), "names": [str(i) for i in range(n)]}
    path = folder / f"random_{dataset}.pt"
    save_checkpoint(path, {"format_version": 1, "kind": "odmo", "config": cfg.to_dict(),
                           "dataset": {"name": m.name, "actions": list(m.action_names), "skeleton": m.skeleton_name,
                                       "fps": m.fps, "length": m.clip_length, "up_axis": m.up_axis},
                           "state_dict": model.state_dict(), "latent_bank": bank,
                           "modes": fit_modes(bank, cfg.n_classes)})
    return path


def bench_sampling(model_path: Path, runs: int, note: str, device: torch.device) -> list[Figure]:
    from odmo_cli.checkpoint import load_odmo
    from odmo_cli.generation.generate import sample

    loads = _timed(lambda: load_odmo(model_path, device), runs)
    loaded = load_odmo(model_path, device)
    per = max(1, 1000 // len(loaded.actions))
    n = per * len(loaded.actions)
    times = _timed(lambda: sample(loaded, ["all"], per, seed=0), runs)
    return [Figure("model load", "s", loads, note),
            Figure(f"sampling throughput (n = {n}, T = {loaded.model.cfg.length})", "motions/s",
                   [n / t for t in times], note)]


COMPOSE_SECONDS = 30  # the composition `bench_composition` times
COMPOSE_SEQUENCES = 100  # side by side: composing is sequential in its windows, so its batch is the sequences


def bench_composition(model_path: Path, runs: int, note: str, device: torch.device) -> list[Figure]:
    """`odmo compose` after load: COMPOSE_SEQUENCES sequences of COMPOSE_SECONDS seconds, every action in
    turn for one model length each (cut at the end), in frames a second; beside it single-clip sampling
    making as many frames (`sample`, every action), and the ratio, run by run."""
    from odmo_cli.checkpoint import load_odmo
    from odmo_cli.generation.compose import compose
    from odmo_cli.generation.generate import sample

    loaded = load_odmo(model_path, device)
    fps, T = float(loaded.dataset["fps"]), loaded.model.cfg.length
    frames = int(round(COMPOSE_SECONDS * fps))
    parts, left = [], frames
    for i in range(-(-frames // T)):
        parts.append(f"{loaded.actions[i % len(loaded.actions)]} {min(T, left)}f")
        left -= T
    spec = ", ".join(parts)
    total = COMPOSE_SEQUENCES * frames
    per = -(-total // (T * len(loaded.actions)))  # clips per action making at least as many frames
    clips = per * len(loaded.actions) * T

    def composing() -> None:
        compose(loaded, spec, COMPOSE_SEQUENCES, seed=0)

    def sampling() -> None:
        sample(loaded, ["all"], per, seed=0)

    composing(), sampling()
    ours, single = [], []
    for _ in range(runs):  # interleaved, so that both see the same machine
        ours.append(total / _timed(composing, 1, warmup=0)[0])
        single.append(clips / _timed(sampling, 1, warmup=0)[0])
    name = f"{COMPOSE_SEQUENCES} compositions of {COMPOSE_SECONDS} s ({frames} frames, {len(parts)} segments)"
    return [Figure(f"`odmo compose` after load: {name}", "frames/s", ours, note),
            Figure(f"single-clip sampling, {clips} frames ({per} clips per action)", "frames/s", single, note),
            Figure("composing over single-clip sampling, per frame", "x", [a / b for a, b in zip(ours, single)],
                   "run by run; >= 1: composing is at least as fast per frame")]


PEER_SHAPES = {"humanact12": "humanact12", "cmu_mocap": "cmu"}  # bench_peer.py --dataset, by our dataset


def find_peer() -> Path | None:
    """The authors' networks' timer (shared/peer/bench_peer.py beside the repository), if present."""
    for root in (Path.cwd().parent, Path(__file__).resolve().parents[3]):
        path = root / "shared" / "peer" / "bench_peer.py"
        if path.is_file():
            return path
    return None


def peer_sampling_rate(peer: Path, n: int, dataset: str) -> float:
    """Motions/s of the authors' bare networks for n motions (one timed run after a warm-up), with
    this process's thread count; UserError if the script fails."""
    cmd = [sys.executable, str(peer), "--what", "sampling", "--n", str(n), "--runs", "1",
           "--threads", str(torch.get_num_threads()), "--dataset", PEER_SHAPES[dataset]]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    try:
        return float(json.loads(proc.stdout.strip().splitlines()[-1])["motions_per_s"])
    except (IndexError, KeyError, ValueError):
        last = (proc.stderr.strip().splitlines() or ["no output"])[-1]
        raise UserError(f"{peer} did not report a sampling rate (exit {proc.returncode}: {last})") from None


def bench_sample_command(model_path: Path, runs: int, note: str, folder: Path, peer: Path | None,
                         device: torch.device) -> list[Figure]:
    """What `odmo sample --action all --n N` does after loading (codes, end points, the networks,
    the file), N per action making at least 1000 motions; with `peer`, the authors' bare networks
    making as many motions, timed in the same run, interleaved run by run with ours."""
    from odmo_cli.checkpoint import load_model
    from odmo_cli.generation.generate import sample

    loaded = load_model(model_path, device)
    per = -(-1000 // len(loaded.actions))
    n = per * len(loaded.actions)
    out = folder / "all.npz"

    def ours() -> None:
        sample(loaded, ["all"], per, seed=0, lazy=True).save(out, "dataset", loaded)

    use_peer = peer is not None and loaded.dataset["name"] in PEER_SHAPES
    ours()
    mine, theirs = [], []
    for _ in range(runs):
        if use_peer:
            theirs.append(peer_sampling_rate(peer, n, loaded.dataset["name"]))
        start = time.perf_counter()
        ours()
        mine.append(n / (time.perf_counter() - start))
    figures = [Figure(f"`odmo sample --action all --n {per}` after load: codes, end points, networks, file",
                      "motions/s", mine, note)]
    if theirs:
        figures += [Figure(f"the authors' networks alone, {n} motions (bench_peer.py, same run)", "motions/s", theirs,
                           f"{peer}"),
                    Figure("`odmo sample` over the authors' networks", "x", [a / b for a, b in zip(mine, theirs)],
                           "run by run; >= 1: odmo delivers more motions per second")]
    return figures


def _cli(args: list[str]) -> list[str]:
    return [sys.executable, "-m", "odmo_cli", *args]


def bench_end_to_end(model_path: Path, runs: int, note: str, folder: Path, device: torch.device) -> list[Figure]:
    action = "--action"
    from odmo_cli.checkpoint import load_odmo

    first = load_odmo(model_path).actions[0]
    cmd = _cli(["sample", "--model", str(model_path), action, first, "--n", "20", "--out", str(folder / "e2e.npz"),
                "--device", str(device)])
    walls = _timed(lambda: subprocess.run(cmd, check=True, capture_output=True), runs)
    rss_cmd = [sys.executable, "-c",
               "import resource, subprocess, sys; subprocess.run(sys.argv[1:], check=True, capture_output=True);"
               "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)",
               *_cli(["sample", "--model", str(model_path), action, first, "--n", "10000",
                      "--out", str(folder / "big.npz"), "--device", str(device)])]
    rss = [int(subprocess.run(rss_cmd, check=True, capture_output=True, text=True).stdout.split()[-1]) / 1024
           for _ in range(max(1, runs // 2))]
    return [Figure("`odmo sample --n 20` end to end (fresh process)", "s", walls, note),
            Figure("peak RSS, `odmo sample --n 10000`", "MiB", rss, note)]


def _lstm_flops(lstm: torch.nn.LSTM, x: torch.Tensor) -> int:
    """Matrix-product FLOPs of an nn.LSTM's forward on x (B, T, I): per layer and step, the four
    gates' products with input and hidden state, 2 * 4H * (I + H) per sequence."""
    b, t = (x.shape[0], x.shape[1]) if lstm.batch_first else (x.shape[1], x.shape[0])
    h = lstm.hidden_size
    sizes = [lstm.input_size] + [h] * (lstm.num_layers - 1)
    return sum(2 * b * t * 4 * h * (i + h) for i in sizes)


def count_flops(fn: Callable[[], object], root: torch.nn.Module) -> int:
    """FLOPs of fn(), a forward and backward through root's modules, counted by torch's
    FlopCounterMode. That counter does not see nn.LSTM's fused CPU kernel: an nn.LSTM call during
    which it counted nothing adds its matrix products from its shapes, x3 for the backward (input
    and weight gradients), as the counter does for the layers it sees. For an LSTM whose input needs
    no gradient that overstates its first layer's backward (in ODMO: the encoder, under 1% of a step)."""
    from torch.utils.flop_counter import FlopCounterMode

    counter = FlopCounterMode(display=False)
    unseen, before = [0], {}

    def pre_hook(module, _):
        before[id(module)] = counter.get_total_flops()

    def hook(module, inputs, _):
        if counter.get_total_flops() == before.pop(id(module)):
            unseen[0] += 3 * _lstm_flops(module, inputs[0])

    lstms = [m for m in root.modules() if isinstance(m, torch.nn.LSTM)]
    handles = [m.register_forward_pre_hook(pre_hook) for m in lstms] + [m.register_forward_hook(hook) for m in lstms]
    try:
        with counter:
            fn()
    finally:
        for handle in handles:
            handle.remove()
    return counter.get_total_flops() + unseen[0]


def matmul_rate(runs: int, n: int = 2048, device: torch.device = torch.device("cpu")) -> list[float]:
    """GFLOP/s of an n x n float32 matrix product: what the device sustains at best."""
    a, b = torch.randn(n, n, device=device), torch.randn(n, n, device=device)

    def product() -> None:
        a @ b
        synchronize(device)

    return [2 * n ** 3 / t / 1e9 for t in _timed(product, runs)]


def bench_training(dataset: str, data, runs: int, device: torch.device = torch.device("cpu")) -> list[Figure]:
    from odmo_cli.data.locate import resolve
    from odmo_cli.data.readers import read_dataset
    from odmo_cli.training.distributed import Group
    from odmo_cli.training.odmo import ODMOTrainer, TrainConfig, model_config_for

    manifest, root = resolve(dataset, data)
    clips = read_dataset(root, manifest)
    tc = TrainConfig(epochs=runs + 1, batch_size=256, val_every=0, checkpoint_every=0, tf_start=0.65, tf_end=0.65)
    with tempfile.TemporaryDirectory() as tmp:
        trainer = ODMOTrainer(clips, model_config_for(clips), tc, Path(tmp) / "bench.pt", Group(device))
        flops = count_flops(trainer.train_epoch, trainer.model)  # the warm-up epoch, not timed
        seconds, rates = [], []
        for _ in range(runs):
            start = time.perf_counter()
            clips_seen = trainer.train_epoch()["clips"]
            synchronize(device)
            seconds.append(time.perf_counter() - start)
            rates.append(clips_seen / seconds[-1])
    note = f"{len(trainer.train_idx)} pairs per epoch, batch 256 pairs, teacher forcing 0.65 (mid-schedule)"
    per_clip = flops / (2 * len(trainer.train_idx)) / 1e9
    return [Figure(f"training s/epoch, {dataset} (T = {manifest.clip_length})", "s", seconds, note),
            Figure(f"training clips/s, {dataset}", "clips/s", rates, note),
            Figure(f"training GFLOP per clip (forward + backward), {dataset}", "GFLOP", [per_clip],
                   "matrix products counted in one epoch"),
            Figure(f"training arithmetic rate, {dataset}", "GFLOP/s", [flops / t / 1e9 for t in seconds], note)]


def bench_evaluation(model: str | None, data, runs: int, device: torch.device, peer: Path | None = None
                     ) -> list[Figure]:
    """The default protocol's wall time; with `peer`, beside it in the same run (interleaved) the time
    the authors' bare networks take to generate as many motions as the protocol generates: the
    host's speed varies between days, their ratio much less."""
    from odmo_cli.evaluation.protocol import EvalConfig, run_evaluation

    cfg = EvalConfig()
    times, theirs = [], []
    dataset = None
    for _ in range(runs):
        start = time.perf_counter()
        report = run_evaluation([model], None, data, None, cfg, device=device)
        times.append(time.perf_counter() - start)
        dataset = report.dataset
        if peer is not None and dataset in PEER_SHAPES:
            generated = cfg.repeats * report.rows[-1]["per_action"] * len(report.rows[-1]["by_action"])
            theirs.append(generated / peer_sampling_rate(peer, 1008, dataset))
    figures = [Figure(f"evaluation protocol, {dataset} (10 repeats, paper's samples per action)", "s", times)]
    if theirs:
        figures += [Figure(f"the authors' networks generating the protocol's {generated} motions (bench_peer.py "
                           "at n = 1008, same run)", "s", theirs, f"{peer}"),
                    Figure("evaluation protocol over the authors' networks' generation alone", "x",
                           [a / b for a, b in zip(times, theirs)],
                           "run by run; the protocol also classifies its real and generated sets and takes their statistics")]
    return figures


def run_bench(model: str | None = None, data=None, runs: int = 5, only: tuple[str, ...] = (),
              progress: Callable[[str], None] | None = None, peer: Path | None = None,
              device: torch.device = torch.device("cpu")) -> BenchReport:
    """Every figure asked for (`only`: some parts), measured with the networks on `device`."""
    from odmo_cli.checkpoint import checkpoint_path, shipped_file

    report = BenchReport(machine(device))
    want = lambda part: not only or part in only  # noqa: E731
    say = progress or (lambda _: None)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        path, note = None, ""
        if model:
            path = checkpoint_path(model)
        else:
            path = shipped_file("humanact12")
        if path is None:
            path, note = random_checkpoint("humanact12", folder), "untrained network, HumanAct12 shapes"
        if want("sampling"):
            say("sampling")
            report.figures += bench_sampling(path, runs, note, device)
            peer = peer or find_peer()
            if peer is None:
                report.skipped.append("the authors' networks: no shared/peer/bench_peer.py beside the repository (--peer)")
            try:
                report.figures += bench_sample_command(path, runs, note, folder, peer, device)
            except UserError as exc:
                report.skipped.append(f"the authors' networks: {exc}")
        if want("composition"):
            say("composition")
            report.figures += bench_composition(path, runs, note, device)
        if want("end-to-end"):
            say("end to end")
            report.figures += bench_end_to_end(path, runs, note, folder, device)
        if want("training"):
            say("matrix multiply")
            report.figures.append(Figure("float32 matrix multiply (2048 x 2048)", "GFLOP/s", matmul_rate(runs, device=device),
                                         "the device's practical peak for the training figures"))
            for dataset in ("humanact12", "cmu_mocap"):
                say(f"training {dataset}")
                try:
                    report.figures += bench_training(dataset, data, min(runs, 3), device)
                except UserError as exc:
                    report.skipped.append(f"training {dataset}: {exc}")
        if want("evaluation"):
            say("evaluation")
            try:
                report.figures += bench_evaluation(model, data, max(1, min(runs, 3)), device, peer or find_peer())
            except UserError as exc:
                report.skipped.append(f"evaluation: {exc}")
    return report
