"""Generation with a trained checkpoint: sample, interpolate, customise end points, complete.

Everything here needs only the checkpoint (weights, latent bank, fitted mode mixtures: loaded by
`checkpoint.load_model`), never the dataset. Motions are decoded in batches, so memory stays flat
in the number asked for.

ODMO checkpoints get the whole on-demand toolbox. Baselines (checkpoint.BASELINES) have
`cfg.length`, `cfg.n_joints` and `generate(labels (N,), generator) -> motions (N, T, J, 3)` (first
root at the origin); they are sampled from noise only, so modes and end points do not apply.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import numpy as np
import torch

from odmo_cli.checkpoint import SAMPLING, LoadedBaseline, LoadedODMO, load_checkpoint, save_checkpoint
from odmo_cli.device import generator, model_device
from odmo_cli.errors import UserError
from odmo_cli.generation.batch import MotionBatch, decode
from odmo_cli.geometry.skeletons import get_skeleton
from odmo_cli.models.latent import K_RULES, codes_and_ends, fit_modes, knn_end_points, sample_codes


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


def end_points_for(loaded: LoadedODMO, action: int, codes: np.ndarray, fixed: np.ndarray | None) -> np.ndarray:
    """KNN end points from the mixtures' codes of this action (loaded.mixture_bank); user-fixed
    coordinates override them."""
    bank = loaded.mixture_bank
    own = bank["labels"].numpy() == action
    ends = knn_end_points(bank["codes"].numpy()[own], bank["end_points"].numpy()[own], codes)
    if fixed is not None:
        given = ~np.isnan(fixed)
        ends[:, given] = fixed[given]
    return ends


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


def sample(loaded: LoadedODMO | LoadedBaseline, actions: list[str], n: int, seed: int = 0, mode: int | None = None,
           mode_weights: list[float] | None = None, sampling: str = "mode-preserving",
           end: str | None = None, end_from: str | None = None, end_to: str | None = None,
           steps: int = 10, lazy: bool = False) -> MotionBatch:
    """n motions per action (["all"]: every action). With end/end_from+end_to every motion is asked
    to end there. lazy: leave the motions undecoded; `MotionBatch.save` decodes them while writing."""
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
    rng = np.random.default_rng(seed)
    labels, codes, modes, ends = [], [], [], []
    for a in loaded.action_indices(actions):
        mixture = loaded.action_modes(a, sampling)
        k = len(mixture.means)
        if mode is not None and not 0 <= mode < k:
            raise UserError(f"--mode {mode} is out of range: {loaded.actions[a]} has {k} modes (0..{k - 1})")
        if mode_weights is not None and len(mode_weights) != k:
            raise UserError(f"--mode-weights has {len(mode_weights)} values; {loaded.actions[a]} has {k} modes")
        z, ids = sample_codes(mixture, n, rng, mode, mode_weights)
        if sampling == "conventional":
            ids = np.full(n, -1)
        for target in targets:
            labels.append(np.full(n, a))
            codes.append(z)
            modes.append(ids)
            ends.append(end_points_for(loaded, a, z, target))
    labels, codes, ends = np.concatenate(labels), np.concatenate(codes), np.concatenate(ends)
    motions = None if lazy else decode(loaded, codes, labels, ends)
    return MotionBatch(motions, np.array(loaded.actions)[labels], np.concatenate(modes), codes, ends,
                       loaded.dataset, loaded.source, seed, axes, labels=labels,
                       extra={"root": np.str_(loaded.model.cfg.root)})


@torch.inference_mode()
def sample_baseline(loaded: LoadedBaseline, actions: list[str], n: int, seed: int = 0,
                    batch: int = 1000) -> MotionBatch:
    """n motions per action from a baseline's noise, decoded in batches from one seeded generator."""
    labels = np.repeat(np.asarray(loaded.action_indices(actions), dtype=np.int64), n)  # (N,)
    dev = model_device(loaded.model)
    gen = generator(dev, seed)  # on a GPU its own stream: other motions than the CPU's for a seed
    cfg = loaded.model.cfg
    motions = np.empty((len(labels), cfg.length, cfg.n_joints, 3), dtype=np.float32)
    for b in range(0, len(labels), batch):
        motions[b:b + batch] = loaded.model.generate(torch.from_numpy(labels[b:b + batch]).to(dev), gen).cpu().numpy()
    return MotionBatch(motions, np.array(loaded.actions)[labels], np.full(len(labels), -1),
                       np.zeros((len(labels), 0), dtype=np.float32), np.full((len(labels), 3), np.nan, np.float32),
                       loaded.dataset, loaded.source, seed, labels=labels)


