"""Generation with a trained checkpoint: sample, interpolate, customise end points.

Everything here needs only the checkpoint (weights, latent bank, fitted mode mixtures), never
the dataset. Motions are decoded in batches, so memory stays flat in the number asked for.

ODMO checkpoints get the whole on-demand toolbox. Baselines (kinds in BASELINES) plug in through
their module's `model_from_checkpoint(ckpt) -> nn.Module`, whose model has `cfg.length`,
`cfg.n_joints` and `generate(labels (N,), generator) -> motions (N, T, J, 3)` (first root at the
origin); they are sampled from noise only, so modes and end points do not apply to them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from importlib import import_module, resources
from pathlib import Path

import numpy as np
import torch

from odmo_cli.data.manifest import canonical_name, normalize_action
from odmo_cli.errors import UserError
from odmo_cli.io import StreamedArray, load_checkpoint, save_npz
from odmo_cli.latent import ActionModes, fit_modes, knn_end_points, sample_codes
from odmo_cli.models.odmo import ODMO, ODMOConfig
from odmo_cli.ship import RECIPES, float_state, shipped_file
from odmo_cli.skeletons import get_skeleton

SAMPLING = ("mode-preserving", "conventional")
BASELINES = {"a2m": "odmo_cli.models.a2m", "dvgan": "odmo_cli.models.dvgan"}  # kind -> module


@dataclass
class LoadedODMO:
    model: ODMO
    dataset: dict  # name, actions, skeleton, fps, length, up_axis
    bank: dict
    modes: dict
    source: str

    @property
    def actions(self) -> list[str]:
        return list(self.dataset["actions"])

    def action_index(self, name: str) -> int:
        key = normalize_action(name)
        if key in self.actions:
            return self.actions.index(key)
        raise UserError(f"unknown action {name!r}; valid: {', '.join(self.actions)}, all")

    def action_modes(self, action: int, sampling: str = "mode-preserving") -> ActionModes:
        group = "actions" if sampling == "mode-preserving" else "conventional"
        return ActionModes.from_plain(self.modes[group][action])


@dataclass
class LoadedBaseline:
    """A baseline generator (Action2Motion, DVGAN): motions from noise, one action at a time."""

    model: torch.nn.Module
    kind: str
    dataset: dict
    source: str

    actions = LoadedODMO.actions
    action_index = LoadedODMO.action_index


def checkpoint_path(spec: str | Path | None) -> Path:
    """A shipped model's short name (humanact12, cmu; None: humanact12) or a path -> the file."""
    spec = str(spec or "humanact12")
    if Path(spec).is_file():
        return Path(spec)
    if canonical_name(spec) not in RECIPES:
        raise UserError(f"no model {spec!r}: give a checkpoint file or a shipped name (humanact12, cmu)")
    path = shipped_file(spec)
    if path is None:
        raise UserError(f"no shipped model {spec!r} in this install; give a checkpoint path instead")
    return path


def _checkpoint(spec: str | Path | None) -> tuple[Path, dict]:
    path = checkpoint_path(spec)
    return path, load_checkpoint(path)


def load_model(spec: str | Path | None) -> "LoadedODMO | LoadedBaseline":
    """Any generator checkpoint: ODMO or a baseline (see the module docstring)."""
    path, ckpt = _checkpoint(spec)
    kind = ckpt.get("kind")
    if kind == "odmo":
        return _odmo_from(path, ckpt)
    if kind not in BASELINES:
        raise UserError(f"{path} holds a {kind!r} model; generators are: odmo, {', '.join(BASELINES)}")
    model = import_module(BASELINES[kind]).model_from_checkpoint(ckpt)
    model.eval()
    return LoadedBaseline(model, kind, ckpt["dataset"], str(path))


def load_odmo(spec: str | Path | None) -> LoadedODMO:
    """A checkpoint path, or a shipped model's short name (humanact12, cmu); None: the default."""
    path, ckpt = _checkpoint(spec)
    if ckpt.get("kind") != "odmo":
        raise UserError(f"{path} holds a {ckpt.get('kind')!r} model; this command needs an ODMO checkpoint "
                        "(modes, latent codes and end points are ODMO's)")
    return _odmo_from(path, ckpt)


