"""The evaluation protocol (ODMO §4.2, supplement §2.5; Action2Motion §4.2.1).

For each model: `repeats` sets of N generated motions per action; for each set, recognition
accuracy, FID against a real set of the same size, Diversity, Multimodality, n-APD and bone-length
consistency; reported as mean and 95% confidence half-width over the sets. Real motions get the
same treatment against an independent real set (the "Real motions" row). Real features are
computed once per evaluation and shared by every model compared. Every row also holds the accuracy
within each action (`by_action`), which an overall figure can hide.

With `held_out`, a second reference row scores crops of only the real clips the classifier was
validated on, never trained on, against the same real sets: what a generator whose motions are as
new to the classifier as unseen real ones, and otherwise real, would score. The "Real motions" row
draws mostly from the classifier's training clips, which it reads better than any new motion.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from odmo_cli.checkpoint import SAMPLING, LoadedODMO, load_model, shipped_file
from odmo_cli.data.dataset import crop_pad_shift, random_start
from odmo_cli.data.locate import resolve
from odmo_cli.data.manifest import available_manifests, load_manifest
from odmo_cli.data.readers import ClipSet, read_dataset
from odmo_cli.errors import UserError
from odmo_cli.evaluation import metrics
from odmo_cli.evaluation.classifier import check_matches, load_classifier
from odmo_cli.formats.samples import read_samples
from odmo_cli.generation.batch import decode
from odmo_cli.generation.generate import sample
from odmo_cli.geometry.skeletons import get_skeleton
from odmo_cli.measures import diagnostics, plausibility
from odmo_cli.models.latent import sample_codes
from odmo_cli.parallel import default_workers, parallel_map

DEFAULT_PER_ACTION = {"cmu_mocap": 400, "humanact12": 250, "uestc": 200}
APD_CAP = 250  # motions per action that n-APD compares (the first ones of each set)


@dataclass
class EvalConfig:
    repeats: int = 10
    per_action: int = 0  # 0: the paper's number for the dataset (250 HumanAct12, 400 CMU, 200 UESTC)
    sampling: str = "mode-preserving"
    seed: int = 0
    workers: int = 0  # sets evaluated side by side (0: one per core, at most 4); the numbers do not depend on it
    root: str | None = None  # ODMO's root readout (ODMOConfig.root) for every ODMO row; None: each file's own

    def n_for(self, dataset: str) -> int:
        return self.per_action or DEFAULT_PER_ACTION.get(dataset, 200)

    def __post_init__(self):
        if self.repeats <= 0 or self.per_action < 0:
            raise UserError(f"--repeats must be positive and --per-action non-negative, got {self.repeats}, {self.per_action}")

    @property
    def n_workers(self) -> int:
        return self.workers or default_workers()


@dataclass
class RealSets:
    """Real crops: features, labels and per-set statistics for every repeat (+1 reference set)."""

    features: list[np.ndarray]  # repeats + 1 sets of (C*N, 30)
    labels: np.ndarray  # (C*N,)
    logits: list[np.ndarray]
    apd: dict  # {action: APD} of the first real set (metrics.class_apd)
    bone_std: list[float]
    speed: list[np.ndarray]  # repeats + 1 sets of (C*N,) body speeds (diagnostics.body_speed)
    amplitude: list[np.ndarray]  # the same for diagnostics.body_amplitude
    plausible: list[dict] = field(default_factory=list)  # repeats + 1 sets of plausibility.measure
    frame: plausibility.Frame | None = None  # up axis, feet, fps and leg length (measured on the first set)
    scale: tuple | None = None  # the z-scoring of the kinetic features (plausibility.standardizer of the first set)


def shipped_classifier(dataset: str) -> Path | None:
    return shipped_file(dataset, "classifier")


def real_crops(clips: ClipSet, per_action: int, rng: np.random.Generator
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """per_action random crops of random clips of every action: (C*N, T, J, 3), (C*N,) and (C*N,)
    the frames of each crop that are its clip's (the rest copy its last frame)."""
    T = clips.manifest.clip_length
    motions, labels, own = [], [], []
    for c in range(len(clips.manifest.actions)):
        idx = rng.choice(np.flatnonzero(clips.labels == c), size=per_action, replace=True)
        for i in idx:
            m = clips.motions[i]
            start = random_start(len(m), T, rng)
            motions.append(crop_pad_shift(m, T, start))
            own.append(min(len(m) - start, T))
        labels += [c] * per_action
    return np.stack(motions), np.asarray(labels), np.asarray(own)