def interpolate(loaded: LoadedODMO, action: str, steps: int = 8, from_mode: int | None = None,
                to_mode: int | None = None, from_code: int | None = None, to_code: int | None = None,
                end: str | None = None, seed: int = 0) -> MotionBatch:
    """One motion per step on the line between two modes' means (or two latent-bank codes).

    With neither end given: the action's first two modes, or, for an action with one mode, its
    first and last latent-bank codes; the batch's `note` says which and how many modes there are.
    """
    if steps < 2:
        raise UserError(f"--steps must be at least 2, got {steps}")
    a = loaded.action_index(action)
    modes = loaded.action_modes(a)
    bank = loaded.bank["codes"].numpy()
    k, name, note = len(modes.means), loaded.actions[a], ""
    if (from_mode, to_mode, from_code, to_code) == (None, None, None, None):
        if k >= 2:
            from_mode, to_mode = 0, 1
            note = f"{name} has {k} modes; blending modes 0 and 1 (choose with --from-mode/--to-mode)"
        else:
            own = np.flatnonzero(loaded.bank["labels"].numpy() == a)
            from_code, to_code = int(own[0]), int(own[-1])
            note = (f"{name} has 1 mode; blending its first and last latent-bank codes, {from_code} and "
                    f"{to_code} (choose with --from-code/--to-code)")
    if (from_mode is None) == (from_code is None) or (to_mode is None) == (to_code is None):
        raise UserError("give --from-mode or --from-code, and --to-mode or --to-code (or none of them)")

    def endpoint(mode, code, flag):
        if mode is not None:
            if not 0 <= mode < k:
                raise UserError(f"{flag}-mode {mode} is out of range: {name} has {k} modes (0..{k - 1})")
            return modes.means[mode].astype(np.float32)
        if not 0 <= code < len(bank):
            raise UserError(f"{flag}-code {code} is out of range: the latent bank has {len(bank)} codes (0..{len(bank) - 1})")
        return bank[code]

    start, stop = endpoint(from_mode, from_code, "--from"), endpoint(to_mode, to_code, "--to")
    w = np.linspace(0, 1, steps, dtype=np.float32)[:, None]
    codes = (1 - w) * start + w * stop  # (steps, D)
    up = get_skeleton(loaded.dataset["skeleton"]).up_index
    fixed, axes = parse_point(end, up) if end else (None, ())
    ends = end_points_for(loaded, a, codes, fixed)
    motions = decode(loaded, codes, np.full(steps, a), ends)
    return MotionBatch(motions, np.array([name] * steps), np.full(steps, -1), codes, ends,
                       loaded.dataset, loaded.source, seed, axes,
                       extra={"weights": w[:, 0], "root": np.str_(loaded.model.cfg.root)},
                       labels=np.full(steps, a), note=note)


def refit_modes(loaded: LoadedODMO, seed: int = 0, crops: dict | None | bool = False, rule: str | None = None) -> None:
    """Refit the mode mixtures and save them into the checkpoint (atomically). `crops`: False keeps
    the file's mixture data (its crop bank, else its latent bank); None drops the crop bank and fits
    on one code per clip; a dict (crop_bank) becomes the file's crop bank. `rule`: how k is
    chosen (models.latent.K_RULES); None keeps the file's."""
    rule = rule or loaded.k_rule
    if rule not in K_RULES:
        raise UserError(f"unknown --k-rule {rule!r}; valid: {', '.join(K_RULES)}")
    if crops is not False:
        loaded.crops = crops
    loaded.set_modes(fit_modes(loaded.mixture_bank, loaded.model.cfg.n_classes, seed, rule))
    assets = Path(str(resources.files("odmo_cli") / "assets")).resolve()
    if Path(loaded.source).resolve().is_relative_to(assets):
        return  # never rewrite the shipped files; the refit serves this run only
    ckpt = load_checkpoint(loaded.source)
    ckpt["modes"] = loaded.modes
    ckpt.pop("crop_bank", None)
    if loaded.crops is not None:
        ckpt["crop_bank"] = loaded.crops
    save_checkpoint(loaded.source, ckpt)


MIXTURE_DATA = ("crops", "clips")  # `odmo modes --mixture-data`

# The authors' release fits each action's mode mixture, and finds the KNN end points, on the encoder
# means of random crops of the training clips: `num_itr` passes of its training loader, 2048 clips a
# pass drawn class-balanced (create_GMM in ensemble.py; num_itr in inference_odmo.py). The paper does
# not say which crops; one code per clip (the latent bank) sees only each clip's first T frames.
CROP_PASSES = {"humanact12": 15, "cmu_mocap": 5, "uestc": 8}  # the release's num_itr
DEFAULT_CROP_PASSES = 5
CROPS_PER_PASS = 2048


