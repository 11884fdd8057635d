"""The action classifier used for evaluation (Acc, FID, Diversity, Multimodality).

Architecture (ODMO supplement Tables 3/4, the same as Action2Motion's `MotionDiscriminator`):
a GRU over the frames, not batch-first, with parameter names `recurrent.*`; the output of the
last time step goes through `linear1` (hidden -> 30) and tanh, which is the 30-d *feature* that
FID, Diversity and Multimodality use; `linear2` (30 -> C) gives the class logits. HumanAct12 and
CMU MoCap use 2 GRU layers of 128 units, UESTC 3 layers of 256 (supplement Table S4).

Input: motions in the dataset's own frame and units after its manifest's scale, cropped to the
dataset's T with the first root at the origin (DESIGN.md), as a (B, T, J, 3) or (B, T, J*3) batch.

The initial GRU hidden state is **zeros**. Action2Motion draws it from N(0, 1) at every call
(`initHidden` uses `torch.randn`), which makes its metrics vary from run to run; zeros is that
distribution's mean and makes every feature a deterministic function of the motion. The released
weights load unchanged (same parameter names and shapes).

Training notes (threads=1, seed 0, 20% per-class held-out split, accuracy on the first T frames
of held-out clips, one run each, so +-1-2 points is noise): plain shuffling of one random crop per
clip reached 85-87% on HumanAct12 and 89% on CMU MoCap-7; mirroring, random playback speed and
length-proportional sampling lifted that to 90.3% (HumanAct12, 200 epochs, speed 2.0) and 90.8%
(CMU-7, 100 epochs, speed 1.3). Dropout, weight decay, input noise, rotation about the up axis and
larger batches or learning rates did not help, nor did label smoothing 0.1 (89.9%) or an
exponential moving average of the weights (decay 0.999 per step: 91.2%, two more clips right).
Most HumanAct12 errors come from subject P12 (about 56% held-out accuracy against 86-100% for
the others; its walks and runs are markedly slower per frame: P12's runs move the body 15 mm and
the root 20 mm per frame, other subjects' runs 23-35 and 18-37 mm, their walks 19-28 and 15-33 mm,
so P12's runs look like everyone else's walks).
Hand-made features with an RBF SVM reach about 91% on the same split.

Files `load_classifier` reads: an odmo classifier checkpoint (kind "classifier", written by
`train_classifier`), or an Action2Motion release file (a torch file holding a dict whose `model`
entry is the state dict; see `A2M_RELEASES`), or a bare state dict with the same names. All are
loaded with `torch.load(weights_only=True)`.
"""

from __future__ import annotations

import hashlib
import math
import time
import warnings
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from torch import nn

from odmo_cli.data.dataset import crop_pad_shift, random_start, split_indices
from odmo_cli.data.manifest import Manifest
from odmo_cli.data.readers import ClipSet
from odmo_cli.errors import UserError
from odmo_cli.io import load_checkpoint, save_checkpoint

FORMAT_VERSION = 1
FEATURE_DIM = 30  # Action2Motion's feature layer; the metrics are defined on it

# The classifiers released with Action2Motion (Guo et al., 2020), by file name. ODMO evaluates
# HumanAct12 with the released one; for CMU MoCap it drops Wash (7 classes) and trains its own.
A2M_RELEASES: dict[str, dict] = {
    "action_recognition_model_humanact12.tar": {
        "sha256": "e2d231fd8a425bc642d4c342466d5eaae2ae16e8a67e8dd253820ef5512d7bca",
        "dataset": "humanact12", "n_classes": 12, "input_size": 72, "hidden": 128, "layers": 2,
        "note": "classes in the order of the coarse action codes 01..12 (the humanact12 manifest's order)",
    },
    "action_recognition_model_mocap_new.tar": {
        "sha256": "7ef619637e61934a57254642021d065adf8afd59f56be7c39f205eea064aa154",
        "dataset": "cmu_mocap", "n_classes": 8, "input_size": 60, "hidden": 128, "layers": 2,
        "note": "8 classes including Wash, which ODMO drops: scored on ODMO's 7 by name (the Wash logit is left out)",
        # its label order (Action2Motion's label_enc_rev_mocap.txt), as manifest action names
        "classes": ["walk", "wash", "run", "jump", "animal_behavior", "dance", "step", "climb"],
    },
}