def held_out_clips(classifier, clips: ClipSet) -> np.ndarray:
    """Indices of the clips `classifier` was validated on (its checkpoint's split), checked against `clips`."""
    name = Path(classifier.info.get("file", "the classifier")).name
    split = classifier.info.get("split")
    if not split or len(split.get("val", ())) == 0:
        raise UserError(f"--held-out needs an odmo classifier checkpoint with a validation split; {name} has none")
    val = split["val"]
    total = len(split.get("train", ())) + len(val)
    if total != len(clips) or val.max() >= len(clips):
        raise UserError(f"--held-out: {name} was split over {total} clips, "
                        f"the dataset has {len(clips)}; use the copy of the data it was trained on")
    missing = [a for c, a in enumerate(clips.manifest.action_names) if not np.any(clips.labels[val] == c)]
    if missing:
        raise UserError(f"--held-out: {name} held out no clip of {', '.join(missing)}")
    return val


# -- one set of motions ----------------------------------------------------------------------------

@dataclass
class SetStats:
    """What the metrics need of one set of motions: the classifier's outputs and the statistics of
    the motions themselves (computed where the motions are, so the motions need not be kept)."""

    logits: np.ndarray  # (N, C)
    features: np.ndarray  # (N, 30)
    labels: np.ndarray  # (N,)
    bone_std: float
    speed: np.ndarray  # (N,)
    amplitude: np.ndarray  # (N,)
    apd: dict  # {action: APD} for the actions with at least 2 motions
    plausible: dict  # plausibility.measure of the motions


def set_stats(motions: np.ndarray, labels: np.ndarray, classifier, parents, frame: plausibility.Frame,
              with_apd: bool = True, own: np.ndarray | None = None) -> SetStats:
    """The statistics in float64 (metrics converts block by block); n-APD only `with_apd`. `own`: each
    motion's frames that are its clip's, for the plausibility measures (real crops; default all)."""
    logits, feats = classifier.predict(motions)
    speed, amplitude = diagnostics.body_speed_and_amplitude(motions)
    return SetStats(logits, feats, labels, metrics.bone_length_consistency(motions, parents), speed, amplitude,
                    metrics.class_apd(motions, labels, cap=APD_CAP) if with_apd else {},
                    plausibility.measure(motions, frame, parents, own))


def real_sets(clips: ClipSet, classifier, cfg: EvalConfig) -> RealSets:
    rng = np.random.default_rng(cfg.seed + 10_000)
    n = cfg.n_for(clips.manifest.name)
    parents = clips.manifest.skeleton.parents
    crops = [real_crops(clips, n, rng) for _ in range(cfg.repeats + 1)]  # drawn in order from one rng
    frame = plausibility.frame_for(clips.manifest.skeleton, clips.manifest.fps, crops[0][0])
    # n-APD compares generated sets with the first real set only
    stats = list(parallel_map(lambda r: set_stats(*crops[r][:2], classifier, parents, frame, with_apd=r == 0,
                                                  own=crops[r][2]),
                              range(len(crops)), cfg.n_workers))
    return RealSets([s.features for s in stats], crops[0][1], [s.logits for s in stats], stats[0].apd,
                    [s.bone_std for s in stats], [s.speed for s in stats], [s.amplitude for s in stats],
                    [s.plausible for s in stats], frame, plausibility.standardizer(stats[0].plausible["kinetic"]))


