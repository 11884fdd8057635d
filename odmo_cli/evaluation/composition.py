"""How good a composition (`odmo compose`) is: each segment its action, seams that do not show.

    python -m odmo_cli.evaluation.composition --model humanact12 [--classifier FILE] [--out report.json]

For a model, one spec per action, each of `segments` segments of T + one transition frames (T: the
model's clip length), so that every action comes once at every place and after different actions
(`specs`); `sequences` sequences of each, composed by priming ("primed") and by the cut-and-paste
baseline ("paste"), the same seeds. Measured (docs/generation.md, "Long motions", gives the numbers):

- accuracy: the evaluation classifier's reading of the window of T frames inside each segment that
  starts right after its transition, turned back by the yaw that placed it and moved to the origin, as
  a clip is read; `accuracy_from_start`, of the segment's first T frames, its transition inside; beside
  them, single-action sampling's accuracy for the same actions (`sample`, as many motions per action).
- seams: per frame, the largest joint speed and acceleration over the joints (units/s, units/s^2).
  The share of frames within one transition of a segment boundary over the 99th percentile of the same
  per-frame figures in every real clip of the dataset (real clips: 1% by definition), and the same share
  over the rest of the composition (the model's own rate).
- transition windows (one transition either side of each boundary): foot skating and the root's
  ground and vertical speed (plausibility), beside the same on as long windows of real clips and of
  single-action samples.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict, dataclass, replace

import numpy as np
import torch

from odmo_cli.measures import plausibility
from odmo_cli.checkpoint import load_odmo
from odmo_cli.errors import UserError
from odmo_cli.generation.compose import ComposeConfig, Composition, compose
from odmo_cli.generation.generate import sample
from odmo_cli.generation.seam import turn
from odmo_cli.geometry.skeletons import get_skeleton


@dataclass
class CompositionEvalConfig:
    sequences: int = 10  # per spec
    segments: int = 3  # per spec
    segment_frames: int = 0  # each segment's length; 0: the model's T plus one transition, so one window of T
    # frames fits inside it after its transition
    seed: int = 0
    real_windows: int = 4000  # random real windows of one transition's length either side


def specs(n_actions: int, segments: int, rng: np.random.Generator) -> list[list[int]]:
    """n_actions specs of `segments` actions: spec i's segment j is (i + offset_j) mod n_actions, the
    offsets distinct and drawn at random (the first 0), so every action comes once at every place."""
    if segments > n_actions:
        raise UserError(f"{segments} segments need at least as many actions; the model has {n_actions}")
    offsets = np.concatenate([[0], 1 + rng.choice(n_actions - 1, size=segments - 1, replace=False)])
    return [[(i + o) % n_actions for o in offsets] for i in range(n_actions)]


def peaks(motions: np.ndarray, fps: float) -> tuple[np.ndarray, np.ndarray]:
    """Per frame, the largest joint speed and acceleration over the joints: motions (N, T, J, 3) ->
    (N, T) each; speed from the step into the frame, acceleration about it (NaN where undefined)."""
    v = np.linalg.norm(np.diff(motions, axis=1), axis=-1).max(-1) * fps  # (N, T-1)
    a = np.linalg.norm(np.diff(motions, n=2, axis=1), axis=-1).max(-1) * fps * fps  # (N, T-2)
    pad = np.full((len(motions), 1), np.nan)
    return np.concatenate([pad, v], axis=1), np.concatenate([pad, a, pad], axis=1)


def real_peaks(clips, fps: float) -> tuple[float, float]:
    """The 99th percentiles of `peaks` over every frame of every real clip."""
    speed, accel = [], []
    for m in clips.motions:
        if len(m) >= 3:
            s, a = peaks(np.asarray(m, dtype=np.float64)[None], fps)
            speed.append(s[0, 1:])
            accel.append(a[0, 1:-1])
    return float(np.percentile(np.concatenate(speed), 99)), float(np.percentile(np.concatenate(accel), 99))


def segment_windows(c: Composition, T: int, transition: int | None) -> tuple[np.ndarray, np.ndarray]:
    """Windows of T frames inside each segment, turned back by the yaw that placed their first frame and
    moved so their first root is at the origin: (W, T, J, 3) and each one's segment index (W,). With a
    transition, the windows starting right after it and ending at the segment's end; with None, the
    segment's first T frames (its transition inside)."""
    windows, which = [], []
    up = get_skeleton(c.dataset["skeleton"]).up_index
    for s, (a, b) in enumerate(c.segments):
        starts = {a} if transition is None else {min(a + transition, b - T), b - T}
        for first in sorted(starts):
            if first < a:
                continue
            w = c.motions[:, first:first + T]  # (K, T, J, 3)
            rot = turn(torch.from_numpy(c.yaw[:, first]).double(), up).numpy()  # (K, 3, 3) model -> world
            w = np.einsum("ktjc,kcd->ktjd", w - w[:, :1, :1], rot)  # back to the model's frame: x R
            windows.append(w)
            which += [s] * len(w)
    return np.concatenate(windows).astype(np.float32), np.asarray(which)