def _odmo_from(path: Path, ckpt: dict) -> LoadedODMO:
    if "latent_bank" not in ckpt:
        raise UserError(f"{path} has no latent bank: its training did not finish (resume it to the end)")
    model = ODMO(ODMOConfig.from_dict(ckpt["config"]))
    model.load_state_dict(float_state(ckpt))
    model.eval()
    modes = ckpt.get("modes") or fit_modes(ckpt["latent_bank"], model.cfg.n_classes)
    return LoadedODMO(model, ckpt["dataset"], ckpt["latent_bank"], modes, str(path))


@dataclass
class MotionBatch:
    """What `odmo sample` writes (DESIGN.md, Samples).

    With `lazy` sampling the motions are not decoded up front: `save` decodes and writes them
    batch by batch (memory flat in N) and keeps only the reached end points.
    """

    motions: np.ndarray | None  # (N, T, J, 3) float32; None until decoded when lazy
    actions: np.ndarray  # (N,) str
    modes: np.ndarray  # (N,) int, -1 when not mode-aware
    codes: np.ndarray  # (N, D)
    end_points: np.ndarray  # (N, 3) asked end points
    dataset: dict
    model: str
    seed: int
    end_axes: tuple[int, ...] = ()  # axes the user fixed, for dist_e
    extra: dict = field(default_factory=dict)
    labels: np.ndarray | None = None  # (N,) action indices, for lazy decoding
    loaded: "LoadedODMO | None" = None
    _reached: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.codes)

    @property
    def reached(self) -> np.ndarray:
        """(N, 3) root at the last frame."""
        if self.motions is not None:
            return self.motions[:, -1, 0]
        if self._reached is None:
            raise ValueError("motions not decoded yet: save() them first")
        return self._reached

    def dist_e(self) -> float | None:
        """Mean squared distance between asked and reached end points over the fixed axes."""
        if not self.end_axes:
            return None
        axes = list(self.end_axes)
        return float(np.mean(np.sum((self.end_points[:, axes] - self.reached[:, axes]) ** 2, axis=1)))

    def head(self, k: int) -> np.ndarray:
        """The first k motions, decoding them if needed."""
        if self.motions is not None:
            return self.motions[:k]
        return decode(self.loaded, self.codes[:k], self.labels[:k], self.end_points[:k])

    def _motion_blocks(self, batch: int = 1000):
        self._reached = np.empty((len(self), 3), dtype=np.float32)
        for b in range(0, len(self), batch):
            block = decode(self.loaded, self.codes[b:b + batch], self.labels[b:b + batch],
                           self.end_points[b:b + batch])
            self._reached[b:b + len(block)] = block[:, -1, 0]
            yield block

    def end_mask(self) -> np.ndarray:
        """(N, 3) bool: the end-point coordinates the user asked for (the others came from the
        nearest latent-bank clip, or are NaN for models that take no end point)."""
        mask = np.zeros((len(self), 3), dtype=bool)
        mask[:, list(self.end_axes)] = True
        return mask

    def save(self, path: str | Path, up: str = "dataset") -> None:
        """Write the samples file (docs/formats.md). up="y" turns positions and end points y-up
        (a proper rotation: left stays left); "dataset" keeps the dataset's own frame."""
        if up not in UP_CHOICES:
            raise UserError(f"unknown --up {up!r}; valid: {', '.join(UP_CHOICES)}")
        sk = get_skeleton(self.dataset["skeleton"])
        rot = sk.y_up_rotation().astype(np.float32) if up == "y" else np.eye(3, dtype=np.float32)
        motions = self.motions @ rot.T if self.motions is not None else None
        if motions is None:
            cfg = self.loaded.model.cfg
            blocks = (block @ rot.T for block in self._motion_blocks())
            motions = StreamedArray((len(self), cfg.length, cfg.n_joints, 3), np.float32, blocks)
        save_npz(path, motions=motions, actions=self.actions.astype(str), modes=self.modes,
                 codes=self.codes, end_points=self.end_points @ rot.T, end_mask=self.end_mask(),
                 fps=np.float32(self.dataset["fps"]), dataset=np.str_(self.dataset["name"]), skeleton=np.str_(sk.name),
                 joint_names=np.array(sk.joint_names), parents=np.array(sk.parents),
                 up_axis=np.str_("+y" if up == "y" else self.dataset["up_axis"]),
                 units=np.str_(self.dataset.get("units", "m")), format_version=np.int64(SAMPLES_FORMAT_VERSION),
                 model=np.str_(model_name(self.model)), seed=np.int64(self.seed), **self.extra)


SAMPLES_FORMAT_VERSION = 1  # the samples .npz (docs/formats.md); files without the key came before it
UP_CHOICES = ("dataset", "y")