# -- configuration -------------------------------------------------------------------------------

@dataclass
class ClassifierConfig:
    input_size: int  # J * 3
    n_classes: int
    hidden: int = 128
    layers: int = 2
    feature: int = FEATURE_DIM

    def __post_init__(self):
        for name in ("input_size", "n_classes", "hidden", "layers", "feature"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value <= 0:
                raise UserError(f"classifier {name} must be a positive integer, got {value!r}")
            setattr(self, name, int(value))
        if self.input_size % 3:
            raise UserError(f"classifier input size must be joints x 3, got {self.input_size}")

    @property
    def n_joints(self) -> int:
        return self.input_size // 3

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "ClassifierConfig":
        known = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in known})


# Presets (supplement Tables 3 and 4): (GRU layers, hidden units).
A2M_PRESET = (2, 128)  # HumanAct12 and CMU MoCap, as in Action2Motion
UESTC_PRESET = (3, 256)  # ODMO's UESTC classifier


def config_for(manifest: Manifest, **overrides) -> ClassifierConfig:
    """The classifier of a dataset: UESTC -> 3 GRU layers of 256, otherwise 2 of 128."""
    layers, hidden = UESTC_PRESET if "uestc" in manifest.name.lower() else A2M_PRESET
    base = dict(input_size=3 * manifest.skeleton.n_joints, n_classes=len(manifest.actions),
                hidden=hidden, layers=layers)
    base.update({k: v for k, v in overrides.items() if v is not None})
    return ClassifierConfig.from_dict(base)


# -- the model -----------------------------------------------------------------------------------

