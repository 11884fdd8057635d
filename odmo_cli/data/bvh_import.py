"""Import a folder of BVH files as a motion folder (`odmo data prepare DIR --format bvh`).

Each file is read and forward-kinematics'd (`odmo_cli.formats.bvh.read_bvh`), its joints are picked by a
joint map (target joint -> source joint names, the first one present wins), turned to the target
dataset's up axis (proper rotation, so left stays left) and units, and resampled to its fps.
Bad files are listed with the reason and skipped; only "nothing readable" is an error.
"""

from __future__ import annotations

import csv
import dataclasses
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

from odmo_cli.formats.bvh import read_bvh
from odmo_cli.data.manifest import Action, Manifest, load_manifest, normalize_action
from odmo_cli.data.readers import ClipSet
from odmo_cli.errors import UserError
from odmo_cli.geometry.lie import rotation_between, so3_exp
from odmo_cli.geometry.skeletons import SKELETONS, Skeleton, get_skeleton


def _sides(template: dict[str, str], left: str, right: str) -> dict[str, list[str]]:
    """Expand {"left_knee": "{S}Leg"} into both sides with the hierarchy's side spellings."""
    out: dict[str, list[str]] = {}
    for target, source in template.items():
        if "{S}" in source:
            out[target] = [source.replace("{S}", left)]
            out[target.replace("left_", "right_")] = [source.replace("{S}", right)]
        else:
            out[target] = [source]
    return out


# The CMU BVH release (cgspeed's MotionBuilder-friendly conversion of the CMU ASF/AMC files).
# Which of its joints A2M's 20 joints are was chosen by anatomy, not checked on the release.
_CMU_TO_CMU20 = _sides({
    "root": "Hips", "thorax": "Spine1", "neck": "Neck", "head": "Head",
    "left_shoulder": "{S}Arm", "left_elbow": "{S}ForeArm", "left_wrist": "{S}Hand",
    "left_hand": "{S}FingerBase", "left_hip": "{S}UpLeg", "left_knee": "{S}Leg",
    "left_ankle": "{S}Foot", "left_toe": "{S}ToeBase",
}, "Left", "Right")

# iClone / Character Creator retargets (`CC_Base_*`, e.g. ../shared/data/bvh_samples).
_CC_TO_HUMANACT12 = _sides({
    "pelvis": "CC_Base_Pelvis", "left_hip": "CC_Base_{S}_Thigh", "spine1": "CC_Base_Waist",
    "left_knee": "CC_Base_{S}_Calf", "spine2": "CC_Base_Spine01", "left_ankle": "CC_Base_{S}_Foot",
    "spine3": "CC_Base_Spine02", "left_foot": "CC_Base_{S}_ToeBase", "neck": "CC_Base_NeckTwist01",
    "left_collar": "CC_Base_{S}_Clavicle", "head": "CC_Base_Head", "left_shoulder": "CC_Base_{S}_Upperarm",
    "left_elbow": "CC_Base_{S}_Forearm", "left_wrist": "CC_Base_{S}_Hand", "left_hand": "CC_Base_{S}_Mid1",
}, "L", "R")
_CC_TO_CMU20 = _sides({
    "root": "CC_Base_Pelvis", "thorax": "CC_Base_Spine02", "neck": "CC_Base_NeckTwist01",
    "head": "CC_Base_Head", "left_shoulder": "CC_Base_{S}_Upperarm", "left_elbow": "CC_Base_{S}_Forearm",
    "left_wrist": "CC_Base_{S}_Hand", "left_hand": "CC_Base_{S}_Mid1", "left_hip": "CC_Base_{S}_Thigh",
    "left_knee": "CC_Base_{S}_Calf", "left_ankle": "CC_Base_{S}_Foot", "left_toe": "CC_Base_{S}_ToeBase",
}, "L", "R")


@dataclass(frozen=True)
class JointMap:
    name: str
    skeleton: str
    joints: dict  # target joint name -> list of source joint names (first present wins)

    def applies_to(self, names) -> bool:
        have = set(names)
        return all(any(s in have for s in srcs) for srcs in self.joints.values())

    def indices(self, names) -> list[int]:
        """Source joint index of every target joint, in the target skeleton's order."""
        where = {n: i for i, n in enumerate(names)}
        sk = get_skeleton(self.skeleton)
        out = []
        for target in sk.joint_names:
            found = [where[s] for s in self.joints[target] if s in where]
            if not found:
                raise UserError(f"joint map {self.name}: no joint {' or '.join(self.joints[target])} "
                                f"(for {target}) in this hierarchy")
            out.append(found[0])
        return out