def damping_metrics(speed: np.ndarray, amplitude: np.ndarray, labels: np.ndarray, real: RealSets,
                    ref: int = 0) -> dict[str, float]:
    """Speed and amplitude ratios against real set `ref`: overall (mean over actions) and
    per action ("speed/<index>", "amplitude/<index>"). An action whose real motions do not move
    about the root has no ratio (the key is absent), and with none left neither has the overall one."""
    out = {}
    for key, values, ref in (("speed", speed, real.speed[ref]), ("amplitude", amplitude, real.amplitude[ref])):
        ratios = {c: v for c, v in diagnostics.class_ratios(values, labels, ref, real.labels).items() if np.isfinite(v)}
        if ratios:
            out[key] = float(np.mean(list(ratios.values())))
        out.update({f"{key}/{c}": v for c, v in ratios.items()})
    return out


def set_metrics(s: SetStats, real_feats: np.ndarray, rng: np.random.Generator, real: RealSets,
                generated: bool = True, ref: int = 0) -> dict[str, float]:
    """Every metric of one set against the real sets; `rng` draws the Diversity and Multimodality pairs.
    Speed, amplitude and the plausibility measures compare with real set `ref` (the one whose features
    are `real_feats`), as FID does.
    An action with too few motions for a per-action figure leaves its key out (see not_available)."""
    pred = s.logits.argmax(axis=1)  # (N,)
    pairs = len(s.labels) >= 2  # FID and Diversity need two motions
    out = {
        "accuracy": 100 * metrics.accuracy(pred, s.labels),
        "fid": metrics.fid_from_features(real_feats, s.features) if pairs else float("nan"),
        "diversity": metrics.diversity(s.features, 200, rng=rng) if pairs else float("nan"),
        "multimodality": _multimodality(s.features, s.labels, rng),
        "inception": metrics.inception_score(_softmax(s.logits)),
    }
    per_class = metrics.accuracy_per_class(pred, s.labels, int(real.labels.max()) + 1)  # (C,), NaN where absent
    out.update({f"accuracy/{c}": 100 * float(v) for c, v in enumerate(per_class) if np.isfinite(v)})
    out["n_apd"] = metrics.apd_ratio(s.apd, real.apd) if generated and s.apd else (1.0 if not generated else float("nan"))
    out["bone_std"] = s.bone_std
    out.update(damping_metrics(s.speed, s.amplitude, s.labels, real, ref))
    out.update(plausibility.compare(s.plausible, s.labels, real.plausible[ref], real.labels, real.scale))
    return out


def _multimodality(feats: np.ndarray, labels: np.ndarray, rng: np.random.Generator) -> float:
    if not any(np.count_nonzero(labels == c) >= 2 for c in np.unique(labels)):
        return float("nan")  # no action has two motions (see not_available)
    return metrics.multimodality(feats, labels, 20, rng=rng)


def not_available(labels: np.ndarray, actions: list[str]) -> list[str]:
    """Why a set's per-action figures are missing: actions with no motion, or with one."""
    counts = np.bincount(labels, minlength=len(actions))
    none = [a for a, k in zip(actions, counts) if k == 0]
    one = [a for a, k in zip(actions, counts) if k == 1]
    notes = []
    if none:
        notes.append(f"no motions of {', '.join(none)}: no accuracy, speed or amplitude for them; "
                     "they are left out of n-APD and Multimodality")
    if one:
        notes.append(f"one motion of {', '.join(one)}: n-APD and Multimodality need two, so these "
                     "actions are left out of them")
    if len(one) + len(none) == len(actions):
        notes.append("no action has two motions: n-APD and Multimodality are not available")
    if len(labels) < 2:
        notes.append("one motion in all: FID and Diversity need two")
    return notes


def _softmax(logits: np.ndarray) -> np.ndarray:
    e = np.exp(logits - logits.max(1, keepdims=True))
    return e / e.sum(1, keepdims=True)


BY_ACTION = {"accuracy": "by_action", "speed": "speed_by_action", "amplitude": "amplitude_by_action",
             **{k: f"{k}_by_action" for k in plausibility.PER_ACTION}}