class MotionClassifier(nn.Module):
    """GRU action classifier; `forward` gives logits, `features` the 30-d tanh feature."""

    def __init__(self, cfg: ClassifierConfig, dropout: float = 0.0):
        super().__init__()
        self.cfg = cfg
        # (T, B, D) as in A2M; `dropout` acts between GRU layers in training mode only (no parameters)
        self.recurrent = nn.GRU(cfg.input_size, cfg.hidden, cfg.layers, dropout=dropout if cfg.layers > 1 else 0.0)
        self.linear1 = nn.Linear(cfg.hidden, cfg.feature)
        self.linear2 = nn.Linear(cfg.feature, cfg.n_classes)
        self.info: dict = {}  # where the weights came from (set by load_classifier)
        self.keep: list[int] | None = None  # logits kept, in the dataset's action order (set by check_matches)

    def _frames(self, motion) -> torch.Tensor:
        """(B, T, J, 3) or (B, T, J*3) -> (T, B, J*3) float32, with a clear error on a shape mismatch."""
        motion = torch.as_tensor(motion)
        if motion.dim() == 4 and motion.shape[-1] == 3:
            motion = motion.reshape(motion.shape[0], motion.shape[1], -1)
        if motion.dim() != 3:
            raise UserError(f"classifier input must be (B, T, J, 3) or (B, T, J*3), got shape {tuple(motion.shape)}")
        if motion.shape[1] < 1:
            raise UserError("classifier input has no frames")
        if motion.shape[-1] != self.cfg.input_size:
            got = motion.shape[-1]
            joints = f" ({got // 3} joints)" if got % 3 == 0 else ""
            raise UserError(f"classifier expects {self.cfg.input_size} inputs per frame "
                            f"({self.cfg.n_joints} joints), got {got}{joints}")
        param = self.linear1.weight
        return motion.to(device=param.device, dtype=param.dtype).transpose(0, 1)

    def logits_and_features(self, motion) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, C) logits and (B, 30) features in [-1, 1]; the initial hidden state is zeros."""
        frames = self._frames(motion)
        h0 = frames.new_zeros(self.cfg.layers, frames.shape[1], self.cfg.hidden)
        out, _ = self.recurrent(frames, h0)
        feature = torch.tanh(self.linear1(out[-1]))
        logits = self.linear2(feature)
        return (logits if self.keep is None else logits[:, self.keep]), feature

    def forward(self, motion) -> torch.Tensor:
        return self.logits_and_features(motion)[0]

    def features(self, motion) -> torch.Tensor:
        return self.logits_and_features(motion)[1]

    @torch.no_grad()
    def predict(self, motions, batch: int = 1024) -> tuple[np.ndarray, np.ndarray]:
        """Logits (N, C) and features (N, 30) as float32 numpy, in eval mode, `batch` motions at a time."""
        if batch <= 0:
            raise UserError(f"batch size must be positive, got {batch}")
        was_training = self.training
        self.eval()
        try:
            motions = torch.as_tensor(np.asarray(motions) if not torch.is_tensor(motions) else motions)
            logits, feats = [], []
            for b in range(0, len(motions), batch):
                lo, fe = self.logits_and_features(motions[b:b + batch])
                logits.append(lo.cpu().float().numpy())
                feats.append(fe.cpu().float().numpy())
        finally:
            self.train(was_training)
        if not logits:
            return (np.zeros((0, self.cfg.n_classes), np.float32), np.zeros((0, self.cfg.feature), np.float32))
        return np.concatenate(logits), np.concatenate(feats)


# -- loading -------------------------------------------------------------------------------------

def file_sha256(path: str | Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def config_from_state_dict(state: dict, source: str = "state dict") -> ClassifierConfig:
    """Infer input size, hidden units, layers, feature size and classes from the tensor shapes."""
    need = ["recurrent.weight_ih_l0", "recurrent.weight_hh_l0", "linear1.weight", "linear2.weight"]
    missing = [k for k in need if k not in state]
    if missing:
        raise UserError(f"{source} is not a motion classifier: missing {', '.join(missing)} "
                        "(expected recurrent.*, linear1.*, linear2.* as in Action2Motion)")
    try:
        w_ih, w_hh = state["recurrent.weight_ih_l0"], state["recurrent.weight_hh_l0"]
        hidden = int(w_hh.shape[1])
        layers = 0
        while f"recurrent.weight_ih_l{layers}" in state:
            layers += 1
        feature, n_classes = int(state["linear1.weight"].shape[0]), int(state["linear2.weight"].shape[0])
        ok = (w_ih.dim() == 2 and w_ih.shape[0] == 3 * hidden and tuple(w_hh.shape) == (3 * hidden, hidden)
              and tuple(state["linear1.weight"].shape) == (feature, hidden)
              and tuple(state["linear2.weight"].shape) == (n_classes, feature))
    except (AttributeError, IndexError, TypeError):
        ok = False
    if not ok:
        raise UserError(f"{source}: tensor shapes are not those of a GRU classifier")
    return ClassifierConfig(input_size=int(w_ih.shape[1]), n_classes=n_classes, hidden=hidden,
                            layers=layers, feature=feature)


def _strip_prefix(state: dict) -> dict:
    """Drop a DataParallel `module.` prefix if every key has it."""
    if state and all(isinstance(k, str) and k.startswith("module.") for k in state):
        return {k[len("module."):]: v for k, v in state.items()}
    return dict(state)


def _is_state_dict(obj) -> bool:
    return isinstance(obj, dict) and bool(obj) and all(torch.is_tensor(v) for v in obj.values())


def load_classifier(path: str | Path, expect_classes: int | None = None, expect_input: int | None = None,
                    expect_actions: list[str] | tuple[str, ...] | None = None) -> MotionClassifier:
    """A classifier in eval mode from an odmo checkpoint or an Action2Motion release file.

    expect_input (J*3) and expect_classes are checked against the weights; a mismatch is a
    UserError naming both sides. expect_actions is checked against the action names an odmo
    checkpoint records (A2M files record none). The returned model's `info` says where it came
    from: `source` ("odmo", "a2m" or "state_dict"), `sha256`, `release` (the A2M release file the
    hash matches, or None), `verified` (hash matches a known release; None for odmo checkpoints),
    `dataset` (the dataset description, when known). An A2M file named like a release whose hash
    differs triggers a warning.
    """
    path = Path(path)
    payload = load_checkpoint(path)  # weights_only=True; UserError for missing/unreadable files
    info: dict = {"file": str(path)}
    if "kind" in payload:
        if payload["kind"] != "classifier":
            raise UserError(f"{path} is a {payload['kind']!r} checkpoint, not a classifier "
                            "(train one with train_classifier or use an Action2Motion classifier file)")
        try:
            cfg = ClassifierConfig.from_dict(payload["config"])
            state = payload["state_dict"]
        except (KeyError, TypeError):
            raise UserError(f"{path}: classifier checkpoint without config or state_dict") from None
        info.update(source="odmo", dataset=payload.get("dataset", {}), report=payload.get("report", {}),
                    format_version=payload.get("format_version"), verified=None, release=None)
        if isinstance(payload.get("split"), dict):  # clip indices it was trained / validated on
            info["split"] = {k: np.asarray(v, dtype=np.int64) for k, v in payload["split"].items()}
    else:
        if "model" in payload and _is_state_dict(payload["model"]):
            state, source = _strip_prefix(payload["model"]), "a2m"
        elif _is_state_dict(payload):
            state, source = _strip_prefix(payload), "state_dict"
        else:
            raise UserError(f"{path} is neither an odmo classifier checkpoint nor an Action2Motion "
                            "classifier file (a dict with the state dict under 'model')")
        cfg = config_from_state_dict(state, str(path))
        digest = file_sha256(path)
        release = next((name for name, r in A2M_RELEASES.items() if r["sha256"] == digest), None)
        info.update(source=source, sha256=digest, release=release, verified=release is not None,
                    dataset={"name": A2M_RELEASES[release]["dataset"]} if release else {})
        if release is None and path.name in A2M_RELEASES:
            warnings.warn(f"{path.name}: SHA-256 {digest[:12]}... does not match the Action2Motion release "
                          f"({A2M_RELEASES[path.name]['sha256'][:12]}...); using its weights as they are",
                          stacklevel=2)
    _check_expectations(cfg, expect_classes, expect_input)
    actions = info.get("dataset", {}).get("actions")
    if expect_actions is not None and actions is not None and list(actions) != list(expect_actions):
        raise UserError(f"classifier was trained on actions {', '.join(actions)}; "
                        f"the dataset has {', '.join(expect_actions)}")
    model = MotionClassifier(cfg)
    try:
        model.load_state_dict(state)
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()[0]
        raise UserError(f"{path}: weights do not fit the classifier ({first})") from None
    model.info = info
    return model.eval()


def _check_expectations(cfg: ClassifierConfig, expect_classes: int | None, expect_input: int | None) -> None:
    if expect_input is not None and int(expect_input) != cfg.input_size:
        joints = f"{expect_input // 3} joints" if expect_input % 3 == 0 else f"{expect_input} inputs per frame"
        raise UserError(f"classifier expects {cfg.input_size} inputs ({cfg.n_joints} joints), "
                        f"the dataset has {joints}")
    if expect_classes is not None and int(expect_classes) != cfg.n_classes:
        raise UserError(f"classifier has {cfg.n_classes} classes, the dataset has {expect_classes} actions")


def check_matches(model: MotionClassifier, manifest: Manifest) -> None:
    """UserError unless the classifier fits the dataset's skeleton and number of actions. An
    Action2Motion release whose classes include all of the dataset's (its MoCap file has Wash, which
    ODMO drops) is scored on those: its logits are taken in the dataset's action order."""
    release = A2M_RELEASES.get(model.info.get("release") or "", {})
    classes, actions = release.get("classes"), list(manifest.action_names)
    if classes and set(actions) <= set(classes) and len(classes) == model.cfg.n_classes:
        _check_expectations(model.cfg, None, 3 * manifest.skeleton.n_joints)
        model.keep = [classes.index(a) for a in actions]
        return
    _check_expectations(model.cfg, len(manifest.actions), 3 * manifest.skeleton.n_joints)


