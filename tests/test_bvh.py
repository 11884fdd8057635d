"""BVH reading, writing, import (`odmo data prepare --format bvh`), export and `odmo render`."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from odmo_cli.geometry import lie
from odmo_cli.formats.bvh import (BvhOptions, bvh_positions, export_bvh, export_motions, motion_to_bvh, read_bvh,
                          write_bvh)
from odmo_cli.cli import app
from odmo_cli.data.bvh_import import BvhImportConfig, import_bvh_folder, resample
from odmo_cli.data.readers import read_dataset
from odmo_cli.errors import UserError
from odmo_cli.geometry.skeletons import get_skeleton

# Two joints: the root moves along x; the child, 10 cm above it, is turned by the root's
# Zrotation (channel order Z, X, Y as in the CMU release) and by its own.
TWO_JOINTS = """HIERARCHY
ROOT hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT chest
  {
    OFFSET 0 10 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    End Site
    {
      OFFSET 0 5 0
    }
  }
}
MOTION
Frames: 3
Frame Time: 0.5
0 0 0 0 0 0 0 0 0
1 2 3 90 0 0 0 0 0
0 0 0 0 90 0 0 0 0
"""


def rigid_motion(skeleton: str, frames: int = 12, seed: int = 0, still_pelvis: bool = False,
                 rigid_torso: bool = False) -> np.ndarray:
    """(T, J, 3) float64 with constant bone lengths: FK of random Lie parameters; the body turns
    one full circle about the up axis (so it faces away from the camera half of the time).
    rigid_torso: the children of every branching joint keep their rest angles."""
    sk = get_skeleton(skeleton)
    g = torch.Generator().manual_seed(seed)
    lie_params = 0.4 * torch.randn(frames, sk.n_joints, 3, generator=g, dtype=torch.float64)
    up = torch.zeros(3, dtype=torch.float64)
    up[sk.up_index] = sk.up_sign
    lie_params[:, 0] = torch.linspace(0, 2 * np.pi, frames, dtype=torch.float64)[:, None] * up  # spins round
    if still_pelvis:  # hips and lower spine keep their rest angles: the body frame is the spin alone
        lie_params[:, [j for j, p in enumerate(sk.parents) if p == 0]] = 0
    if rigid_torso:
        branching = [j for j in range(sk.n_joints) if list(sk.parents).count(j) > 1]
        lie_params[:, [j for j, p in enumerate(sk.parents) if p in branching]] = 0
    root = torch.cumsum(0.05 * torch.randn(frames, 3, generator=g, dtype=torch.float64), 0)
    lengths = 0.05 + 0.3 * torch.rand(sk.n_joints, generator=g, dtype=torch.float64)
    return lie.forward_kinematics(root, lie_params, lengths, sk).numpy()


def test_hand_written_two_joint_file(tmp_path):
    path = tmp_path / "two.bvh"
    path.write_text(TWO_JOINTS)
    clip = read_bvh(path)
    assert clip.names == ("hips", "chest") and clip.parents == (-1, 0)
    assert clip.fps == pytest.approx(2.0)
    expected = np.array([
        [[0, 0, 0], [0, 10, 0]],
        [[1, 2, 3], [1 - 10, 2, 3]],  # 90 deg about z takes +y to -x
        [[0, 0, 0], [0, 0, 10]],  # 90 deg about x takes +y to +z
    ], dtype=float)
    np.testing.assert_allclose(clip.positions, expected, atol=1e-9)


EXACT = BvhOptions(units="m", floor=False, helpers=True)  # the file's frame is the dataset's turned y-up


@pytest.mark.parametrize("skeleton", ["humanact12", "cmu20"])
def test_write_read_round_trip(tmp_path, skeleton):
    sk = get_skeleton(skeleton)
    motion = rigid_motion(skeleton)
    path = write_bvh(tmp_path / "m.bvh", motion_to_bvh(motion, sk, fps=20, options=EXACT))
    clip = read_bvh(path)
    assert clip.fps == pytest.approx(20)
    names = list(clip.names)
    back = clip.positions[:, [names.index(n) for n in sk.bvh_names]]
    if sk.up_sign < 0:  # the file is y-up: undo the half turn about x
        back = back * np.array([1.0, -1.0, -1.0])
    assert np.abs(back - motion).max() < 1e-3  # within 1 mm
    assert np.abs(back - motion).max() < 1e-5  # in fact to the file's 6 decimals


# An independent reader: the BVH format's own rules, written here, not the code that wrote the file.
def _parse_bvh(text: str) -> dict:
    """{"joints": [(name, parent, offset, channels)], "frames": int, "frame_time": float, "values": (F, C)}."""
    tokens = text.split()
    joints, stack, i = [], [], 0
    while tokens[i] != "MOTION":
        tok = tokens[i]
        if tok in ("ROOT", "JOINT"):
            joints.append([tokens[i + 1], stack[-1] if stack else -1, None, []])
            stack.append(len(joints) - 1)
            i += 2
        elif tok == "End":  # End Site { OFFSET x y z }: no channels, not a joint
            i += 8
        elif tok == "OFFSET":
            joints[stack[-1]][2] = np.array([float(v) for v in tokens[i + 1:i + 4]])
            i += 4
        elif tok == "CHANNELS":
            n = int(tokens[i + 1])
            joints[stack[-1]][3] = tokens[i + 2:i + 2 + n]
            i += 2 + n
        elif tok == "}":
            stack.pop()
            i += 1
        else:
            i += 1
    frames, frame_time = int(tokens[i + 2]), float(tokens[i + 5])
    values = np.array(tokens[i + 6:], dtype=float).reshape(frames, -1)
    return {"joints": joints, "frames": frames, "frame_time": frame_time, "values": values}


def _axis_rotation(axis: str, degrees: np.ndarray) -> np.ndarray:
    a = np.deg2rad(degrees)
    c, s_ = np.cos(a), np.sin(a)
    one, zero = np.ones_like(a), np.zeros_like(a)
    rows = {"X": [[one, zero, zero], [zero, c, -s_], [zero, s_, c]],
            "Y": [[c, zero, s_], [zero, one, zero], [-s_, zero, c]],
            "Z": [[c, -s_, zero], [s_, c, zero], [zero, zero, one]]}[axis]
    return np.moveaxis(np.array(rows), (0, 1), (-2, -1))  # (F, 3, 3)


def _fk(parsed: dict) -> tuple[list[str], np.ndarray]:
    """World position of every joint (F, J, 3): x_child = R_parent x_offset + p_parent, where a joint's
    rotation is its parent's times its own channels applied in the order they are listed."""
    values, col = parsed["values"], 0
    pos, rot = [], []
    for name, parent, offset, channels in parsed["joints"]:
        local = np.broadcast_to(np.eye(3), (len(values), 3, 3))
        translation = np.zeros((len(values), 3))
        for ch in channels:
            if ch.endswith("position"):
                translation[:, "XYZ".index(ch[0])] = values[:, col]
            else:
                local = local @ _axis_rotation(ch[0], values[:, col])
            col += 1
        if parent < 0:
            pos.append(offset + translation)
            rot.append(local)
        else:
            pos.append(pos[parent] + (rot[parent] @ offset))
            rot.append(rot[parent] @ local)
    return [j[0] for j in parsed["joints"]], np.stack(pos, 1)