def split_by_action(row: dict, actions) -> None:
    """Move the per-action figures ("accuracy/<index>", "speed/<index>", ...) of row["metrics"] and of
    each of row["per_repeat"] into dicts keyed by action name beside them: "by_action" (accuracy),
    "<metric>_by_action" for the others (BY_ACTION)."""
    for part in [row] + row.get("per_repeat", []):
        values = part["metrics"] if part is row else part
        for metric, home in BY_ACTION.items():
            keys = [k for k in values if k.startswith(metric + "/")]
            part[home] = {actions[int(k.split("/")[1])]: values.pop(k) for k in keys}


def summarize(per_repeat: list[dict[str, float]]) -> dict[str, list[float]]:
    """metric -> [mean, 95% CI half-width] over repeats (of the repeats that have it)."""
    keys = dict.fromkeys(k for r in per_repeat for k in r)
    return {k: list(metrics.mean_ci95([r[k] for r in per_repeat if k in r])) for k in keys}


# -- rows --------------------------------------------------------------------------------------------

def evaluate_real(real: RealSets, cfg: EvalConfig) -> dict:
    rng = np.random.default_rng(cfg.seed + 20_000)
    rows = []
    for r in range(cfg.repeats):
        s = SetStats(real.logits[r + 1], real.features[r + 1], real.labels, real.bone_std[r + 1],
                     real.speed[r + 1], real.amplitude[r + 1], {}, real.plausible[r + 1])
        rows.append(set_metrics(s, real.features[0], rng, real, generated=False))
    return {"name": "Real motions", "metrics": summarize(rows), "per_repeat": rows}


def evaluate_held_out(clips: ClipSet, val: np.ndarray, classifier, real: RealSets, cfg: EvalConfig) -> dict:
    """The protocol for crops of the classifier's held-out real clips, against the shared real sets."""
    rng = np.random.default_rng(cfg.seed + 40_000)
    held = replace(clips, motions=[clips.motions[i] for i in val], labels=clips.labels[val])
    n, parents = cfg.n_for(clips.manifest.name), clips.manifest.skeleton.parents
    rows = []
    for r in range(cfg.repeats):  # in order: the crops of set r + 1 are drawn after set r's metrics
        motions, labels, own = real_crops(held, n, rng)  # (C*n, T, J, 3), (C*n,), (C*n,)
        stats = set_stats(motions, labels, classifier, parents, real.frame, own=own)
        rows.append(set_metrics(stats, real.features[r + 1], rng, real, ref=r + 1))
    return {"name": "Real, classifier's held-out clips", "metrics": summarize(rows), "per_repeat": rows,
            "clips": int(len(val))}


def evaluate_model(loaded, classifier, real: RealSets, cfg: EvalConfig, progress=None) -> dict:
    """The protocol for one generator checkpoint (ODMO with cfg.sampling; baselines from noise):
    the sets are generated and read side by side (cfg.workers), their metrics taken in order."""
    rng = np.random.default_rng(cfg.seed + 30_000)
    n = cfg.n_for(loaded.dataset["name"])
    parents = get_skeleton(loaded.dataset["skeleton"]).parents
    sampling = cfg.sampling if isinstance(loaded, LoadedODMO) else "mode-preserving"
    seeds = [cfg.seed + r for r in range(cfg.repeats)]

    def one_set(seed: int) -> SetStats:
        batch = sample(loaded, ["all"], n, seed=seed, sampling=sampling)
        return set_stats(batch.motions, batch.labels, classifier, parents, real.frame)

    rows, start = [], time.perf_counter()
    for r, stats in enumerate(parallel_map(one_set, seeds, cfg.n_workers)):
        rows.append(set_metrics(stats, real.features[r + 1], rng, real, ref=r + 1))
        if progress:
            progress(r + 1)
    conv = isinstance(loaded, LoadedODMO) and cfg.sampling != "mode-preserving"
    return {"name": Path(loaded.source).name + (f" ({cfg.sampling})" if conv else ""),
            "model": loaded.source, "metrics": summarize(rows), "per_repeat": rows, "seeds": seeds,
            "per_action": n, "seconds": time.perf_counter() - start}