# -- training ------------------------------------------------------------------------------------

SAMPLINGS = ("shuffle", "balanced", "length")


@dataclass
class ClassifierTrainConfig:
    # Defaults: the settings of the measured HumanAct12 run (see the module's training notes).
    epochs: int = 200
    batch_size: int = 64
    lr: float = 1e-3
    lr_final: float = 1e-5  # cosine decay from lr to lr_final over the epochs; 0 keeps lr constant
    weight_decay: float = 0.0
    dropout: float = 0.0  # between GRU layers, training only
    rotate: float = 0.0  # augmentation: random rotation about the up axis, up to this many degrees
    mirror: bool = True  # augmentation: half the crops mirrored (left/right joints swapped)
    # augmentation: playback speed drawn log-uniformly in [1/speed, speed]; 1: off. Off by default:
    # a classifier that has learnt a slowed-down punch is still a punch cannot see damped motion.
    speed: float = 1.0
    noise: float = 0.0  # augmentation: std of Gaussian noise added to every coordinate (dataset units)
    val_fraction: float = 0.2
    # "shuffle": every training clip once per epoch; "length": every clip ceil(frames / T) times
    # (long clips give more crops); "balanced": as many draws as clips, classes equally likely
    sampling: str = "length"
    crop: str = "random"  # "random": a random T-frame crop of every clip each epoch; "start": the first T frames
    grad_clip: float = 1.0  # max gradient norm; 0 disables
    seed: int = 0
    threads: int = 0  # torch intra-op threads during training; 0 leaves torch's default
    hidden: int = 0  # 0: the dataset's preset (config_for)
    layers: int = 0

    def __post_init__(self):
        if self.epochs <= 0 or self.batch_size <= 0:
            raise UserError(f"epochs and batch size must be positive, got {self.epochs} and {self.batch_size}")
        if not self.lr > 0 or self.lr_final < 0:
            raise UserError(f"learning rate must be positive, got {self.lr} (final {self.lr_final})")
        if not 0 <= self.dropout < 1:
            raise UserError(f"dropout must be in [0, 1), got {self.dropout}")
        if not 1.0 <= self.speed <= 4.0:
            raise UserError(f"speed must be in [1, 4] (1: no change), got {self.speed}")
        if self.noise < 0:
            raise UserError(f"noise must not be negative, got {self.noise}")
        if not 0 <= self.rotate <= 180:
            raise UserError(f"rotate must be in [0, 180] degrees, got {self.rotate}")
        if self.weight_decay < 0:
            raise UserError(f"weight decay must not be negative, got {self.weight_decay}")
        if not 0 <= self.val_fraction < 1:
            raise UserError(f"validation fraction must be in [0, 1), got {self.val_fraction}")
        if self.sampling not in SAMPLINGS:
            raise UserError(f"unknown sampling {self.sampling!r}; valid: {', '.join(SAMPLINGS)}")
        if self.crop not in ("random", "start"):
            raise UserError(f"unknown crop {self.crop!r}; valid: random, start")
        if self.grad_clip < 0 or self.threads < 0 or self.hidden < 0 or self.layers < 0:
            raise UserError("grad_clip, threads, hidden and layers must not be negative")

    @classmethod
    def from_dict(cls, d: dict) -> "ClassifierTrainConfig":
        known = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in known})

    def learning_rate(self, epoch: int) -> float:
        """The rate of 0-based `epoch`: cosine from lr to lr_final, or constant lr."""
        from odmo_cli.train import cosine_rate

        return cosine_rate(self.lr, self.lr_final or self.lr, epoch, self.epochs)