@pytest.mark.parametrize("skeleton", ["humanact12", "cmu20"])
def test_default_export_read_by_an_independent_reader(tmp_path, skeleton):
    sk = get_skeleton(skeleton)
    motion = rigid_motion(skeleton, frames=15, rigid_torso=True)
    report = export_motions(motion[None], ["jump"], sk, 20, tmp_path / "out")
    _, frame = export_bvh(motion, sk, 20)
    parsed = _parse_bvh(report.files[0].read_text())
    names, positions = _fk(parsed)
    assert sorted(names) == sorted(sk.bvh_names) and report.joints == sk.n_joints  # one joint per skeleton joint
    positions = positions[:, [names.index(n) for n in sk.bvh_names]]  # (F, J, 3) in the skeleton's order
    assert parsed["frames"] == 15 and parsed["frame_time"] == pytest.approx(1 / 20, abs=1e-6)
    # centimetres, y-up, the lowest foot on the floor over the whole motion
    assert frame.scale == 100 and report.units == "cm"
    feet = [j for j, n in enumerate(sk.joint_names) if any(k in n for k in ("ankle", "foot", "toe"))]
    assert positions[:, feet, 1].min() == pytest.approx(0.0, abs=1e-3)
    assert np.abs(positions - frame.to_file(motion)).max() < 0.1  # within 1 mm, in cm
    np.testing.assert_allclose(frame.from_file(positions), motion, atol=1e-3)  # back in metres, the dataset's axes
    assert report.max_error_mm < 1e-2