def model_name(source: str | Path) -> str:
    """What a samples file records as its model: a shipped model's short name, else the file name
    (never a path of the machine that made it)."""
    path = Path(source)
    for short, recipe in (("humanact12", "humanact12"), ("cmu", "cmu_mocap")):
        shipped = shipped_file(recipe)
        if shipped is not None and path.resolve() == shipped.resolve():
            return short
    return path.name


@torch.inference_mode()
def decode(loaded: LoadedODMO, codes: np.ndarray, labels: np.ndarray, end_points: np.ndarray,
           batch: int = 1000) -> np.ndarray:
    """Codes (N, D), labels (N,), end points (N, 3) -> motions (N, T, J, 3), batch by batch."""
    cfg = loaded.model.cfg
    out = np.empty((len(codes), cfg.length, cfg.n_joints, 3), dtype=np.float32)
    for b in range(0, len(codes), batch):
        z = torch.from_numpy(np.ascontiguousarray(codes[b:b + batch], dtype=np.float32))
        lab = torch.from_numpy(np.asarray(labels[b:b + batch], dtype=np.int64))
        end = torch.from_numpy(np.ascontiguousarray(end_points[b:b + batch], dtype=np.float32))
        _, motion = loaded.model.decode(z, lab, end)
        out[b:b + batch] = motion.numpy()
    return out


def parse_point(text: str, up_axis: int, name: str = "--end") -> tuple[np.ndarray, tuple[int, ...]]:
    """'x,z' (ground plane) or 'x,y,z' -> (3-vector with NaN where not given, the axes given)."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) not in (2, 3) or not np.all(np.isfinite(values)):
        raise UserError(f"{name} must be two (ground plane) or three comma-separated numbers, got {text!r}")
    point = np.full(3, np.nan, dtype=np.float32)
    axes = tuple(i for i in range(3) if i != up_axis) if len(values) == 2 else (0, 1, 2)
    point[list(axes)] = values
    return point, axes


def _end_points(loaded: LoadedODMO, action: int, codes: np.ndarray, fixed: np.ndarray | None) -> np.ndarray:
    """KNN end points from the bank's codes of this action; user-fixed coordinates override them."""
    labels = loaded.bank["labels"].numpy()
    own = labels == action
    ends = knn_end_points(loaded.bank["codes"].numpy()[own], loaded.bank["end_points"].numpy()[own], codes)
    if fixed is not None:
        given = ~np.isnan(fixed)
        ends[:, given] = fixed[given]
    return ends


def sample(loaded: LoadedODMO, actions: list[str], n: int, seed: int = 0, mode: int | None = None,
           mode_weights: list[float] | None = None, sampling: str = "mode-preserving",
           end: str | None = None, end_from: str | None = None, end_to: str | None = None,
           steps: int = 10, lazy: bool = False) -> MotionBatch:
    """n motions per action. With end/end_from+end_to every motion is asked to end there.

    lazy: leave the motions undecoded; `MotionBatch.save` then decodes them while writing.
    """
    if n <= 0:
        raise UserError(f"--n must be a positive number of motions, got {n}")
    if sampling not in SAMPLING:
        raise UserError(f"unknown sampling {sampling!r}; valid: {', '.join(SAMPLING)}")
    if isinstance(loaded, LoadedBaseline):
        asked = {"--mode": mode is not None, "--mode-weights": mode_weights is not None,
                 "--sampling conventional": sampling == "conventional",
                 "--end/--end-from/--end-to": bool(end or end_from or end_to)}
        for flag, given in asked.items():
            if given:
                raise UserError(f"{flag} needs an ODMO model; {loaded.source} is a {loaded.kind} model "
                                "(it samples from noise only)")
        return sample_baseline(loaded, actions, n, seed)
    if mode_weights is not None and (any(w < 0 for w in mode_weights) or sum(mode_weights) <= 0):
        raise UserError("--mode-weights must be non-negative numbers with a positive sum")
    up = get_skeleton(loaded.dataset["skeleton"]).up_index
    targets, axes = _end_targets(end, end_from, end_to, steps, up)
    idx = list(range(len(loaded.actions))) if actions == ["all"] else [loaded.action_index(a) for a in actions]
    rng = np.random.default_rng(seed)
    parts = []
    for a in idx:
        modes = loaded.action_modes(a, sampling)
        k = len(modes.means)
        if mode is not None and not 0 <= mode < k:
            raise UserError(f"--mode {mode} is out of range: {loaded.actions[a]} has {k} modes (0..{k - 1})")
        if mode_weights is not None and len(mode_weights) != k:
            raise UserError(f"--mode-weights has {len(mode_weights)} values; {loaded.actions[a]} has {k} modes")
        codes, ids = sample_codes(modes, n, rng, mode, mode_weights)
        if sampling == "conventional":
            ids = np.full(n, -1)
        for target in targets:
            parts.append((a, codes, ids, _end_points(loaded, a, codes, target)))
    labels = np.concatenate([np.full(len(p[1]), p[0]) for p in parts])
    codes = np.concatenate([p[1] for p in parts])
    ends = np.concatenate([p[3] for p in parts])
    motions = None if lazy else decode(loaded, codes, labels, ends)
    return MotionBatch(motions, np.array(loaded.actions)[labels], np.concatenate([p[2] for p in parts]),
                       codes, ends, loaded.dataset, loaded.source, seed, axes, labels=labels, loaded=loaded)


