"""The checkpoint format: one `.pt` file per model, holding only tensors and plain values.

Every checkpoint odmo writes is a dict (docs/formats.md, "Checkpoints"):
    format_version  FORMAT_VERSION; a file from a newer odmo is refused with a clear message
    kind            odmo | a2m | dvgan | classifier
    config          the model's config (`Config.to_dict`), train_config the training's
    dataset         dataset_description(clips): what the model was trained on
    state_dict      the weights (float32; shipped files: float16 and int8 rows, see float_state)
    optimizer*, epoch, rng, split, history   training state, for an exact resume
    latent_bank, crop_bank, modes (ODMO), report   what training measured at the end
It is written atomically and read with torch.load(weights_only=True): no pickled classes, so a
file from anyone is safe to open.

Here too: the table of shipped files and their short names (`--model humanact12`, `--model cmu`),
and `load_model`, which turns any generator checkpoint into a ready model.
"""

from __future__ import annotations

import copy
import zipfile
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path

import numpy as np
import torch

from odmo_cli.data.manifest import canonical_name, normalize_action
from odmo_cli.errors import UserError
from odmo_cli.io import atomic_path
from odmo_cli.models import a2m, dvgan
from odmo_cli.models.latent import ActionModes, fit_modes
from odmo_cli.models.odmo import ODMO, ROOTS, ODMOConfig

FORMAT_VERSION = 1  # bump when a reader of the old format would misread a new file


# -- reading and writing -------------------------------------------------------------------------

def save_checkpoint(path: str | Path, payload: dict) -> None:
    """Write a checkpoint atomically. The payload must hold only tensors and plain values; tensors
    on a GPU are written as CPU tensors, so every file loads on any machine."""
    with atomic_path(path) as tmp:
        torch.save(cpu_tensors(payload), tmp)


def cpu_tensors(value):
    """`value` with every tensor inside (dicts, lists, tuples) on the CPU. What holds no tensor off
    the CPU is returned as the same object, so a CPU run's payload is exactly what it was."""
    if isinstance(value, torch.Tensor):
        return value.detach().cpu() if value.device.type != "cpu" else value
    if isinstance(value, dict):
        moved = {k: cpu_tensors(v) for k, v in value.items()}
        if all(moved[k] is v for k, v in value.items()):
            return value
        out = copy.copy(value)  # the same type, and a state dict's _metadata with it
        out.update(moved)
        return out
    if isinstance(value, (list, tuple)):
        moved = [cpu_tensors(v) for v in value]
        return value if all(m is v for m, v in zip(moved, value)) else type(value)(moved)
    return value