def test_export_conventions():
    sk = get_skeleton("humanact12")
    motion = rigid_motion("humanact12", frames=24, still_pelvis=True)  # turns 360/23 degrees a frame
    bvh = motion_to_bvh(motion, sk, fps=20, options=EXACT)
    # with helpers, branching joints get one zero-length joint per child
    assert "Hips_to_LeftUpLeg" in bvh.joint_names and "Spine2_to_Neck" in bvh.joint_names
    assert len(bvh.joint_names) == 24 + 6
    assert len(motion_to_bvh(motion, sk, fps=20).joint_names) == 24  # the default: none
    # no twist: a single-child joint's local rotation axis is perpendicular to its child's rest offset
    from pybvh.rotations import euler_to_rotmat

    knee = bvh.joint_names.index("LeftLeg")
    rot = torch.as_tensor(euler_to_rotmat(bvh.joint_angles[:, knee], "ZYX"))
    axis = lie.so3_log(rot)  # (T, 3)
    rest = lie.rest_directions(sk)[sk.joint_names.index("left_ankle")] * torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64)
    assert torch.abs(axis @ rest).max() < 1e-6
    # the root's angles are continuous although the body turns round (no Euler-branch flips)
    assert np.abs(np.diff(np.rad2deg(bvh.joint_angles[:, 0]), axis=0)).max() < 20
    # the root rotation is the facing: a turn about the (y-up) vertical by 15 degrees a frame
    yaw = np.rad2deg(bvh.joint_angles[:, 0, 1])
    np.testing.assert_allclose(np.diff(yaw), np.full(23, 360 / 23), atol=1e-6)
    np.testing.assert_allclose(bvh_positions(bvh, sk, export_bvh(motion, sk, 20, EXACT)[1]), motion, atol=1e-9)


def test_export_reports_stretch(tmp_path):
    sk = get_skeleton("cmu20")
    motion = rigid_motion("cmu20", frames=6)
    stretched = motion.copy()
    stretched[3, 3] += (stretched[3, 3] - stretched[3, 2]) * 0.5  # the head bone 50% longer in one frame
    report = export_motions(np.stack([motion, stretched]), ["walk", "run"], sk, 12, tmp_path / "out", EXACT)
    assert [f.name for f in report.files] == ["000_walk.bvh", "001_run.bvh"]
    assert all(f.stat().st_size > 0 for f in report.files)
    assert report.max_stretch_mm > 10 and report.max_error_mm > 1  # reported, not hidden
    exact = export_motions(motion[None], ["walk"], sk, 12, tmp_path / "exact", EXACT)
    assert exact.max_error_mm < 1e-3


def test_resample_keeps_duration():
    motion = np.arange(61, dtype=float)[:, None, None] * np.ones((1, 2, 3))  # 1 s at 60 fps
    out = resample(motion, 60, 20)
    assert len(out) == 21
    np.testing.assert_allclose(out[:, 0, 0], np.arange(0, 61, 3))


# ----------------------------------------------------------------------------- real files


@pytest.fixture(scope="module")
def bvh_dir(data_dir):
    folder = data_dir / "bvh_samples"
    if not folder.is_dir():
        pytest.fail(f"ODMO_DATA_DIR has no bvh_samples/ ({folder})")
    return folder


def _labels(path, rows):
    path.write_text("file,action\n" + "".join(f"{f},{a}\n" for f, a in rows))
    return path