@torch.inference_mode()
def sample_baseline(loaded: LoadedBaseline, actions: list[str], n: int, seed: int = 0,
                    batch: int = 1000) -> MotionBatch:
    """n motions per action from a baseline's noise, decoded in batches from one seeded generator."""
    idx = list(range(len(loaded.actions))) if actions == ["all"] else [loaded.action_index(a) for a in actions]
    labels = np.repeat(np.asarray(idx, dtype=np.int64), n)  # (N,)
    gen = torch.Generator().manual_seed(seed)
    cfg = loaded.model.cfg
    motions = np.empty((len(labels), cfg.length, cfg.n_joints, 3), dtype=np.float32)
    for b in range(0, len(labels), batch):
        motions[b:b + batch] = loaded.model.generate(torch.from_numpy(labels[b:b + batch]), gen).numpy()
    return MotionBatch(motions, np.array(loaded.actions)[labels], np.full(len(labels), -1),
                       np.zeros((len(labels), 0), dtype=np.float32), np.full((len(labels), 3), np.nan, np.float32),
                       loaded.dataset, loaded.source, seed, labels=labels, loaded=loaded)


def _end_targets(end, end_from, end_to, steps, up) -> tuple[list[np.ndarray | None], tuple[int, ...]]:
    if end is not None and (end_from or end_to):
        raise UserError("give either --end or --end-from/--end-to, not both")
    if end is not None:
        point, axes = parse_point(end, up)
        return [point], axes
    if end_from or end_to:
        if not (end_from and end_to):
            raise UserError("--end-from and --end-to go together")
        if steps < 2:
            raise UserError(f"--steps must be at least 2, got {steps}")
        a, axes = parse_point(end_from, up, "--end-from")
        b, axes_b = parse_point(end_to, up, "--end-to")
        if axes != axes_b:
            raise UserError("--end-from and --end-to must have the same number of coordinates")
        return [a + (b - a) * s for s in np.linspace(0, 1, steps, dtype=np.float32)], axes
    return [None], ()


def interpolate(loaded: LoadedODMO, action: str, steps: int = 8, from_mode: int | None = None,
                to_mode: int | None = None, from_code: int | None = None, to_code: int | None = None,
                end: str | None = None, seed: int = 0) -> MotionBatch:
    """One motion per step on the line between two modes' means (or two latent-bank codes)."""
    if steps < 2:
        raise UserError(f"--steps must be at least 2, got {steps}")
    a = loaded.action_index(action)
    if (from_mode is None) == (from_code is None) or (to_mode is None) == (to_code is None):
        raise UserError("give --from-mode or --from-code, and --to-mode or --to-code")
    modes = loaded.action_modes(a)
    bank = loaded.bank["codes"].numpy()

    def endpoint(mode, code, flag):
        if mode is not None:
            if not 0 <= mode < len(modes.means):
                raise UserError(f"{flag}-mode {mode} is out of range: {loaded.actions[a]} has "
                                f"{len(modes.means)} modes (0..{len(modes.means) - 1})")
            return modes.means[mode].astype(np.float32)
        if not 0 <= code < len(bank):
            raise UserError(f"{flag}-code {code} is out of range: the latent bank has {len(bank)} codes (0..{len(bank) - 1})")
        return bank[code]

    start, stop = endpoint(from_mode, from_code, "--from"), endpoint(to_mode, to_code, "--to")
    w = np.linspace(0, 1, steps, dtype=np.float32)[:, None]
    codes = (1 - w) * start + w * stop  # (steps, D)
    up = get_skeleton(loaded.dataset["skeleton"]).up_index
    fixed, axes = parse_point(end, up) if end else (None, ())
    ends = _end_points(loaded, a, codes, fixed)
    motions = decode(loaded, codes, np.full(steps, a), ends)
    return MotionBatch(motions, np.array([loaded.actions[a]] * steps), np.full(steps, -1), codes, ends,
                       loaded.dataset, loaded.source, seed, axes, extra={"weights": w[:, 0]},
                       labels=np.full(steps, a), loaded=loaded)