def crop_batch(clips: ClipSet, idx: np.ndarray, length: int, rng: np.random.Generator | None = None,
               speed: float = 1.0) -> np.ndarray:
    """(len(idx), length, J, 3) float32: random crops when `rng` is given, else the first frames.

    speed > 1 (needs rng): each clip is replayed at a random speed in [1/speed, speed] (linear
    interpolation between frames) before its random crop.
    """
    out = np.empty((len(idx), length) + clips.motions[0].shape[1:], dtype=np.float32)
    for k, i in enumerate(idx):
        m = clips.motions[int(i)]
        if rng is not None and speed > 1.0:
            m = _resample(m, float(np.exp(rng.uniform(-np.log(speed), np.log(speed)))))
        start = random_start(len(m), length, rng) if rng is not None else 0
        out[k] = crop_pad_shift(m, length, start)
    return out


def _resample(motion: np.ndarray, rate: float) -> np.ndarray:
    """The clip played `rate` times as fast: frame t of the result is source time t * rate."""
    n = max(1, int((len(motion) - 1) / rate) + 1)
    t = np.minimum(np.arange(n) * rate, len(motion) - 1)
    i0 = np.floor(t).astype(np.int64)
    i1 = np.minimum(i0 + 1, len(motion) - 1)
    w = (t - i0).astype(np.float32)[:, None, None]
    return motion[i0] * (1 - w) + motion[i1] * w