@pytest.mark.parametrize("skeleton", ["humanact12", "cmu20"])
def test_real_bvh_import(tmp_path, bvh_dir, skeleton):
    labels = _labels(tmp_path / "labels.csv", [("002_01.bvh", "walk"), ("002_03.bvh", "run"), ("002_04", "jump")])
    result = import_bvh_folder(bvh_dir, BvhImportConfig(skeleton=skeleton, labels=labels))
    clips = result.clips
    sk = clips.manifest.skeleton
    assert result.problems == [] and clips.names == ["02_01", "02_03", "02_04"]
    assert set(result.units.values()) == {"cm"}
    assert clips.manifest.fps == (20 if skeleton == "humanact12" else 12)
    up = np.zeros(3)
    up[sk.up_index] = sk.up_sign
    left = sk.joint_names.index("left_hip"), sk.joint_names.index("right_hip")
    travel = {}
    for name, m in zip(clips.names, clips.motions):
        assert m.shape[1:] == (sk.n_joints, 3) and m.dtype == np.float32
        height = m @ up
        stand = np.percentile(height.max(1) - height.min(1), 90)
        assert 1.3 < stand < 2.0, (name, stand)  # metres, head above the feet
        bones = np.linalg.norm(m[:, 1:] - m[:, list(sk.parents[1:])], axis=-1)
        assert bones.std(0).max() < 0.005  # rigid bones (mm-level, after resampling)
        assert (m[:, sk.joint_names.index("head")] @ up > m[:, 0] @ up).all()
        ground = m[-1, 0] - m[0, 0] - ((m[-1, 0] - m[0, 0]) @ up) * up
        travel[name] = np.linalg.norm(ground)
        forward = np.cross(m[:, left[0]] - m[:, left[1]], up).mean(0)  # left x up
        if travel[name] > 1:
            assert forward @ ground > 0  # walks forwards: the left side is on the walker's left
    assert travel["02_01"] > 2.5 and travel["02_03"] > 2.5 and travel["02_04"] < 0.5
    assert len(clips.motions[0]) == int(170 / 60 * clips.manifest.fps) + 1


def test_real_bvh_round_trip(tmp_path, bvh_dir, skeleton="humanact12", options=BvhOptions()):
    """The three CMU files: import, export (cm, on the floor), import again: the same joints within 1 mm
    plus what a BVH cannot carry: a bone whose length changes in the source. At the files' own 60 fps
    (resampling blends poses, which shortens bones in fast turns). The rig's head "bone" spans two
    neck joints and bends: 0.2 mm (walk), 0.7 mm (run), 2.6 mm (jump). humanact12 is what --skeleton
    auto picks for this rig, and the default options (no helper joints) are exact for its rigid
    pelvis and chest; as cmu20, whose shoulder "bones" span the moving clavicles, bones change
    length by up to 3 mm."""
    labels = _labels(tmp_path / "labels.csv", [("002_01.bvh", "walk"), ("002_03.bvh", "run"), ("002_04", "jump")])
    first = import_bvh_folder(bvh_dir, BvhImportConfig(skeleton=skeleton, labels=labels, fps=60)).clips
    sk, fps = first.manifest.skeleton, first.manifest.fps
    T = min(len(m) for m in first.motions)
    report = export_motions(np.stack([m[:T] for m in first.motions]), ["walk", "run", "jump"], sk, fps,
                            tmp_path / "out", options)
    assert report.units == "cm" and report.max_error_mm <= report.max_stretch_mm + 1.0
    labels = _labels(tmp_path / "again.csv", [(f.name, a) for f, a in zip(report.files, ["walk", "run", "jump"])])
    again = import_bvh_folder(tmp_path / "out", BvhImportConfig(skeleton="auto", labels=labels, fps=60))
    assert again.problems == [] and set(again.units.values()) == {"cm"}
    assert again.clips.manifest.skeleton_name == skeleton and again.clips.manifest.fps == fps
    errors = []
    for a, b in zip(first.motions, again.clips.motions):
        a, b = a[:T] - a[0, 0], b - b[0, 0]  # the floor lift moved every frame by the same height
        bones = np.linalg.norm(a[:, 1:] - a[:, list(sk.parents[1:])], axis=-1)  # (T, J-1)
        stretch = np.abs(bones - bones.mean(0)).max()
        errors.append(np.linalg.norm(a - b, axis=-1).max())
        assert errors[-1] < 1e-3 + stretch
    assert max(errors[:2]) < 1e-3  # the walk and the run: within 1 mm outright


def test_cmu20_export_names_are_the_cmu_release_names():
    from odmo_cli.data.bvh_import import _CMU_TO_CMU20

    sk = get_skeleton("cmu20")
    assert {j: [b] for j, b in zip(sk.joint_names, sk.bvh_names)} == _CMU_TO_CMU20


def test_cmu_import_uses_manifest_trials(tmp_path, bvh_dir):
    result = import_bvh_folder(bvh_dir, BvhImportConfig(skeleton="cmu20"))
    names = [a.name for a in result.clips.manifest.actions]
    assert names == ["walk", "run", "jump"]
    assert [names[k] for k in result.clips.labels] == ["walk", "run", "jump"]


