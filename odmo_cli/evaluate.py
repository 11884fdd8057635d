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

from odmo_cli import metrics
from odmo_cli.data.dataset import crop_pad_shift, random_start
from odmo_cli.data.readers import ClipSet
from odmo_cli.errors import UserError
from odmo_cli.ship import shipped_file

DEFAULT_PER_ACTION = {"cmu_mocap": 400, "humanact12": 250, "uestc": 200}
METRICS = ("accuracy", "fid", "diversity", "multimodality", "inception", "n_apd", "bone_std")


@dataclass
class EvalConfig:
    repeats: int = 10
    per_action: int = 0  # 0: the paper's number for the dataset (250 HumanAct12, 400 CMU, 200 UESTC)
    sampling: str = "mode-preserving"
    seed: int = 0

    def n_for(self, dataset: str) -> int:
        return self.per_action or DEFAULT_PER_ACTION.get(dataset, 200)

    def __post_init__(self):
        if self.repeats <= 0 or self.per_action < 0:
            raise UserError(f"--repeats must be positive and --per-action non-negative, got {self.repeats}, {self.per_action}")


@dataclass
class RealSets:
    """Real crops: features, labels and per-set statistics for every repeat (+1 reference set)."""

    features: list[np.ndarray]  # repeats + 1 sets of (C*N, 30)
    labels: np.ndarray  # (C*N,)
    logits: list[np.ndarray]
    apd: np.ndarray  # (C,) per-action APD of the first real set
    bone_std: list[float]
    speed: list[np.ndarray]  # repeats + 1 sets of (C*N,) body speeds (metrics.body_speed)
    amplitude: list[np.ndarray]  # the same for metrics.body_amplitude


def shipped_classifier(dataset: str) -> Path | None:
    return shipped_file(dataset, "classifier_file")