def _export_map(skeleton: str) -> JointMap:
    """The names `odmo export` writes (Skeleton.bvh_names): its files read back as they were written."""
    sk = get_skeleton(skeleton)
    return JointMap("odmo-export", skeleton, {j: [b] for j, b in zip(sk.joint_names, sk.bvh_names)})


# Order matters for --skeleton auto: the first map whose joints a file has wins. An odmo humanact12
# export also has every joint the CMU map needs, so the export maps come first (the CMU release and
# a cmu20 export have no Spine2 and no LeftShoulder, so the humanact12 one never takes them).
BUILTIN_MAPS = (
    _export_map("humanact12"),
    JointMap("cmu-bvh", "cmu20", _CMU_TO_CMU20),
    JointMap("cc-base", "humanact12", _CC_TO_HUMANACT12),
    JointMap("cc-base", "cmu20", _CC_TO_CMU20),
)

# Length units a BVH file may use, in metres. "cmu" is the CMU ASF unit (1/0.45 inch).
UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254, "cmu": 0.0254 / 0.45}
_HEAD_ABOVE_ANKLES_M = 1.45  # a standing adult's head joint above the ankle joints


def load_joint_map(path: Path) -> JointMap:
    """A user joint map: `skeleton = "humanact12"` and a [joints] table target = "Source" or [..]."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"joint map not found: {path}")
    try:
        raw = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise UserError(f"joint map {path} is not valid TOML: {exc}") from None
    if raw.get("skeleton") not in SKELETONS or not isinstance(raw.get("joints"), dict):
        raise UserError(f"joint map {path} needs skeleton = one of {', '.join(SKELETONS)} and a [joints] table")
    sk = get_skeleton(raw["skeleton"])
    joints = {k: [v] if isinstance(v, str) else list(v) for k, v in raw["joints"].items()}
    missing = [j for j in sk.joint_names if j not in joints]
    unknown = [j for j in joints if j not in sk.joint_names]
    if missing or unknown:
        raise UserError(f"joint map {path}: " + (f"missing {', '.join(missing)}" if missing else
                        f"unknown joint {unknown[0]!r}") + f"; {sk.name} joints: {', '.join(sk.joint_names)}")
    return JointMap(path.name, sk.name, joints)


@dataclass
class BvhImportConfig:
    skeleton: str = "auto"  # humanact12 | cmu20 | auto (from the first file's hierarchy)
    dataset: str | None = None  # manifest for actions/fps/clip length (default: the skeleton's dataset)
    fps: float | None = None  # default: the dataset's
    unit: str = "auto"  # one of UNITS, or auto (from the body height)
    labels: Path | None = None  # CSV file,action; default: the manifest's trial list
    joint_map: Path | None = None


@dataclass
class BvhImport:
    clips: ClipSet
    read: int = 0
    problems: list[str] = field(default_factory=list)
    units: dict = field(default_factory=dict)  # file -> unit used


_DATASET_OF = {"humanact12": "humanact12", "cmu20": "cmu_mocap"}


def trial_id(path: Path) -> str:
    """'002_01.bvh' and '02_01.bvh' -> '02_01' (the id pose_clip.csv uses); other names: the stem."""
    m = re.fullmatch(r"0*(\d+)_0*(\d+)", path.stem)
    return f"{int(m.group(1)):02d}_{int(m.group(2)):02d}" if m else path.stem


def import_bvh_folder(source: Path, cfg: BvhImportConfig) -> BvhImport:
    """Read every BVH under `source` that has a label; return the clips in the target's frame."""
    source = Path(source)
    if not source.is_dir():
        raise UserError(f"BVH folder not found: {source}")
    if cfg.unit != "auto" and cfg.unit not in UNITS:
        raise UserError(f"unknown unit {cfg.unit!r}; valid: auto, {', '.join(UNITS)}")
    if cfg.skeleton != "auto" and cfg.skeleton not in _DATASET_OF:
        raise UserError(f"unknown skeleton {cfg.skeleton!r} for BVH import; valid: auto, {', '.join(_DATASET_OF)}")
    files = sorted(source.rglob("*.bvh"), key=lambda p: p.relative_to(source).as_posix())
    if not files:
        raise UserError(f"no .bvh files in {source}")
    user_map = load_joint_map(cfg.joint_map) if cfg.joint_map else None
    if user_map and cfg.skeleton not in ("auto", user_map.skeleton):
        raise UserError(f"--skeleton {cfg.skeleton} disagrees with the joint map's skeleton {user_map.skeleton}")

    problems: list[str] = []
    parsed = []
    for path in files:
        try:
            parsed.append((path, read_bvh(path)))
        except UserError as exc:
            problems.append(str(exc))
    skeleton = user_map.skeleton if user_map else cfg.skeleton
    if skeleton == "auto":
        skeleton = next((m.skeleton for _, clip in parsed for m in BUILTIN_MAPS if m.applies_to(clip.names)), None)
        if skeleton is None:
            raise UserError(f"no built-in joint map fits the BVH files in {source} "
                            f"({'; '.join(problems[:3]) or 'unknown hierarchy'}); pass --joint-map map.toml")
    manifest = load_manifest(cfg.dataset or _DATASET_OF[skeleton])
    if manifest.skeleton_name != skeleton:
        raise UserError(f"dataset {manifest.name} uses skeleton {manifest.skeleton_name}, not {skeleton}")
    fps = float(cfg.fps or manifest.fps)
    if not np.isfinite(fps) or fps <= 0:
        raise UserError(f"--fps must be a positive number, got {cfg.fps}")
    labels = _labels(cfg.labels, manifest)
    sk = get_skeleton(skeleton)

    motions, names, actions, units = [], [], [], {}
    for path, clip in parsed:
        key = _label_key(path, labels)
        if key is None:
            problems.append(f"{path.name}: no label (add a row `{path.name},ACTION` to the labels CSV)")
            continue
        jmap = user_map or next((m for m in BUILTIN_MAPS if m.skeleton == skeleton and m.applies_to(clip.names)), None)
        if jmap is None:
            problems.append(f"{path.name}: no built-in joint map from its hierarchy (root {clip.names[0]}) "
                            f"to {skeleton}; pass --joint-map map.toml")
            continue
        try:
            motion, unit = to_target(clip, jmap, sk, manifest, fps, cfg.unit)
        except UserError as exc:
            problems.append(f"{path.name}: {exc}")
            continue
        motions.append(motion)
        names.append(_unique(trial_id(path), names))
        actions.append(labels[key])
        units[path.name] = unit
    problems += [f"{f}: listed in the labels but not found" for f in sorted(set(labels) - _seen_keys(files, labels))
                 if cfg.labels is not None]
    if not motions:
        raise UserError(f"no BVH file in {source} could be imported: " + "; ".join(problems[:5])
                        + (f" ... ({len(problems)} problems)" if len(problems) > 5 else ""))
    clips = _clipset(manifest, source, motions, names, actions, fps)
    return BvhImport(clips, len(motions), problems, units)


