"""Shared pytest fixtures.

Sections are owned by different test files; add new fixtures in a section of their own.
"""

from __future__ import annotations

import csv
import os
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]


# =====================================================================================
# Datasets: real data (ODMO_DATA_DIR) and tiny fixture datasets written into tmp_path.
# Used by test_data.py and test_cli_data.py; generic enough for any test to reuse.
# =====================================================================================

NO_DATA_REASON = "ODMO_DATA_DIR is not set: real-data tests need the datasets (see README)"


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """The real data root from $ODMO_DATA_DIR (absolute), or skip when the variable is unset.

    A relative value is taken from the current folder, else from the repository root (CI sets
    ODMO_DATA_DIR=../shared/data relative to the repo). When the variable is set the data must
    be there: a wrong value fails instead of silently skipping.
    """
    value = os.environ.get("ODMO_DATA_DIR")
    if not value:
        pytest.skip(NO_DATA_REASON)
    path = Path(value).expanduser()
    if not path.is_absolute() and not path.is_dir():
        path = REPO / path
    if not path.is_dir():
        pytest.fail(f"ODMO_DATA_DIR={value!r} is set but is not a folder (looked at {path.resolve()})")
    return path.resolve()


@pytest.fixture(scope="session")
def humanact12_dir(data_dir: Path) -> Path:
    """The real HumanAct12 release folder (1191 npy files)."""
    folder = data_dir / "humanact12" / "HumanAct12"
    if not folder.is_dir():
        pytest.fail(f"ODMO_DATA_DIR has no humanact12/HumanAct12/ ({folder})")
    return folder


@pytest.fixture(scope="session")
def cmu_dir(data_dir: Path) -> Path:
    """The real CMU MoCap (Action2Motion release) folder: pose_clip.csv + mocap_3djoints/."""
    folder = data_dir / "cmu_a2m"
    if not (folder / "pose_clip.csv").is_file():
        pytest.fail(f"ODMO_DATA_DIR has no cmu_a2m/pose_clip.csv ({folder})")
    return folder


# CMU classes of the Action2Motion release, in the order of the cmu_mocap manifest.
CMU_CLASSES = ("Walk", "Run", "Jump", "Animal Behavior", "Dance", "Step", "Climb")

_UP_NAMES = ("spine", "neck", "head", "thorax", "collar", "shoulder")
_DOWN_NAMES = ("hip", "knee", "ankle", "foot", "toe")


def synthetic_motion(skeleton_name: str, length: int, rng: np.random.Generator,
                     scale: float = 1.0) -> np.ndarray:
    """A plausible float64 (length, J, 3) motion of a named skeleton in its own frame.

    Upper-body joints sit above the pelvis along the skeleton's up axis, legs below it; the
    root drifts on the ground plane and joints wobble a little. The first root is NOT at the
    origin (readers must not depend on that). `scale` multiplies everything (CMU raw = x20).
    """
    from odmo_cli.geometry.skeletons import get_skeleton

    sk = get_skeleton(skeleton_name)
    up = np.zeros(3)
    up[sk.up_index] = sk.up_sign
    rest = np.zeros((sk.n_joints, 3))
    for j, p in enumerate(sk.parents):
        if p < 0:
            continue
        name = sk.joint_names[j]
        offset = rng.normal(0.0, 0.03, 3)
        if any(k in name for k in _UP_NAMES):
            offset += 0.15 * up
        elif any(k in name for k in _DOWN_NAMES):
            offset -= 0.15 * up
        rest[j] = rest[p] + offset
    ground = np.zeros(3)
    ground[list(sk.ground_axes)] = rng.normal(0.0, 0.02, 2)
    root = rng.normal(0.0, 0.5, 3) + np.cumsum(np.tile(ground, (length, 1)), axis=0)
    t = np.arange(length)[:, None, None]
    wobble = 0.02 * np.sin(0.3 * t + rng.uniform(0, 6.3, (1, sk.n_joints, 3)))
    motion = rest[None] + root[:, None, :] + wobble
    return (motion * scale).astype(np.float64)


def humanact12_name(subject: int, index: int, length: int, action: int, fine: int) -> str:
    """A release file name P<pp>G<gg>R<rr>F<ffff>T<tttt>A<cc><ff>.npy."""
    first = 1 + (100 * index) % 9000
    return (f"P{subject:02d}G01R{index // 90 + 1:02d}F{first:04d}T{first + length - 1:04d}"
            f"A{action:02d}{fine:02d}.npy")