def test_malformed_files_are_skipped(tmp_path, bvh_dir):
    src = tmp_path / "src"
    src.mkdir()
    good = (bvh_dir / "002_01.bvh").read_text()
    (src / "good.bvh").write_text(good)
    (src / "truncated.bvh").write_text(good[: len(good) // 2])  # MOTION block cut in the middle
    head, motion = good.split("MOTION", 1)
    lines = motion.splitlines(keepends=True)
    (src / "short.bvh").write_text(head + "MOTION" + "".join(lines[:-5]))  # whole frames missing
    (src / "values.bvh").write_text(head + "MOTION" + "".join(lines[:3]) + "".join(  # a value short per frame
        " ".join(ln.split()[:-1]) + "\n" for ln in lines[3:]))
    (src / "channels.bvh").write_text(head.replace("CHANNELS 3 Zrotation Yrotation Xrotation",
                                                   "CHANNELS 3 Zrotation Yrotation", 1) + "MOTION" + motion)
    names = ("good", "truncated", "short", "values", "channels")
    labels = _labels(tmp_path / "l.csv", [(f, "walk") for f in names])
    result = import_bvh_folder(src, BvhImportConfig(skeleton="humanact12", labels=labels))
    assert result.clips.names == ["good"]
    reasons = {p.split(":")[0]: p for p in result.problems}
    assert set(reasons) == {f"{n}.bvh" for n in names[1:]}
    assert "MOTION block is truncated" in reasons["truncated.bvh"]
    assert "declares 171 frames but file contains 166" in reasons["short.bvh"]
    assert "values per frame but the hierarchy declares" in reasons["values.bvh"]
    assert "CHANNELS declares 3 channels but lists 2" in reasons["channels.bvh"]


# ----------------------------------------------------------------------------- CLI


@pytest.fixture
def run(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    runner = CliRunner()
    return lambda *args: runner.invoke(app, [str(a) for a in args])


def test_cli_prepare_bvh_then_read(run, tmp_path, bvh_dir):
    labels = _labels(tmp_path / "labels.csv", [("002_01.bvh", "walk"), ("002_03.bvh", "run"), ("002_04.bvh", "jump")])
    res = run("data", "prepare", bvh_dir, "--format", "bvh", "--labels", labels, "--skeleton", "humanact12",
              "--fps", 20, "--out", tmp_path / "DATA")
    assert res.exit_code == 0, res.output
    assert "3 clips in 3 actions" in " ".join(res.output.split())
    from odmo_cli.data.locate import resolve

    manifest, root = resolve(str(tmp_path / "DATA"))
    clips = read_dataset(root, manifest)  # strict: trainable as is
    assert len(clips) == 3 and manifest.skeleton_name == "humanact12"


def test_cli_prepare_bvh_nothing_readable(run, tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    (src / "a.bvh").write_text(TWO_JOINTS.replace("Frames: 3", "Frames: 9"))
    labels = _labels(tmp_path / "l.csv", [("a.bvh", "walk")])
    res = run("data", "prepare", src, "--format", "bvh", "--labels", labels, "--skeleton", "humanact12",
              "--out", tmp_path / "DATA")
    assert res.exit_code == 2
    assert "a.bvh" in res.output and "Traceback" not in res.output
    assert not (tmp_path / "DATA").exists()


def test_cli_prepare_bvh_joint_map(run, tmp_path):
    """A user map for a hierarchy with no built-in map: the humanact12 export re-imported."""
    sk = get_skeleton("humanact12")
    src = tmp_path / "src"
    src.mkdir()
    motion = rigid_motion("humanact12", frames=10)
    bvh = motion_to_bvh(motion, sk, fps=20, options=EXACT)
    bvh.nodes = [n for n in bvh.nodes]  # rename the joints to names no built-in map knows
    for n in bvh.nodes:
        n.name = "x_" + n.name
    write_bvh(src / "x.bvh", bvh)
    jm = tmp_path / "map.toml"
    jm.write_text('skeleton = "humanact12"\n[joints]\n' + "".join(f'{n} = "x_{b}"\n' for n, b in zip(sk.joint_names, sk.bvh_names)))
    labels = _labels(tmp_path / "l.csv", [("x.bvh", "jump")])
    res = run("data", "prepare", src, "--format", "bvh", "--labels", labels, "--joint-map", jm,
              "--unit", "m", "--out", tmp_path / "DATA")
    assert res.exit_code == 0, res.output
    got = np.load(tmp_path / "DATA" / "x.npy")
    # same up axis (-y) and units; the horizontal heading may differ by a turn about the up axis
    np.testing.assert_allclose(got[..., 1] - got[:1, :1, 1], motion[..., 1] - motion[:1, :1, 1], atol=1e-4)


def test_bad_joint_map(run, tmp_path):
    jm = tmp_path / "map.toml"
    jm.write_text('skeleton = "humanact12"\n[joints]\npelvis = "Hips"\n')
    src = tmp_path / "src"
    src.mkdir()
    (src / "a.bvh").write_text(TWO_JOINTS)
    res = run("data", "prepare", src, "--format", "bvh", "--labels", _labels(tmp_path / "l.csv", [("a", "walk")]),
              "--joint-map", jm, "--out", tmp_path / "DATA")
    assert res.exit_code == 2 and "missing left_hip" in res.output


def _samples(path, n=2, frames=6):
    sk = get_skeleton("humanact12")
    motions = np.stack([rigid_motion("humanact12", frames, seed=i) for i in range(n)]).astype(np.float32)
    ends = motions[:, -1, 0].copy()
    np.savez(path, motions=motions, actions=np.array(["walk"] * n), fps=np.float32(20),
             skeleton=np.str_("humanact12"), joint_names=np.array(sk.joint_names), parents=np.array(sk.parents),
             up_axis=np.str_("-y"), end_points=ends)
    return path


def test_render_writes_gif(run, tmp_path):
    samples = _samples(tmp_path / "s.npz")
    res = run("render", samples, "--out", tmp_path / "a.gif", "--grid", "1x2", "--trail")
    assert res.exit_code == 0, res.output
    from PIL import Image

    with Image.open(tmp_path / "a.gif") as im:
        assert im.n_frames == 6 and im.size[0] > 100
    res = run("render", samples, "--out", tmp_path / "b.gif", "--index", 1)
    assert res.exit_code == 0 and (tmp_path / "b.gif").stat().st_size > 0


def test_render_mp4_or_fallback(run, tmp_path, monkeypatch):
    from matplotlib import animation

    monkeypatch.setattr(animation.writers, "is_available", lambda name: False)
    res = run("render", _samples(tmp_path / "s.npz"), "--out", tmp_path / "a.mp4")
    assert res.exit_code == 0, res.output
    assert (tmp_path / "a.gif").stat().st_size > 0 and not (tmp_path / "a.mp4").exists()
    assert "ffmpeg" in res.output


def test_render_size_and_still_frame(run, tmp_path):
    from PIL import Image

    samples = _samples(tmp_path / "s.npz")
    res = run("render", samples, "--out", tmp_path / "a.gif", "--grid", "1x2", "--size", "300x200")
    assert res.exit_code == 0, res.output
    with Image.open(tmp_path / "a.gif") as im:
        assert im.size == (300, 200) and im.n_frames == 6
    stills = {}
    for k in (0, 5):
        out = tmp_path / f"f{k}.png"
        res = run("render", samples, "--out", out, "--frame", k, "--size", "320x240")
        assert res.exit_code == 0, res.output
        with Image.open(out) as im:
            assert im.size == (320, 240)
            stills[k] = np.asarray(im.convert("L"), dtype=float)
    assert np.abs(stills[0] - stills[5]).mean() > 0.1  # a different pose is drawn


def test_render_compare_real(run, tmp_path, humanact12_dir):
    from PIL import Image

    samples = _samples(tmp_path / "s.npz", n=2)  # two walks of the humanact12 skeleton
    res = run("render", samples, "--out", tmp_path / "c.png", "--grid", "1x2", "--compare", "real",
              "--data", humanact12_dir, "--size", "400x400")
    assert res.exit_code == 0, res.output
    with Image.open(tmp_path / "c.png") as im:
        assert im.size == (400, 400)
    from odmo_cli.geometry.skeletons import get_skeleton
    from odmo_cli.formats.viz import real_examples

    real = real_examples(None, get_skeleton("humanact12"), ["walk", "jump"], 60, humanact12_dir, seed=0)
    assert real.shape == (2, 60, 24, 3) and np.allclose(real[:, 0, 0], 0)
    again = real_examples("humanact12", get_skeleton("humanact12"), ["walk", "jump"], 60, humanact12_dir, seed=0)
    np.testing.assert_array_equal(real, again)  # the seed picks the clips and crops
    res = run("render", samples, "--out", tmp_path / "d.png", "--compare", "real", "--data", tmp_path / "nothing")
    assert res.exit_code == 2 and not (tmp_path / "d.png").exists()


@pytest.mark.parametrize("args, fragment", [
    (("--index", 5), "out of range"), (("--grid", "4y5"), "ROWSxCOLS"), (("--index", 0, "--grid", "1x1"), "either"),
    (("--frame", 3), "--frame makes a still"), (("--size", "big"), "WIDTHxHEIGHT"),
    (("--compare", "fake"), "valid: real"),
])
def test_render_bad_options(run, tmp_path, args, fragment):
    res = run("render", _samples(tmp_path / "s.npz"), "--out", tmp_path / "a.gif", *args)
    assert res.exit_code == 2 and fragment in res.output
    assert not list(tmp_path.glob("*.gif")) and not list(tmp_path.glob(".a.gif*"))


def test_render_bad_extension(run, tmp_path):
    res = run("render", _samples(tmp_path / "s.npz"), "--out", tmp_path / "a.avi")
    assert res.exit_code == 2 and ".gif, .mp4" in res.output


def test_cli_export(run, tmp_path):
    import json

    res = run("export", _samples(tmp_path / "s.npz", n=3), "--bvh", tmp_path / "bvh", "--json", "--helper-joints")
    assert res.exit_code == 0, res.output
    files = sorted((tmp_path / "bvh").glob("*.bvh"))
    assert [f.name for f in files] == ["000_walk.bvh", "001_walk.bvh", "002_walk.bvh"]
    out = json.loads(res.output)
    assert out["max_error_mm"] < 1.0 and out["joints"] == 30 and out["units"] == "cm"
    # without helpers, these random torsos (hips and collars turning 0.4 rad against each other) cannot be exact
    res = run("export", tmp_path / "s.npz", "--bvh", tmp_path / "bvh2", "--json", "--units", "m")
    out = json.loads(res.output)
    assert out["joints"] == 24 and out["units"] == "m" and out["max_error_mm"] > 10
    res = run("export", tmp_path / "s.npz", "--bvh", tmp_path / "bvh3", "--units", "mm")
    assert res.exit_code == 2 and "unknown units 'mm'; valid: cm, m" in res.output
    assert not (tmp_path / "bvh3").exists()
    res = run("export", tmp_path / "missing.npz", "--bvh", tmp_path / "b2")
    assert res.exit_code == 2 and "not found" in res.output


def test_unreadable_bvh_is_user_error(tmp_path):
    path = tmp_path / "x.bvh"
    path.write_text("HIERARCHY\nROOT a\n{\n OFFSET 0 0\n")
    with pytest.raises(UserError, match="x.bvh"):
        read_bvh(path)


def test_generated_jump_exports_for_animation_tools(run, tmp_path):
    """`odmo sample --action jump --bvh DIR` on the shipped model: 24 joints, centimetres, on the floor."""
    res = run("sample", "--action", "jump", "--n", "2", "--out", tmp_path / "jump.npz", "--bvh", tmp_path / "bvh")
    assert res.exit_code == 0, res.output
    files = sorted((tmp_path / "bvh").glob("*.bvh"))
    assert len(files) == 2
    sk = get_skeleton("humanact12")
    for f in files:
        parsed = _parse_bvh(f.read_text())
        names, positions = _fk(parsed)  # (F, 24, 3), file units
        assert len(names) == 24 and sorted(names) == sorted(sk.bvh_names)
        assert parsed["frames"] == 60 and parsed["frame_time"] == pytest.approx(1 / 20, abs=1e-6)
        feet = [names.index(n) for n in ("LeftFoot", "RightFoot", "LeftToeBase", "RightToeBase")]
        assert abs(positions[:, feet, 1].min()) <= 1.0  # the lowest foot on the floor, within 1 cm
        head = names.index("Head")
        height = np.median(positions[:, head, 1] - positions[:, feet, 1].min(1))
        assert 100 < height < 200  # a standing person's head, in centimetres
        # the character faces +z (forward = left x up), what docs/formats.md tells Blender users
        left = positions[:, names.index("LeftUpLeg")] - positions[:, names.index("RightUpLeg")]
        assert np.cross(left, [0.0, 1.0, 0.0])[:, 2].mean() > 0