def refit_modes(loaded: LoadedODMO, seed: int = 0) -> None:
    """Refit the mode mixtures from the latent bank and save them into the checkpoint (atomically)."""
    from odmo_cli.io import save_checkpoint

    loaded.modes = fit_modes(loaded.bank, loaded.model.cfg.n_classes, seed)
    assets = Path(str(resources.files("odmo_cli") / "assets")).resolve()
    if Path(loaded.source).resolve().is_relative_to(assets):
        return  # never rewrite the shipped files; the refit serves this run only
    ckpt = load_checkpoint(loaded.source)
    ckpt["modes"] = loaded.modes
    save_checkpoint(loaded.source, ckpt)


def read_prefix(path: str | Path) -> np.ndarray:
    """A (T0, J, 3) motion from a .npy file, float32; UserError when it is not one."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"prefix not found: {path}")
    try:
        motion = np.load(path, allow_pickle=False)
    except Exception as exc:  # numpy raises several types for files that are not arrays
        raise UserError(f"cannot read prefix {path}: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}") from None
    if motion.ndim != 3 or motion.shape[2] != 3 or not np.issubdtype(motion.dtype, np.number):
        raise UserError(f"prefix {path} must be a (frames, joints, 3) array of numbers, got shape {motion.shape}")
    if not np.all(np.isfinite(motion)):
        raise UserError(f"prefix {path} holds NaN or infinite values")
    return motion.astype(np.float32)


@torch.inference_mode()
def complete(loaded: "LoadedODMO | LoadedBaseline", prefix: np.ndarray, frames: int, actions: list[str],
             n: int, seed: int = 0) -> MotionBatch:
    """n continuations per action of the first `frames` frames of `prefix` (T0, J, 3).

    The prefix is moved so its first root is at the origin (the models' frame); every output
    motion (T, J, 3) starts with exactly those frames. Only DVGAN-RNN models complete.
    """
    kind = loaded.kind if isinstance(loaded, LoadedBaseline) else "odmo"
    generator = getattr(loaded.model.cfg, "generator", "")
    if kind != "dvgan" or generator != "rnn":
        name = f"DVGAN-{generator.upper()}" if kind == "dvgan" else {"odmo": "ODMO"}.get(kind, kind)
        raise UserError(f"{loaded.source} is {name}, which does not complete; completion needs a DVGAN-RNN model "
                        "(odmo train --model dvgan --generator rnn)")
    cfg = loaded.model.cfg
    if n <= 0:
        raise UserError(f"--n must be a positive number of motions, got {n}")
    if not 1 <= frames < cfg.length:
        raise UserError(f"--frames must be between 1 and {cfg.length - 1} (the model makes {cfg.length} frames), got {frames}")
    if prefix.shape[1] != cfg.n_joints:
        raise UserError(f"the prefix has {prefix.shape[1]} joints; the model's skeleton "
                        f"{loaded.dataset['skeleton']} has {cfg.n_joints}")
    if len(prefix) < frames:
        raise UserError(f"the prefix has {len(prefix)} frames; --frames {frames} needs at least {frames}")
    given = prefix[:frames] - prefix[:1, :1]  # (frames, J, 3), first root at the origin
    idx = list(range(len(loaded.actions))) if actions == ["all"] else [loaded.action_index(a) for a in actions]
    labels = np.repeat(np.asarray(idx, dtype=np.int64), n)  # (N,)
    gen = torch.Generator().manual_seed(seed)
    start = torch.from_numpy(given)[None].expand(len(labels), -1, -1, -1)  # (N, frames, J, 3)
    motions = loaded.model.complete(start, torch.from_numpy(labels), gen).numpy()
    return MotionBatch(motions, np.array(loaded.actions)[labels], np.full(len(labels), -1),
                       np.zeros((len(labels), 0), dtype=np.float32), np.full((len(labels), 3), np.nan, np.float32),
                       loaded.dataset, loaded.source, seed, extra={"prefix_frames": np.int64(frames)},
                       labels=labels, loaded=loaded)