def _labels(path: Path | None, manifest: Manifest) -> dict[str, str]:
    """label key (file stem or trial id) -> action name in the manifest's spelling if it has it."""
    if path is None:
        table = {t: a.name for a in manifest.actions for t in a.trials}
        if not table:
            raise UserError(f"--labels is required: dataset {manifest.name} lists no trials")
        return table
    path = Path(path)
    if not path.is_file():
        raise UserError(f"labels file not found: {path}")
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        if not {"file", "action"} <= set(reader.fieldnames or ()):
            raise UserError(f"{path}: needs columns file,action, has {reader.fieldnames}")
        rows = [r for r in reader if (r["file"] or "").strip()]
    if not rows:
        raise UserError(f"{path}: no labelled files")
    known = {normalize_action(a.name): a.name for a in manifest.actions}
    known.update({normalize_action(a.label): a.name for a in manifest.actions})
    out = {}
    for r in rows:
        stem = Path(r["file"].strip()).stem if r["file"].strip().lower().endswith(".bvh") else r["file"].strip()
        action = (r["action"] or "").strip()
        if not action:
            raise UserError(f"{path}: file {stem} has an empty action")
        out[stem] = known.get(normalize_action(action), normalize_action(action))
    return out


def _label_key(path: Path, labels: dict[str, str]) -> str | None:
    for key in (path.stem, trial_id(path)):
        if key in labels:
            return key
    return None