def crop_bank(model, clips, idx: np.ndarray, passes: int, rng: np.random.Generator,
              per_pass: int = CROPS_PER_PASS, batch: int = 512) -> dict:
    """Codes of `passes` x `per_pass` random crops of clips[idx] (a ClipSet), drawn class-balanced (every
    action equally often, clips uniformly within it) as the release's loader draws them; a crop drawn
    twice (same clip, same start) is kept once. Keys: codes, labels, end_points as the latent bank's; clip
    (the crop's position in idx, which is the latent bank's order when idx is its), start, passes."""
    from odmo_cli.data.dataset import crop_pad_shift, random_start

    if passes < 1:
        raise ValueError(f"passes must be at least 1, got {passes}")
    labels = clips.labels[idx]
    actions = np.unique(labels)
    T = model.cfg.length
    per_action = max(1, passes * per_pass // len(actions))
    pairs = set()  # (position in idx, start)
    for a in actions:
        for p in rng.choice(np.flatnonzero(labels == a), per_action):
            pairs.add((int(p), random_start(len(clips.motions[idx[p]]), T, rng)))
    pairs = sorted(pairs)
    codes, ends = codes_and_ends(model, (
        torch.stack([torch.from_numpy(crop_pad_shift(clips.motions[idx[p]], T, s)) for p, s in pairs[b:b + batch]])
        for b in range(0, len(pairs), batch)))
    return {"codes": codes,  # (M, D)
            "labels": torch.from_numpy(labels[[p for p, _ in pairs]].copy()),  # (M,)
            "end_points": ends,  # (M, 3)
            "clip": torch.tensor([p for p, _ in pairs], dtype=torch.int32),  # (M,)
            "start": torch.tensor([s for _, s in pairs], dtype=torch.int32),  # (M,)
            "passes": passes}


def mixture_data(loaded: LoadedODMO, kind: str, data: str | Path | None = None, seed: int = 0) -> dict | None:
    """What refit_modes' `crops` takes for --mixture-data: "crops", a crop bank of the file's training
    clips (its latent bank's names, read from the dataset: by name under `data`, or the motion folder
    `data` itself); "clips", None (one code per clip)."""
    from odmo_cli.data.locate import FOLDER_MANIFEST, resolve
    from odmo_cli.data.readers import read_dataset

    if kind not in MIXTURE_DATA:
        raise UserError(f"unknown --mixture-data {kind!r}; valid: {', '.join(MIXTURE_DATA)}")
    if kind == "clips":
        return None
    if data is not None and (Path(data) / FOLDER_MANIFEST).is_file():
        manifest, root = resolve(data)
    else:
        manifest, root = resolve(loaded.dataset["name"], data)
    clips = read_dataset(root, manifest)
    where = {name: i for i, name in enumerate(clips.names)}
    missing = [n for n in loaded.bank["names"] if n not in where]
    if missing:
        raise UserError(f"{len(missing)} of the model's training clips are not in the dataset given "
                        f"(first: {missing[0]}); pass the data it was trained on")
    idx = np.array([where[n] for n in loaded.bank["names"]], dtype=np.int64)
    passes = CROP_PASSES.get(clips.manifest.name, DEFAULT_CROP_PASSES)
    return crop_bank(loaded.model, clips, idx, passes, np.random.default_rng(seed + 50_000))


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
def complete(loaded: LoadedODMO | LoadedBaseline, prefix: np.ndarray, frames: int, actions: list[str],
             n: int, seed: int = 0) -> MotionBatch:
    """n continuations per action of the first `frames` frames of `prefix` (T0, J, 3).

    The prefix is moved so its first root is at the origin (the models' frame); every output
    motion (T, J, 3) starts with exactly those frames. Only DVGAN-RNN models complete.
    """
    kind = loaded.kind if isinstance(loaded, LoadedBaseline) else "odmo"
    net = getattr(loaded.model.cfg, "generator", "")  # DVGAN's generator network: cnn or rnn
    if kind != "dvgan" or net != "rnn":
        name = f"DVGAN-{net.upper()}" if kind == "dvgan" else {"odmo": "ODMO"}.get(kind, kind)
        raise UserError(f"{loaded.source} is {name}, which does not complete; completion needs a DVGAN-RNN model "
                        "(odmo train dvgan --generator rnn)")
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
    labels = np.repeat(np.asarray(loaded.action_indices(actions), dtype=np.int64), n)  # (N,)
    dev = model_device(loaded.model)
    gen = generator(dev, seed)
    start = torch.from_numpy(given)[None].expand(len(labels), -1, -1, -1).to(dev)  # (N, frames, J, 3)
    motions = loaded.model.complete(start, torch.from_numpy(labels).to(dev), gen).cpu().numpy()
    return MotionBatch(motions, np.array(loaded.actions)[labels], np.full(len(labels), -1),
                       np.zeros((len(labels), 0), dtype=np.float32), np.full((len(labels), 3), np.nan, np.float32),
                       loaded.dataset, loaded.source, seed, extra={"prefix_frames": np.int64(frames)},
                       labels=labels)