def load_checkpoint(path: str | Path) -> dict:
    """Load a checkpoint without unpickling classes (safe for untrusted files). UserError for a
    missing or unreadable file, and for one written in a newer format than this odmo reads."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"checkpoint not found: {path}")
    if path.stat().st_size == 0:
        raise UserError(f"cannot load checkpoint {path}: the file is empty")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises several types for bad or unsafe files
        if not _torch_file(path):
            raise UserError(f"cannot load checkpoint {path}: not a PyTorch checkpoint") from None
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise UserError(f"cannot load checkpoint {path}: {first}") from None
    if not isinstance(payload, dict):
        raise UserError(f"cannot load checkpoint {path}: not an odmo checkpoint (no dict inside)")
    version = payload.get("format_version")
    if isinstance(version, int) and version > FORMAT_VERSION:
        raise UserError(f"{path} has checkpoint format {version}, newer than this odmo reads "
                        f"(format {FORMAT_VERSION} and older): upgrade odmo to load it")
    return payload


def _torch_file(path: Path) -> bool:
    """Whether a file is laid out as torch.save writes: a zip archive (torch 1.6 and later) or the older
    pickle stream (Action2Motion's released files), which starts with pickle's protocol byte."""
    with open(path, "rb") as f:
        return zipfile.is_zipfile(path) or f.read(1) == b"\x80"


def describe_checkpoint(path: str | Path) -> dict:
    """The plain-value parts of a checkpoint: what `odmo info` prints."""
    ckpt = load_checkpoint(path)
    if "kind" not in ckpt or "config" not in ckpt:
        raise UserError(f"{path} is not an odmo checkpoint (no model kind or config inside)")
    state = ckpt.get("state_dict", {})
    # buffers such as A2M's bone-length bank are data, not parameters
    n_params = sum(t.numel() for k, t in state.items() if k != "bone_bank")
    bank = ckpt.get("latent_bank")
    last = ckpt.get("history", [])[-1:] or [{}]
    banks = {"latent_bank": f"{len(bank['codes'])} codes" if bank else "none (training not finished)"}
    if ckpt.get("crop_bank"):
        crops = ckpt["crop_bank"]
        banks["crop_bank"] = f"{len(crops['codes'])} codes of random crops ({crops['passes']} passes): the mode mixtures' data"
    if ckpt["kind"] == "a2m":
        banks = {"bone_bank": f"{len(state['bone_bank'])} real bone-length sets for sampling"}
    elif ckpt["kind"] != "odmo":
        banks = {}
    return {
        "file": str(path), "format_version": ckpt.get("format_version"), "kind": ckpt["kind"],
        "parameters": n_params, "weights": ckpt.get("weights_dtype", "float32"),
        "epoch": ckpt.get("epoch"), "dataset": ckpt.get("dataset", {}),
        "config": ckpt["config"], "train_config": ckpt.get("train_config", {}),
        **({"init": ckpt["init"]} if ckpt.get("init") else {}), **banks,  # the stage it started from
        "last_epoch_losses": {k: round(v, 5) if isinstance(v, float) else v for k, v in last[0].items()},
        "report": ckpt.get("report", {}),
    }


# -- what a checkpoint records -------------------------------------------------------------------

def dataset_description(clips) -> dict:
    """What a model was trained on: name, actions, skeleton, fps, clip length T and up axis."""
    m = clips.manifest
    return {"name": m.name, "actions": list(m.action_names), "skeleton": m.skeleton_name,
            "fps": float(m.fps), "length": int(m.clip_length), "up_axis": m.up_axis}


def rng_state(np_rng: np.random.Generator, torch_gen: torch.Generator) -> dict:
    """Every random stream a trainer draws from, as plain values: its numpy generator (PCG64, the
    128-bit integers as strings), its torch generator, and torch's global generator (dropout)."""
    s = np_rng.bit_generator.state
    return {"numpy": {"bit_generator": s["bit_generator"], "state": str(s["state"]["state"]),
                      "inc": str(s["state"]["inc"]), "has_uint32": int(s["has_uint32"]),
                      "uinteger": int(s["uinteger"])},
            "torch": torch_gen.get_state(), "torch_global": torch.get_rng_state()}


def restore_rng(state: dict, np_rng: np.random.Generator, torch_gen: torch.Generator) -> bool:
    """Put the streams back where rng_state found them (files without the global state keep it).
    False when torch_gen's state was saved from a generator on another kind of device (a CPU
    generator's state does not fit a GPU's): torch_gen is then left as it is."""
    d = state["numpy"]
    np_rng.bit_generator.state = {"bit_generator": d["bit_generator"],
                                  "state": {"state": int(d["state"]), "inc": int(d["inc"])},
                                  "has_uint32": d["has_uint32"], "uinteger": d["uinteger"]}
    if "torch_global" in state:
        torch.set_rng_state(state["torch_global"])
    if state["torch"].numel() != torch_gen.get_state().numel():
        return False
    torch_gen.set_state(state["torch"])
    return True


# -- compact files: what `odmo ship` writes, and reading it back --------------------------------

_KEEP = ("format_version", "kind", "config", "train_config", "dataset", "epoch", "latent_bank", "crop_bank", "modes", "report",
         "init", "recipe", "recipe_phase")


INT8_MIN_VALUES = 1 << 20  # matrices with at least this many values are stored as int8 rows


def compact(ckpt: dict, int8_min_values: int = INT8_MIN_VALUES) -> dict:
    """A finished checkpoint without what only training needs: weights as float16, and matrices of
    at least `int8_min_values` values as int8 rows with a float32 scale each."""
    out = {k: ckpt[k] for k in _KEEP if k in ckpt}
    state, scales = {}, {}
    for k, v in ckpt["state_dict"].items():
        if v.is_floating_point() and v.dim() == 2 and v.numel() >= int8_min_values:
            state[k], scales[k] = int8_rows(v)
        else:
            state[k] = v.half() if v.is_floating_point() else v
    out["state_dict"] = state
    out["int8_scales"] = scales
    out["history"] = list(ckpt.get("history", []))[-1:]
    out["weights_dtype"] = "float16" + (f"; int8 rows for {', '.join(scales)}" if scales else "")
    return out


def int8_rows(w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(R, K) float -> (R, K) int8 and (R, 1) float32 scales with w ~= q * scale, |q| <= 127.

    The scales stay float32 (R values): in float16 the floor that keeps an all-zero row from
    dividing by zero would underflow to 0.
    """
    w = w.float()
    scale = (w.abs().amax(dim=1, keepdim=True) / 127).clamp_min(1e-12)
    q = torch.round(w / scale).clamp(-127, 127).to(torch.int8)
    return q, scale


def compact_classifier(ckpt: dict) -> dict:
    """A finished classifier checkpoint without its optimizer and RNG state; weights stay float32
    (evaluation numbers must not move) and the split stays (`odmo eval --held-out` reads it)."""
    return {k: v for k, v in ckpt.items() if k not in ("optimizer", "rng")}


def float_state(ckpt: dict) -> dict:
    """The checkpoint's state dict with int8 rows (compact files, see compact) turned back into
    float32 matrices; float16 tensors load into float32 parameters as they are."""
    scales = ckpt.get("int8_scales") or {}
    return {k: v.float() * scales[k].float() if k in scales else v for k, v in ckpt["state_dict"].items()}


# -- the shipped files ---------------------------------------------------------------------------

# Per dataset: the short name users type (`--model cmu`) and the files in odmo_cli/assets/models
# (`odmo ship` writes them, with the recipes in odmo_cli/ship.py).
SHIPPED = {
    "humanact12": {"short": "humanact12", "odmo": "odmo_humanact12.pt", "classifier": "classifier_humanact12.pt"},
    "cmu_mocap": {"short": "cmu", "odmo": "odmo_cmu.pt", "classifier": "classifier_cmu.pt"},
}
DEFAULT_MODEL = "humanact12"


def shipped_file(name: str, part: str = "odmo") -> Path | None:
    """The installed shipped file ("odmo" or "classifier") of a dataset or short name; None if absent."""
    entry = SHIPPED.get(canonical_name(name))
    if entry is None:
        return None
    path = Path(str(resources.files("odmo_cli") / "assets" / "models" / entry[part]))
    return path if path.is_file() else None


def shipped_names() -> str:
    return ", ".join(e["short"] for e in SHIPPED.values())


def checkpoint_path(spec: str | Path | None) -> Path:
    """A checkpoint file, or a shipped model's short name (None: the default) -> the file."""
    spec = str(spec or DEFAULT_MODEL)
    if Path(spec).is_file():
        return Path(spec)
    if canonical_name(spec) not in SHIPPED:
        raise UserError(f"no model {spec!r}: give a checkpoint file or a shipped name ({shipped_names()})")
    path = shipped_file(spec)
    if path is None:
        raise UserError(f"no shipped model {spec!r} in this install; give a checkpoint path instead")
    return path


def model_name(source: str | Path) -> str:
    """How a samples file names its model: a shipped model's short name, else the file name (never
    a path of the machine that made it)."""
    path = Path(source)
    for dataset, entry in SHIPPED.items():
        shipped = shipped_file(dataset)
        if shipped is not None and path.resolve() == shipped.resolve():
            return entry["short"]
    return path.name


# -- loading a generator -------------------------------------------------------------------------

BASELINES = {"a2m": a2m.model_from_checkpoint, "dvgan": dvgan.model_from_checkpoint}  # kind -> builder
SAMPLING = ("mode-preserving", "conventional")


@dataclass
class Loaded:
    """A generator in eval mode with what its checkpoint says about the data."""

    model: torch.nn.Module
    dataset: dict  # name, actions, skeleton, fps, length, up_axis
    source: str  # the file it came from

    @property
    def actions(self) -> list[str]:
        return list(self.dataset["actions"])

    def action_index(self, name: str) -> int:
        key = normalize_action(name)
        if key in self.actions:
            return self.actions.index(key)
        raise UserError(f"unknown action {name!r}; valid: {', '.join(self.actions)}, all")

    def action_indices(self, names: list[str]) -> list[int]:
        """["all"] -> every action; else each name's index."""
        return list(range(len(self.actions))) if list(names) == ["all"] else [self.action_index(a) for a in names]


@dataclass
class LoadedODMO(Loaded):
    """ODMO with its latent bank and mode mixtures (built once, at load)."""

    bank: dict = field(default_factory=dict)  # codes (N, D), labels, end_points (N, 3), modes, names
    modes: dict = field(default_factory=dict)  # plain values, as stored (models.latent.fit_modes)
    crops: dict | None = None  # generation.generate.crop_bank: what the mixtures and KNN end points are fitted on, where present
    mixtures: dict = field(init=False, repr=False)  # sampling -> [ActionModes per action]

    def __post_init__(self):
        self.set_modes(self.modes)

    @property
    def mixture_bank(self) -> dict:
        """The codes the mixtures were fitted on and end points are looked up in: one code per clip
        (the latent bank), or the crop bank of a file refitted with `odmo modes --mixture-data crops`."""
        return self.crops if self.crops is not None else self.bank

    @property
    def k_rule(self) -> str:
        """How the mixtures' number of modes was chosen (models.latent.K_RULES); files fitted before the
        choice was recorded used the paper's rule."""
        return self.modes.get("rule", "paper")

    def set_modes(self, modes: dict) -> None:
        self.modes = modes
        self.mixtures = {"mode-preserving": [ActionModes.from_plain(m) for m in modes["actions"]],
                         "conventional": [ActionModes.from_plain(m) for m in modes["conventional"]]}

    def set_root(self, root: str) -> None:
        """Read decoded motions' roots from `root` (ODMOConfig.root) instead of the file's choice."""
        if root not in ROOTS:
            raise UserError(f"unknown --root {root!r}; valid: {', '.join(ROOTS)}")
        self.model.cfg = replace(self.model.cfg, root=root)

    def action_modes(self, action: int, sampling: str = "mode-preserving") -> ActionModes:
        return self.mixtures[sampling][action]


@dataclass
class LoadedBaseline(Loaded):
    """A baseline generator (Action2Motion, DVGAN): motions from noise, no codes or end points."""

    kind: str = ""


def load_model(spec: str | Path | None, device: torch.device | None = None,
               root: str | None = None) -> LoadedODMO | LoadedBaseline:
    """Any generator checkpoint (path or shipped short name; None: the default), ready to sample
    on `device` (None: the CPU). `root`: ODMO's root readout (ODMOConfig.root; None: the file's)."""
    path = checkpoint_path(spec)
    ckpt = load_checkpoint(path)
    kind = ckpt.get("kind")
    if kind == "odmo":
        return _odmo_from(path, ckpt, device, root)
    if kind not in BASELINES:
        raise UserError(f"{path} holds a {kind!r} model; generators are: odmo, {', '.join(BASELINES)}")
    if root is not None:
        raise UserError(f"--root is ODMO's (its trajectory generator); {path} holds a {kind} model")
    model = BASELINES[kind](ckpt)
    model.eval()
    if device is not None:
        model.to(device)
    return LoadedBaseline(model, ckpt["dataset"], str(path), kind)


def load_odmo(spec: str | Path | None, device: torch.device | None = None, root: str | None = None) -> LoadedODMO:
    """An ODMO checkpoint (path or shipped short name; None: the default), on `device` (None: CPU);
    `root` as in load_model."""
    path = checkpoint_path(spec)
    ckpt = load_checkpoint(path)
    if ckpt.get("kind") != "odmo":
        raise UserError(f"{path} holds a {ckpt.get('kind')!r} model; this command needs an ODMO checkpoint "
                        "(modes, latent codes and end points are ODMO's)")
    return _odmo_from(path, ckpt, device, root)


def odmo_config(path: str | Path, config: dict) -> ODMOConfig:
    """The ODMOConfig a file's config describes; UserError naming the file if a value is invalid (a file
    written by hand or damaged: a nan loss weight, an unknown readout)."""
    try:
        return ODMOConfig.from_saved(config)
    except ValueError as e:
        raise UserError(f"{path} holds an invalid ODMO config: {e}") from None


def _odmo_from(path: Path, ckpt: dict, device: torch.device | None = None, root: str | None = None) -> LoadedODMO:
    if "latent_bank" not in ckpt:
        raise UserError(f"{path} has no latent bank: its training did not finish (resume it to the end, or stop "
                        "it with Ctrl-C, which saves one)")
    # files written before the config named its skeleton take the dataset's, and decode their bones as
    # they were trained to (free) unless the file says otherwise
    cfg = odmo_config(path, {"skeleton": ckpt["dataset"].get("skeleton", ""), "bones": "free", **ckpt["config"]})
    with torch.device("meta"):  # no random initialisation: every weight comes from the file
        model = ODMO(cfg)
    state = {k: v.float() if v.is_floating_point() else v for k, v in float_state(ckpt).items()}
    model.load_state_dict(state, assign=True)
    model.eval()
    if device is not None:
        model.to(device)
    crops = ckpt.get("crop_bank")
    modes = ckpt.get("modes") or fit_modes(crops or ckpt["latent_bank"], model.cfg.n_classes)
    loaded = LoadedODMO(model, ckpt["dataset"], str(path), ckpt["latent_bank"], modes, crops)
    if root is not None:
        loaded.set_root(root)
    return loaded