def mirror_map(joint_names) -> list[int]:
    """Joint permutation swapping left_*/right_* (or *_a/*_b) partners; unpaired joints stay."""
    names = list(joint_names)
    swaps = (("left_", "right_"), ("right_", "left_"))
    perm = []
    for j, name in enumerate(names):
        partner = name
        for a, b in swaps:
            if name.startswith(a):
                partner = b + name[len(a):]
        for a, b in (("_a", "_b"), ("_b", "_a")):
            if name.endswith(a):
                partner = name[:-len(a)] + b
        perm.append(names.index(partner) if partner in names else j)
    return perm


def mirror_half(motions: np.ndarray, perm: list[int], axis: int, rng: np.random.Generator) -> np.ndarray:
    """Mirror a random half of (N, T, J, 3) motions: swap partner joints, negate `axis`."""
    flip = rng.random(len(motions)) < 0.5
    out = motions.copy()
    out[flip] = motions[flip][:, :, perm]
    out[flip, ..., axis] *= -1
    return out


def rotate_up(motions: np.ndarray, up_index: int, max_degrees: float, rng: np.random.Generator) -> np.ndarray:
    """Rotate each motion of (N, T, J, 3) about the up axis through the origin by a random angle."""
    if max_degrees <= 0:
        return motions
    angle = np.deg2rad(rng.uniform(-max_degrees, max_degrees, size=len(motions)))
    a, b = [i for i in range(3) if i != up_index]
    c, s = np.cos(angle)[:, None, None], np.sin(angle)[:, None, None]
    out = motions.copy()
    out[..., a] = c * motions[..., a] - s * motions[..., b]
    out[..., b] = s * motions[..., a] + c * motions[..., b]
    return out


def accuracy(model: MotionClassifier, motions: np.ndarray, labels: np.ndarray, batch: int = 1024) -> float:
    if len(labels) == 0:
        return float("nan")
    logits, _ = model.predict(motions, batch)
    return float((logits.argmax(1) == labels).mean())