def _seen_keys(files: list[Path], labels: dict[str, str]) -> set[str]:
    return {k for p in files if (k := _label_key(p, labels)) is not None}


def _unique(name: str, taken: list[str]) -> str:
    out, k = name, 1
    while out in taken:
        k += 1
        out = f"{name}_{k}"
    return out


def to_target(clip, jmap: JointMap, sk: Skeleton, manifest: Manifest, fps: float,
              unit: str = "auto") -> tuple[np.ndarray, str]:
    """BvhClip -> (motion (T, J, 3) float32 in the target's frame, units and fps; the unit used)."""
    pos = clip.positions[:, jmap.indices(clip.names)]  # (F, J, 3) file units and axes
    if len(pos) < 2:
        raise UserError(f"only {len(pos)} frame(s)")
    names = sk.joint_names
    head = names.index("head")
    ankles = [names.index(n) for n in names if "ankle" in n]
    rise = pos[:, head] - pos[:, ankles].mean(1)  # (F, 3)
    axis = int(np.abs(rise.mean(0)).argmax())
    file_up = np.zeros(3)
    file_up[axis] = np.sign(rise.mean(0)[axis])
    target_up = np.zeros(3)
    target_up[sk.up_index] = sk.up_sign
    if axis == 1 and sk.up_index == 1:  # y-up to -y-up (or back): half a turn about x, as `odmo export` turns
        sign = file_up[1] * target_up[1]
        turn = np.diag([1.0, sign, sign])
    else:
        turn = so3_exp(rotation_between(torch.as_tensor(file_up), torch.as_tensor(target_up))).numpy()
    pos = pos @ turn.T  # proper rotation: the subject's left stays left
    height = float(np.percentile(np.abs(rise[:, axis]), 90))
    if unit == "auto":
        if height <= 0:
            raise UserError("cannot tell its units: the head is not above the ankles")
        unit = min(UNITS, key=lambda u: abs(np.log(height * UNITS[u] / _HEAD_ABOVE_ANKLES_M)))
    # the CMU release's own unit goes through the manifest's scale, so clips match the A2M copy
    scale = manifest.scale if unit == "cmu" and manifest.format == "cmu_a2m" else UNITS[unit]
    motion = resample(pos * scale, clip.fps, fps)
    if not np.isfinite(motion).all():
        raise UserError("non-finite joint positions")
    return motion.astype(np.float32), unit


def resample(motion: np.ndarray, src_fps: float, fps: float) -> np.ndarray:
    """Linear interpolation in time: (F, J, 3) at src_fps -> (T, J, 3) at fps, same start."""
    if src_fps <= 0:
        raise UserError(f"frame rate {src_fps} is not positive")
    duration = (len(motion) - 1) / src_fps
    t = np.arange(0.0, duration + 1e-9, 1.0 / fps) * src_fps  # in source frames
    lo = np.minimum(np.floor(t).astype(int), len(motion) - 1)
    hi = np.minimum(lo + 1, len(motion) - 1)
    w = (t - lo)[:, None, None]
    return motion[lo] * (1 - w) + motion[hi] * w


def _clipset(manifest: Manifest, source: Path, motions, names, actions, fps: float) -> ClipSet:
    """The imported clips with a manifest of their own: the target's, with only the actions present."""
    order = [a.name for a in manifest.actions if a.name in set(actions)]
    order += sorted(set(actions) - set(order))  # actions the target dataset does not have
    by_name = {a.name: a for a in manifest.actions}
    acts = tuple(Action(n, by_name[n].label if n in by_name else n, actions.count(n)) for n in order)
    m = dataclasses.replace(manifest, name=f"{manifest.name}_bvh", title=f"{manifest.title}, from BVH",
                            format="folder", scale=1.0, fps=fps, actions=acts, path=None)
    labels = np.array([order.index(a) for a in actions], dtype=np.int64)
    return ClipSet(m, source, motions, labels, names, np.full(len(motions), -1, dtype=np.int64),
                   subjects=[n.split("_")[0] for n in names])