def read_samples_for(path: Path, classifier, manifest) -> tuple[np.ndarray, np.ndarray]:
    """A samples file's motions (N, T, J, 3) and action indices, checked against the dataset and
    its classifier: skeleton, joints, frames, actions, finite values. UserError naming the mismatch."""
    data = read_samples(path, optional=("dataset",))
    motions, names = data["motions"].astype(np.float32), [str(a) for a in data["actions"]]
    if data["skeleton"] != manifest.skeleton_name:
        raise UserError(f"samples {path.name} have skeleton {data['skeleton']}; {manifest.name} has "
                        f"{manifest.skeleton_name}")
    if motions.ndim != 4 or motions.shape[-1] != 3 or len(motions) == 0:
        raise UserError(f"samples {path.name}: motions must be (N, frames, joints, 3) with N >= 1, got {motions.shape}")
    joints = classifier.cfg.n_joints
    if motions.shape[2] != joints:
        raise UserError(f"samples {path.name} have {motions.shape[2]} joints; the classifier reads {joints}")
    if motions.shape[1] != manifest.clip_length:
        raise UserError(f"samples {path.name} have {motions.shape[1]} frames; {manifest.name}'s protocol (and "
                        f"its classifier) reads {manifest.clip_length}-frame motions")
    bad = np.flatnonzero(~np.isfinite(motions).all(axis=(1, 2, 3)))
    if len(bad):
        raise UserError(f"samples {path.name} hold NaN or infinite values ({len(bad)} motions, the first: {bad[0]})")
    actions = list(manifest.action_names)
    unknown = sorted(set(names) - set(actions))
    if unknown:
        raise UserError(f"samples {path.name} have actions {', '.join(unknown)} not in {manifest.name} "
                        f"({', '.join(actions)})")
    return motions, np.array([actions.index(a) for a in names])


def evaluate_samples(path: Path, classifier, real: RealSets, manifest, cfg: EvalConfig) -> dict:
    """Motions produced elsewhere (a samples .npz) against the same real sets: one set, no CI.
    Figures an action has too few motions for are left out and said why (`not_available`)."""
    motions, labels = read_samples_for(path, classifier, manifest)
    stats = set_stats(motions, labels, classifier, manifest.skeleton.parents, real.frame)
    row = set_metrics(stats, real.features[1], np.random.default_rng(cfg.seed), real, ref=1)
    return {"name": path.name, "metrics": {k: [v, 0.0] for k, v in row.items()}, "per_repeat": [row],
            "not_available": not_available(labels, list(manifest.action_names))}


@torch.inference_mode()
def customization(loaded, classifier, cfg: EvalConfig, codes_per_action: int = 40, n_ends: int = 10) -> dict:
    """ODMO §4.4: per action, codes_per_action codes x n_ends end points on the segment between
    two real end points of the class; accuracy and dist_e over `repeats` draws."""
    bank_labels, bank_ends = loaded.bank["labels"].numpy(), loaded.bank["end_points"].numpy()

    def one_draw(r: int) -> dict:
        rng = np.random.default_rng(cfg.seed + 40_000 + r)
        codes, labels, ends = [], [], []
        for a in range(len(loaded.actions)):
            own = np.flatnonzero(bank_labels == a)
            e0, e1 = bank_ends[rng.choice(own, 2, replace=len(own) < 2)]
            z, _ = sample_codes(loaded.action_modes(a, cfg.sampling), codes_per_action, rng)
            for w in np.linspace(0, 1, n_ends):
                codes.append(z)
                labels.append(np.full(codes_per_action, a))
                ends.append(np.repeat(((1 - w) * e0 + w * e1)[None], codes_per_action, 0))
        codes, labels, ends = np.concatenate(codes), np.concatenate(labels), np.concatenate(ends).astype(np.float32)
        motions = decode(loaded, codes, labels, ends)
        logits, _ = classifier.predict(motions)
        return {"accuracy": 100 * metrics.accuracy(logits, labels), "dist_e": metrics.dist_e(ends, motions[:, -1, 0])}

    rows = list(parallel_map(one_draw, range(cfg.repeats), cfg.n_workers))
    return {"name": Path(loaded.source).name, "metrics": summarize(rows), "per_repeat": rows}