def train_classifier(clips: ClipSet, tc: ClassifierTrainConfig, out: str | Path,
                     progress: Callable[[dict], None] | None = None) -> dict:
    """Train the dataset's classifier on real clips; write the checkpoint `out`; return the report.

    Split: `split_indices(clips, val_fraction, seed)` (per class, seeded). Each epoch takes one
    T-frame crop per training clip (random start, or the first frames with crop="start"), Adam
    and cross-entropy. Validation: the first T frames of every held-out clip (the canonical crop),
    plus one fixed seeded random crop of each. The final weights are kept (no selection on the
    validation set). The same seed gives the same weights. `progress` gets one dict per epoch.
    """
    if len(clips) == 0:
        raise UserError("no clips to train the classifier on")
    manifest = clips.manifest
    cfg = config_for(manifest, hidden=tc.hidden or None, layers=tc.layers or None)
    length = int(manifest.clip_length)
    train_idx, val_idx = split_indices(clips, tc.val_fraction, tc.seed)
    if len(train_idx) < 2:
        raise UserError(f"need at least 2 training clips, have {len(train_idx)}")
    out = Path(out)
    folder = out.parent if str(out.parent) else Path(".")
    if not folder.is_dir():  # fail before training, not after
        raise UserError(f"cannot write {out}: folder {folder} does not exist")
    old_threads = torch.get_num_threads()
    if tc.threads:
        torch.set_num_threads(tc.threads)
    try:
        torch.manual_seed(tc.seed)
        model = MotionClassifier(cfg, dropout=tc.dropout)
        opt = torch.optim.Adam(model.parameters(), lr=tc.lr, weight_decay=tc.weight_decay)
        rng = np.random.default_rng(tc.seed)
        labels = clips.labels
        val_x = crop_batch(clips, val_idx, length)
        val_y = labels[val_idx]
        val_x_rand = crop_batch(clips, val_idx, length, np.random.default_rng(tc.seed + 1))
        train_labels = labels[train_idx]
        skeleton = manifest.skeleton
        perm = mirror_map(skeleton.joint_names)
        n_crops = [max(1, math.ceil(len(clips.motions[i]) / length)) for i in train_idx]
        repeats = np.repeat(train_idx, n_crops)
        by_class = [train_idx[train_labels == c] for c in np.unique(train_labels)]
        history = []
        start_time = time.perf_counter()
        for epoch in range(1, tc.epochs + 1):
            t0 = time.perf_counter()
            model.train()
            for group in opt.param_groups:
                group["lr"] = tc.learning_rate(epoch - 1)
            if tc.sampling == "balanced":
                picks = rng.integers(0, len(by_class), size=len(train_idx))
                order = np.array([by_class[k][rng.integers(len(by_class[k]))] for k in picks], dtype=np.int64)
            elif tc.sampling == "length":
                order = repeats[rng.permutation(len(repeats))]
            else:
                order = train_idx[rng.permutation(len(train_idx))]
            x = crop_batch(clips, order, length, rng if tc.crop == "random" else None, tc.speed)
            x = rotate_up(x, skeleton.up_index, tc.rotate, rng)
            if tc.mirror:
                x = mirror_half(x, perm, skeleton.ground_axes[0], rng)
            if tc.noise > 0:
                x = x + rng.normal(0.0, tc.noise, size=x.shape).astype(np.float32)
            x = torch.from_numpy(x)
            y = torch.from_numpy(labels[order])
            loss_sum, correct = 0.0, 0
            for b in range(0, len(order), tc.batch_size):
                xb, yb = x[b:b + tc.batch_size], y[b:b + tc.batch_size]
                logits = model(xb)
                loss = nn.functional.cross_entropy(logits, yb)
                opt.zero_grad(set_to_none=True)
                loss.backward()
                if tc.grad_clip > 0:
                    nn.utils.clip_grad_norm_(model.parameters(), tc.grad_clip)
                opt.step()
                loss_sum += float(loss.detach()) * len(yb)
                correct += int((logits.detach().argmax(1) == yb).sum())
            log = {"epoch": epoch, "loss": loss_sum / len(order), "train_accuracy": correct / len(order),
                   "val_accuracy": accuracy(model, val_x, val_y), "seconds": time.perf_counter() - t0}
            history.append(log)
            if progress:
                progress(log)
        seconds = time.perf_counter() - start_time
        train_acc = accuracy(model, crop_batch(clips, train_idx, length), labels[train_idx])
        val_pred = model.predict(val_x)[0].argmax(1) if len(val_idx) else np.zeros(0, np.int64)
        per_class = {a: float((val_pred[val_y == k] == k).mean()) if (val_y == k).any() else float("nan")
                     for k, a in enumerate(manifest.action_names)}
        report = {
            "val_accuracy": float((val_pred == val_y).mean()) if len(val_idx) else float("nan"),
            "val_accuracy_random_crop": accuracy(model, val_x_rand, val_y),
            "val_balanced_accuracy": float(np.nanmean(list(per_class.values()))) if len(val_idx) else float("nan"),
            "val_per_class": per_class,
            "train_accuracy": train_acc,
            "epochs": tc.epochs, "seconds": seconds,
            "train_clips": int(len(train_idx)), "val_clips": int(len(val_idx)),
        }
        from odmo_cli.train import dataset_description  # the one definition shared by all checkpoints

        save_checkpoint(out, {
            "format_version": FORMAT_VERSION, "kind": "classifier", "config": cfg.to_dict(),
            "train_config": asdict(tc), "dataset": dataset_description(clips),
            "state_dict": model.state_dict(), "epoch": tc.epochs, "history": history, "report": report,
            "split": {"train": torch.from_numpy(train_idx), "val": torch.from_numpy(val_idx)},
        })
    finally:
        torch.set_num_threads(old_threads)
    return report