def seam_frames(c: Composition, transition: int) -> np.ndarray:
    """(L,) bool: the frames within one transition of a boundary between two segments."""
    mask = np.zeros(c.motions.shape[1], dtype=bool)
    for b in c.segments[1:, 0]:
        mask[max(b - transition, 0):b + transition] = True
    return mask


def transition_windows(c: Composition, transition: int) -> np.ndarray:
    """(K * boundaries, 2 transition, J, 3): the frames one transition either side of each boundary."""
    return np.concatenate([c.motions[:, b - transition:b + transition] for b in c.segments[1:, 0]])


def random_windows(motions: list[np.ndarray], length: int, n: int, rng: np.random.Generator) -> np.ndarray:
    """n random windows of `length` frames of the motions (those long enough), first root at the origin."""
    long = [m for m in motions if len(m) >= length]
    pick = rng.integers(0, len(long), size=n)
    out = []
    for i in pick:
        start = rng.integers(0, len(long[i]) - length + 1)
        w = np.asarray(long[i][start:start + length], dtype=np.float32)
        out.append(w - w[:1, :1])
    return np.stack(out)


def window_measures(windows: np.ndarray, frame: plausibility.Frame) -> dict[str, float]:
    _, steps, skate = plausibility.foot_contacts(windows, frame)
    up, ground = plausibility.root_speeds(windows, frame)
    return {"foot_skate": plausibility.share(skate, steps), "root_ground": float(np.mean(ground)),
            "root_up": float(np.mean(up))}