def write_humanact12(folder: Path, per_action: int = 2, length: int = 70, seed: int = 0,
                     actions=range(1, 13), n_joints: int = 24) -> Path:
    """A HumanAct12-style release folder: `per_action` float64 (length, n_joints, 3) clips per
    coarse action code in `actions`; clip k of an action has fine label k % 2 + 1 (so mode
    action*100 + fine) and subject P0(k % 3 + 1). Returns the folder."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    index = 0
    for action in actions:
        for k in range(per_action):
            motion = synthetic_motion("humanact12", length, rng)
            if n_joints != 24:
                motion = motion[:, :n_joints] if n_joints < 24 else np.concatenate(
                    [motion, motion[:, : n_joints - 24]], axis=1)
            np.save(folder / humanact12_name(k % 3 + 1, index, length, action, k % 2 + 1), motion)
            index += 1
    return folder


def write_cmu(folder: Path, per_action: int = 2, length: int = 30, seed: int = 0, wash: int = 2,
              classes=CMU_CLASSES) -> Path:
    """A CMU-style release folder: pose_clip.csv (motion,action_type) and mocap_3djoints/*.npy,
    float64 (length, 20, 3) in raw units (20x metres). Includes `wash` 'Wash' rows (with their
    files), which the cmu_mocap manifest leaves out. Clip names are SS_TT. Returns the folder."""
    folder = Path(folder)
    (folder / "mocap_3djoints").mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    rows = []
    for c, label in enumerate(list(classes) + ["Wash"]):
        for k in range(wash if label == "Wash" else per_action):
            name = f"{c + 1:02d}_{k + 1:02d}"
            np.save(folder / "mocap_3djoints" / f"{name}.npy",
                    synthetic_motion("cmu20", length, rng, scale=20.0))
            rows.append((name, label))
    rng.shuffle(rows)  # the release's csv is not grouped by class either
    with open(folder / "pose_clip.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["motion", "action_type"])
        writer.writerows(rows)
    return folder


def write_motion_folder(folder: Path, manifest_name: str = "humanact12", per_action: int = 2,
                        length: int = 40, seed: int = 0, actions=None, splits=None,
                        with_manifest: bool = True) -> Path:
    """A motion folder (index.csv + one npy per row + dataset.toml from `manifest_toml`).

    actions: action names, one per clip (default: every action of the manifest `per_action`
    times); names need not be in the manifest (to test errors). splits: optional list of
    `split` column values, one per clip. Clips are float32 (length, J, 3). Returns the folder.
    """
    from odmo_cli.data.locate import FOLDER_MANIFEST
    from odmo_cli.data.manifest import load_manifest
    from odmo_cli.data.prepare import manifest_toml

    manifest = load_manifest(manifest_name)
    if actions is None:
        actions = [a for a in manifest.action_names for _ in range(per_action)]
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=False)
    rng = np.random.default_rng(seed)
    header = ["motion", "action", "mode", "subject"] + (["split"] if splits is not None else [])
    with open(folder / "index.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(header)
        for i, action in enumerate(actions):
            name = f"clip{i:03d}"
            np.save(folder / f"{name}.npy",
                    synthetic_motion(manifest.skeleton_name, length, rng).astype(np.float32))
            row = [name, action, i % 2, f"S{i % 3}"] + ([splits[i]] if splits is not None else [])
            writer.writerow(row)
    if with_manifest:
        (folder / FOLDER_MANIFEST).write_text(manifest_toml(manifest, manifest.name))
    return folder


def corrupt_clip(path: Path, kind: str) -> None:
    """Spoil one clip file the way a bad download or export would (kind names how)."""
    if kind == "garbage":
        path.write_bytes(b"this is not a numpy file \x00\x01\x02" * 10)
    elif kind == "nan":
        arr = np.load(path)
        arr[3, 5, 1] = np.nan
        np.save(path, arr)
    elif kind == "inf":
        arr = np.load(path)
        arr[0, 0, 0] = np.inf
        np.save(path, arr)
    elif kind == "joints":
        np.save(path, np.load(path)[:, :22])
    elif kind == "shape":
        np.save(path, np.load(path)[:, :, :2])
    elif kind == "empty":
        np.save(path, np.zeros((0, 24, 3)))
    elif kind == "strings":
        np.save(path, np.full((4, 24, 3), "x"))
    elif kind == "truncated":
        path.write_bytes(path.read_bytes()[:200])


@pytest.fixture
def spoil_clip():
    """corrupt_clip(path, kind): garbage, truncated, nan, inf, joints, shape, empty, strings."""
    return corrupt_clip


@pytest.fixture
def make_humanact12():
    """write_humanact12(folder, per_action=2, length=70, seed=0, actions=range(1, 13), n_joints=24)."""
    return write_humanact12


@pytest.fixture
def make_cmu():
    """write_cmu(folder, per_action=2, length=30, seed=0, wash=2)."""
    return write_cmu


@pytest.fixture
def make_motion_folder():
    """write_motion_folder(folder, manifest_name="humanact12", per_action=2, length=40, seed=0,
    actions=None, splits=None, with_manifest=True)."""
    return write_motion_folder


@pytest.fixture
def humanact12_fixture(tmp_path: Path) -> Path:
    """A fresh HumanAct12-style folder tmp_path/ha12: 12 actions x 2 clips of 70 frames."""
    return write_humanact12(tmp_path / "ha12")


@pytest.fixture
def cmu_fixture(tmp_path: Path) -> Path:
    """A fresh CMU-style folder tmp_path/cmu: 7 classes x 2 clips of 30 frames, plus 2 Wash rows."""
    return write_cmu(tmp_path / "cmu")


# ============================ end of the datasets section ============================


@pytest.fixture
def one_thread():
    """torch at one thread for the test, the previous count restored after."""
    import torch

    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


# =====================================================================================
# A tiny trained ODMO: straight-line motions of a rigid body (test_generate, test_evaluate).
# =====================================================================================

MANIFEST = """name = "lines"
title = "synthetic straight-line walks"
format = "folder"
skeleton = "cmu20"
up_axis = "+y"
fps = 10
clip_length = 12

[[actions]]
name = "glide"
[[actions]]
name = "crouch"
"""


def write_lines(folder, per_action=40, length=12, seed=0):
    """Rigid bodies moving on straight lines from the origin to a random ground-plane end point;
    the two actions differ in pose, and each action has two speeds (modes)."""
    rng = np.random.default_rng(seed)
    folder.mkdir()
    (folder / "dataset.toml").write_text(MANIFEST)
    base = rng.normal(0, 0.3, (20, 3)).astype(np.float32)
    base[0] = 0
    rows = ["motion,action,mode"]
    for a, name in enumerate(["glide", "crouch"]):
        pose = base * (1.0 if a == 0 else 0.5)
        for i in range(per_action):
            mode = i % 2
            end = rng.uniform(-1, 1, 2) * (0.5 + mode)
            t = np.linspace(0, 1, length)[:, None]
            root = np.stack([end[0] * t[:, 0], np.zeros(length), end[1] * t[:, 0]], -1)
            motion = root[:, None, :] + pose[None]
            np.save(folder / f"{name}{i}.npy", motion.astype(np.float32))
            rows.append(f"{name}{i},{name},{mode}")
    (folder / "index.csv").write_text("\n".join(rows) + "\n")
    return folder


@pytest.fixture(scope="session")
def lines_folder(tmp_path_factory):
    return write_lines(tmp_path_factory.mktemp("data") / "lines")


@pytest.fixture(scope="session")
def lines_model(tmp_path_factory, lines_folder):
    from odmo_cli.data.locate import resolve
    from odmo_cli.data.readers import read_dataset
    from odmo_cli.training.odmo import TrainConfig, train_odmo

    manifest, root = resolve(lines_folder)
    clips = read_dataset(root, manifest)
    overrides = {"motion_hidden": 32, "traj_hidden": 32, "encoder_fc": 32, "latent_dim": 4}
    tc = TrainConfig(epochs=150, batch_size=40, val_fraction=0.0, val_every=0, checkpoint_every=0,
                     pairs_per_epoch=160, seed=0, lr=1e-2, lr_final=1e-3, tf_epochs=75,
                     same_class_fraction=-1.0, threads=1)  # one thread while training, torch's default after
    # independent pairs (not the release's half same-class): this is the recipe the end-point
    # tests were written for; with 0.5 the far end point of test_end_points_are_reached is missed
    # by 0.11 instead of < 0.1 (measured once, seed 0)
    # and the paper's loss scales (preset "paper"): the release's tighter prior and doubled
    # reconstruction weight, made for real data, miss the near end point by 0.02 instead of < 0.01
    # on this four-dimensional toy (measured once, seed 0)
    out = tmp_path_factory.mktemp("model") / "lines.pt"
    train_odmo(clips, tc, out, preset="paper", overrides=overrides)
    return out


@pytest.fixture(scope="module")
def demo_clips():
    """The HumanAct12 demo subset shipped in the package, read as a ClipSet."""
    from odmo_cli.data.demo import demo_folder
    from odmo_cli.data.locate import resolve
    from odmo_cli.data.readers import read_dataset

    manifest, root = resolve(demo_folder("humanact12"))
    return read_dataset(root, manifest)


def tiny_config(**kw):
    """A small ODMOConfig (4 joints, 3 actions, 8 frames) for fast model tests; kw override it."""
    from odmo_cli.models.odmo_config import ODMOConfig

    base = dict(n_joints=4, n_classes=3, length=8, latent_dim=5, encoder_hidden=8, encoder_fc=16,
                traj_hidden=12, motion_hidden=12)
    base.update(kw)
    return ODMOConfig(**base)