@dataclass
class Report:
    dataset: str
    classifier: str
    config: dict
    rows: list[dict] = field(default_factory=list)
    customization: list[dict] = field(default_factory=list)
    seconds: float = 0.0


def model_spec(spec: str | None) -> tuple[str | None, str | None]:
    """'odmo.pt@conventional' -> ('odmo.pt', 'conventional'): one model's row with its own sampling."""
    if spec and "@" in spec:
        path, _, sampling = spec.rpartition("@")
        if sampling not in SAMPLING:
            raise UserError(f"unknown sampling {sampling!r} in {spec!r}; valid: {', '.join(SAMPLING)}")
        return path, sampling
    return spec, None


def samples_dataset(path: Path) -> str:
    """The dataset a samples file was made for: its `dataset` entry, else the dataset of its skeleton."""
    data = read_samples(path, keys=(), optional=("dataset",))
    if data["dataset"] is not None:
        return str(data["dataset"])
    named = [m for m in available_manifests() if load_manifest(m).skeleton_name == data["skeleton"]]
    if not named:
        raise UserError(f"samples {path.name} have skeleton {data['skeleton']}, which no known dataset has; "
                        "give --dataset")
    return named[0]


def run_evaluation(models: list[str | None], dataset: str | None, data, classifier_path: str | None,
                   cfg: EvalConfig, samples: list[Path] = (), with_customization: bool = False,
                   progress=None, held_out: bool = False, device: torch.device | None = None) -> Report:
    """Load everything once, compute real features once, evaluate every model (and samples file);
    the networks (generators and classifier) run on `device` (None: the CPU)."""
    if cfg.sampling not in SAMPLING:
        raise UserError(f"unknown sampling {cfg.sampling!r}; valid: {', '.join(SAMPLING)}")
    start = time.perf_counter()
    specs = [model_spec(m) for m in (models or ([] if samples else [None]))]
    loaded = [load_model(path, device) for path, _ in specs]
    for m in loaded:
        if cfg.root is not None and isinstance(m, LoadedODMO):  # baselines have no trajectory generator
            m.set_root(cfg.root)
    name = dataset or (loaded[0].dataset["name"] if loaded else samples_dataset(Path(samples[0])))
    manifest, root = resolve(name, data)
    for m in loaded:
        if m.actions != list(manifest.action_names):
            raise UserError(f"{m.source} was trained on {m.dataset['name']} actions; the dataset is {manifest.name}")
    clf_path = classifier_path or shipped_classifier(manifest.name)
    if clf_path is None:
        raise UserError(f"no classifier for {manifest.name}: pass --classifier (e.g. one trained with "
                        f"`odmo train classifier --dataset {manifest.name}`)")
    classifier = load_classifier(clf_path)
    if device is not None:
        classifier.to(device)
    check_matches(classifier, manifest)
    for path in samples:  # every samples file is checked before the slow part
        read_samples_for(Path(path), classifier, manifest)
    torch.manual_seed(cfg.seed)
    clips = read_dataset(root, manifest)
    val = held_out_clips(classifier, clips) if held_out else None  # fail before the slow part
    real = real_sets(clips, classifier, cfg)
    report = Report(manifest.name, str(clf_path), {"repeats": cfg.repeats, "per_action": cfg.n_for(manifest.name),
                                                  "sampling": cfg.sampling, "seed": cfg.seed,
                                                  "root": cfg.root})
    report.rows.append(evaluate_real(real, cfg))
    if val is not None:
        report.rows.append(evaluate_held_out(clips, val, classifier, real, cfg))
    for m, (_, sampling) in zip(loaded, specs):
        own = replace(cfg, sampling=sampling or cfg.sampling)
        report.rows.append(evaluate_model(m, classifier, real, own, progress))
        if with_customization and isinstance(m, LoadedODMO):  # baselines take no end point
            report.customization.append({**customization(m, classifier, own), "name": report.rows[-1]["name"]})
    for path in samples:
        report.rows.append(evaluate_samples(Path(path), classifier, real, manifest, cfg))
    for row in report.rows:
        split_by_action(row, list(manifest.action_names))
    report.seconds = time.perf_counter() - start
    return report