def measure(model: str | None = None, data=None, classifier: str | None = None,
            cfg: CompositionEvalConfig | None = None, progress=print, compose_cfg: ComposeConfig | None = None) -> dict:
    """The report (module docstring) for one model: primed and paste beside single-action sampling."""
    from odmo_cli.data.locate import resolve
    from odmo_cli.data.readers import read_dataset
    from odmo_cli.evaluation.classifier import check_matches, load_classifier
    from odmo_cli.evaluation.protocol import shipped_classifier

    cfg = cfg or CompositionEvalConfig()
    started = time.perf_counter()
    loaded = load_odmo(model)
    manifest, root = resolve(loaded.dataset["name"], data)
    clf = load_classifier(classifier or shipped_classifier(manifest.name))
    check_matches(clf, manifest)
    clips = read_dataset(root, manifest)
    fps, T = float(loaded.dataset["fps"]), loaded.model.cfg.length
    compose_cfg = compose_cfg or ComposeConfig()
    transition = compose_cfg.blend
    frame = plausibility.frame_for(manifest.skeleton, fps, random_windows(clips.motions, T, 500,
                                                                           np.random.default_rng(cfg.seed)))
    rng = np.random.default_rng(cfg.seed)
    plans = specs(len(loaded.actions), cfg.segments, rng)
    seg_len = cfg.segment_frames or T + transition
    if seg_len < T + transition:
        raise UserError(f"segments of {seg_len} frames leave no window of {T} frames after the transition ({transition})")
    speed99, accel99 = real_peaks(clips, fps)
    report = {"model": loaded.source, "dataset": manifest.name, "classifier": str(classifier or "shipped"),
              "config": asdict(cfg), "compose": asdict(compose_cfg), "transition_frames": transition,
              "segment_frames": seg_len, "real_speed_p99": speed99, "real_accel_p99": accel99, "specs": [],
              "methods": {}}
    real_windows = random_windows(clips.motions, 2 * transition, cfg.real_windows, rng)
    report["real_windows"] = window_measures(real_windows, frame)
    n_single = None
    for method in ("primed", "paste"):
        hits, counts, seam, rest, trans, at_start = {}, {}, [], [], [], []
        for i, actions in enumerate(plans):
            spec = ", ".join(f"{loaded.actions[a]} {seg_len}f" for a in actions)
            if method == "primed":
                report["specs"].append(spec)
            c = compose(loaded, spec, cfg.sequences, seed=cfg.seed + i, cfg=replace(compose_cfg, method=method))
            windows, which = segment_windows(c, T, transition)
            logits, _ = clf.predict(windows)
            truth = np.array([actions[s] for s in which])
            for a, ok in zip(truth, logits.argmax(1) == truth):
                hits[a] = hits.get(a, 0) + int(ok)
                counts[a] = counts.get(a, 0) + 1
            windows, which = segment_windows(c, T, None)
            truth = np.array([actions[s] for s in which])
            at_start.append(clf.predict(windows)[0].argmax(1) == truth)
            s, acc = peaks(c.motions.astype(np.float64), fps)
            mask = seam_frames(c, transition)
            seam.append(np.stack([s[:, mask].ravel(), acc[:, mask].ravel()]))
            rest.append(np.stack([s[:, ~mask].ravel(), acc[:, ~mask].ravel()]))
            trans.append(transition_windows(c, transition))
        n_single = n_single or max(counts.values())
        seam, rest = np.concatenate(seam, axis=1), np.concatenate(rest, axis=1)
        over = lambda x, p: float(np.mean(x[np.isfinite(x)] > p))  # noqa: E731
        report["methods"][method] = {
            "accuracy": float(sum(hits.values()) / sum(counts.values())),
            "accuracy_by_action": {loaded.actions[a]: hits[a] / counts[a] for a in sorted(counts)},
            "windows": int(sum(counts.values())),
            "accuracy_from_start": float(np.concatenate(at_start).mean()),
            "seam_speed_over_p99": over(seam[0], speed99), "seam_accel_over_p99": over(seam[1], accel99),
            "rest_speed_over_p99": over(rest[0], speed99), "rest_accel_over_p99": over(rest[1], accel99),
            "seam_speed_max_over_p99": float(np.nanmax(seam[0]) / speed99),
            "seam_accel_max_over_p99": float(np.nanmax(seam[1]) / accel99),
            "transition_windows": window_measures(np.concatenate(trans), frame),
        }
        progress(f"{manifest.name} {method}: {time.perf_counter() - started:.0f} s")
    single = sample(loaded, ["all"], n_single, seed=cfg.seed)
    logits, _ = clf.predict(single.motions)
    ok = logits.argmax(1) == single.labels
    report["single"] = {"accuracy": float(ok.mean()), "accuracy_by_action": {
        loaded.actions[a]: float(ok[single.labels == a].mean()) for a in range(len(loaded.actions))},
        "motions": int(len(ok))}
    s, acc = peaks(single.motions.astype(np.float64), fps)
    report["single"]["speed_over_p99"] = float(np.mean(s[:, 1:] > speed99))
    report["single"]["accel_over_p99"] = float(np.mean(acc[:, 1:-1] > accel99))
    report["single"]["windows"] = window_measures(
        random_windows(list(single.motions), 2 * transition, cfg.real_windows, rng), frame)
    report["seconds"] = time.perf_counter() - started
    return report


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default=None, help="checkpoint or shipped name (default humanact12)")
    parser.add_argument("--data", default=None, help="data root (else $ODMO_DATA_DIR)")
    parser.add_argument("--classifier", default=None, help="classifier file (default: the shipped one)")
    parser.add_argument("--sequences", type=int, default=CompositionEvalConfig.sequences)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=None, help="also write the report as JSON here")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    try:
        report = measure(args.model, args.data, args.classifier,
                         CompositionEvalConfig(sequences=args.sequences, seed=args.seed),
                         progress=lambda s: print(s, file=sys.stderr))
    except UserError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    text = json.dumps(report, indent=2)
    if args.out:
        from odmo_cli.io import atomic_path

        with atomic_path(args.out) as tmp:
            tmp.write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