def real_crops(clips: ClipSet, per_action: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """per_action random crops of random clips of every action: (C*N, T, J, 3), (C*N,)."""
    T = clips.manifest.clip_length
    motions, labels = [], []
    for c in range(len(clips.manifest.actions)):
        idx = rng.choice(np.flatnonzero(clips.labels == c), size=per_action, replace=True)
        for i in idx:
            m = clips.motions[i]
            motions.append(crop_pad_shift(m, T, random_start(len(m), T, rng)))
        labels += [c] * per_action
    return np.stack(motions), np.asarray(labels)


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


def evaluate_held_out(clips: ClipSet, val: np.ndarray, classifier, real: RealSets, cfg: EvalConfig) -> dict:
    """The protocol for crops of the classifier's held-out real clips, against the shared real sets."""
    rng = np.random.default_rng(cfg.seed + 40_000)
    held = replace(clips, motions=[clips.motions[i] for i in val], labels=clips.labels[val])
    n, parents = cfg.n_for(clips.manifest.name), clips.manifest.skeleton.parents
    rows = []
    for r in range(cfg.repeats):
        motions, labels = real_crops(held, n, rng)  # (C*n, T, J, 3)
        logits, feats = classifier.predict(motions)
        rows.append(set_metrics(logits, feats, labels, real.features[r + 1], motions, parents, real.apd, rng,
                                real=real))
    return {"name": "Real, classifier's held-out clips", "metrics": summarize(rows), "per_repeat": rows,
            "clips": int(len(val))}


def _apd_per_action(motions: np.ndarray, labels: np.ndarray, n_classes: int, cap: int = 250) -> np.ndarray:
    return np.array([metrics.apd(motions[labels == c][:cap]) for c in range(n_classes)])


def real_sets(clips: ClipSet, classifier, cfg: EvalConfig) -> RealSets:
    rng = np.random.default_rng(cfg.seed + 10_000)
    n = cfg.n_for(clips.manifest.name)
    parents = clips.manifest.skeleton.parents
    feats, logits, bone, apd, labels, speed, amplitude = [], [], [], None, None, [], []
    for r in range(cfg.repeats + 1):
        motions, labels = real_crops(clips, n, rng)
        lo, fe = classifier.predict(motions)
        feats.append(fe)
        logits.append(lo)
        bone.append(metrics.bone_length_consistency(motions, parents))
        speed.append(metrics.body_speed(motions))
        amplitude.append(metrics.body_amplitude(motions))
        if r == 0:
            apd = _apd_per_action(motions, labels, len(clips.manifest.actions))
    return RealSets(feats, labels, logits, apd, bone, speed, amplitude)


def damping_metrics(speed: np.ndarray, amplitude: np.ndarray, labels: np.ndarray, real: RealSets) -> dict[str, float]:
    """Speed and amplitude ratios against the first real set: overall (mean over actions) and
    per action ("speed/<index>", "amplitude/<index>"). An action whose real motions do not move
    about the root has no ratio (the key is absent), and with none left neither has the overall one."""
    out = {}
    for key, values, ref in (("speed", speed, real.speed[0]), ("amplitude", amplitude, real.amplitude[0])):
        ratios = {c: v for c, v in metrics.class_ratios(values, labels, ref, real.labels).items() if np.isfinite(v)}
        if ratios:
            out[key] = float(np.mean(list(ratios.values())))
        out.update({f"{key}/{c}": v for c, v in ratios.items()})
    return out


def set_metrics(logits: np.ndarray, feats: np.ndarray, labels: np.ndarray, real_feats: np.ndarray,
                motions: np.ndarray | None, parents, real_apd: np.ndarray, rng: np.random.Generator,
                bone_std: float | None = None, real: RealSets | None = None) -> dict[str, float]:
    pred = logits.argmax(axis=1)  # (N,)
    out = {
        "accuracy": 100 * metrics.accuracy(pred, labels),
        "fid": metrics.fid_from_features(real_feats, feats),
        "diversity": metrics.diversity(feats, 200, rng=rng),
        "multimodality": metrics.multimodality(feats, labels, 20, rng=rng),
        "inception": metrics.inception_score(_softmax(logits)),
    }
    per_class = metrics.accuracy_per_class(pred, labels, len(real_apd))  # (C,), NaN where absent
    out.update({f"accuracy/{c}": 100 * float(v) for c, v in enumerate(per_class) if np.isfinite(v)})
    if motions is not None:
        gen_apd = _apd_per_action(motions, labels, len(real_apd))
        out["n_apd"] = float(np.mean(gen_apd / real_apd))
        out["bone_std"] = metrics.bone_length_consistency(motions, parents)
        if real is not None:
            out.update(damping_metrics(metrics.body_speed(motions), metrics.body_amplitude(motions), labels, real))
    elif bone_std is not None:
        out["n_apd"] = 1.0
        out["bone_std"] = bone_std
    return out


def _softmax(logits: np.ndarray) -> np.ndarray:
    e = np.exp(logits - logits.max(1, keepdims=True))
    return e / e.sum(1, keepdims=True)


BY_ACTION = {"accuracy": "by_action", "speed": "speed_by_action", "amplitude": "amplitude_by_action"}


def split_by_action(row: dict, actions) -> None:
    """Move the per-action figures ("accuracy/<index>", "speed/<index>", "amplitude/<index>") of
    row["metrics"] and of each of row["per_repeat"] into dicts keyed by action name beside them:
    "by_action" (accuracy), "speed_by_action" and "amplitude_by_action"."""
    for part in [row] + row.get("per_repeat", []):
        values = part["metrics"] if part is row else part
        for metric, home in BY_ACTION.items():
            keys = [k for k in values if k.startswith(metric + "/")]
            part[home] = {actions[int(k.split("/")[1])]: values.pop(k) for k in keys}


def summarize(per_repeat: list[dict[str, float]]) -> dict[str, list[float]]:
    """metric -> [mean, 95% CI half-width] over repeats."""
    keys = per_repeat[0].keys()
    return {k: list(metrics.mean_ci95([r[k] for r in per_repeat])) for k in keys}


def evaluate_real(real: RealSets, cfg: EvalConfig, parents) -> dict:
    rng = np.random.default_rng(cfg.seed + 20_000)
    rows = [{**set_metrics(real.logits[r + 1], real.features[r + 1], real.labels, real.features[0], None,
                           parents, real.apd, rng, real.bone_std[r + 1]),
             **damping_metrics(real.speed[r + 1], real.amplitude[r + 1], real.labels, real)}
            for r in range(cfg.repeats)]
    return {"name": "Real motions", "metrics": summarize(rows), "per_repeat": rows}


def evaluate_model(loaded, classifier, real: RealSets, cfg: EvalConfig, progress=None) -> dict:
    """The protocol for one generator checkpoint (ODMO with cfg.sampling; baselines from noise)."""
    from odmo_cli.generate import LoadedODMO, sample

    rng = np.random.default_rng(cfg.seed + 30_000)
    n = cfg.n_for(loaded.dataset["name"])
    parents = _parents(loaded.dataset["skeleton"])
    rows, seeds, start = [], [], time.perf_counter()
    for r in range(cfg.repeats):
        seed = cfg.seed + r
        sampling = cfg.sampling if isinstance(loaded, LoadedODMO) else "mode-preserving"
        batch = sample(loaded, ["all"], n, seed=seed, sampling=sampling)
        labels = np.array([loaded.actions.index(a) for a in batch.actions])
        logits, feats = classifier.predict(batch.motions)
        rows.append(set_metrics(logits, feats, labels, real.features[r + 1], batch.motions, parents,
                                real.apd, rng, real=real))
        seeds.append(seed)
        if progress:
            progress(r + 1)
    conv = isinstance(loaded, LoadedODMO) and cfg.sampling != "mode-preserving"
    return {"name": Path(loaded.source).name + (f" ({cfg.sampling})" if conv else ""),
            "model": loaded.source, "metrics": summarize(rows), "per_repeat": rows, "seeds": seeds,
            "per_action": n, "seconds": time.perf_counter() - start}


def evaluate_samples(path: Path, classifier, real: RealSets, actions: list[str], cfg: EvalConfig,
                     parents) -> dict:
    """Motions produced elsewhere (a samples .npz) against the same real sets: one set, no CI."""
    from odmo_cli.io import read_samples

    data = read_samples(path)
    motions, names = data["motions"].astype(np.float32), [str(a) for a in data["actions"]]
    unknown = sorted(set(names) - set(actions))
    if unknown:
        raise UserError(f"samples {path} have actions {', '.join(unknown)} not in the dataset ({', '.join(actions)})")
    labels = np.array([actions.index(a) for a in names])
    logits, feats = classifier.predict(motions)
    row = set_metrics(logits, feats, labels, real.features[1], motions, parents, real.apd,
                      np.random.default_rng(cfg.seed), real=real)
    return {"name": path.name, "metrics": {k: [v, 0.0] for k, v in row.items()}, "per_repeat": [row]}


def _parents(skeleton: str):
    from odmo_cli.skeletons import get_skeleton

    return get_skeleton(skeleton).parents


@torch.inference_mode()
def customization(loaded, classifier, cfg: EvalConfig, codes_per_action: int = 40, n_ends: int = 10) -> dict:
    """ODMO §4.4: per action, codes_per_action codes x n_ends end points on the segment between
    two real end points of the class; accuracy and dist_e over `repeats` draws."""
    from odmo_cli.generate import decode
    from odmo_cli.latent import sample_codes

    rows = []
    bank_labels, bank_ends = loaded.bank["labels"].numpy(), loaded.bank["end_points"].numpy()
    for r in range(cfg.repeats):
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
        rows.append({"accuracy": 100 * metrics.accuracy(logits, labels),
                     "dist_e": metrics.dist_e(ends, motions[:, -1, 0])})
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
    from odmo_cli.generate import SAMPLING

    if spec and "@" in spec:
        path, _, sampling = spec.rpartition("@")
        if sampling not in SAMPLING:
            raise UserError(f"unknown sampling {sampling!r} in {spec!r}; valid: {', '.join(SAMPLING)}")
        return path, sampling
    return spec, None


def run_evaluation(models: list[str | None], dataset: str | None, data, classifier_path: str | None,
                   cfg: EvalConfig, samples: list[Path] = (), with_customization: bool = False,
                   progress=None, held_out: bool = False) -> Report:
    """Load everything once, compute real features once, evaluate every model (and samples file)."""
    from odmo_cli.data.locate import resolve
    from odmo_cli.data.readers import read_dataset
    from odmo_cli.generate import SAMPLING, LoadedODMO, load_model
    from odmo_cli.models.classifier import check_matches, load_classifier

    if cfg.sampling not in SAMPLING:
        raise UserError(f"unknown sampling {cfg.sampling!r}; valid: {', '.join(SAMPLING)}")
    start = time.perf_counter()
    specs = [model_spec(m) for m in (models or ([] if samples else [None]))]
    loaded = [load_model(path) for path, _ in specs]
    name = dataset or (loaded[0].dataset["name"] if loaded else None)
    if name is None:
        raise UserError("give --dataset with --samples")
    manifest, root = resolve(name, data)
    for m in loaded:
        if m.actions != list(manifest.action_names):
            raise UserError(f"{m.source} was trained on {m.dataset['name']} actions; the dataset is {manifest.name}")
    clf_path = classifier_path or shipped_classifier(manifest.name)
    if clf_path is None:
        raise UserError(f"no classifier for {manifest.name}: pass --classifier (e.g. one trained with "
                        f"`odmo train --model classifier --dataset {manifest.name}`)")
    classifier = load_classifier(clf_path)
    check_matches(classifier, manifest)
    torch.manual_seed(cfg.seed)
    clips = read_dataset(root, manifest)
    val = held_out_clips(classifier, clips) if held_out else None  # fail before the slow part
    real = real_sets(clips, classifier, cfg)
    report = Report(manifest.name, str(clf_path), {"repeats": cfg.repeats, "per_action": cfg.n_for(manifest.name),
                                                  "sampling": cfg.sampling, "seed": cfg.seed})
    report.rows.append(evaluate_real(real, cfg, manifest.skeleton.parents))
    if val is not None:
        report.rows.append(evaluate_held_out(clips, val, classifier, real, cfg))
    for m, (_, sampling) in zip(loaded, specs):
        own = replace(cfg, sampling=sampling or cfg.sampling)
        report.rows.append(evaluate_model(m, classifier, real, own, progress))
        if with_customization and isinstance(m, LoadedODMO):  # baselines take no end point
            report.customization.append({**customization(m, classifier, own), "name": report.rows[-1]["name"]})
    for path in samples:
        report.rows.append(evaluate_samples(Path(path), classifier, real, list(manifest.action_names), cfg,
                                            manifest.skeleton.parents))
    for row in report.rows:
        split_by_action(row, list(manifest.action_names))
    report.seconds = time.perf_counter() - start
    return report
