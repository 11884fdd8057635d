"""Long motions (`odmo compose`, generation/compose.py and seam.py): the spec, segments of the asked
lengths and actions, a root and body that carry on across every boundary, a given start kept exactly,
the same bytes for a seed, the errors; and the measurements' own arithmetic (evaluation/composition.py).

They run on the shipped models and the shipped demo clips (no data folder needed)."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from odmo_cli.checkpoint import load_checkpoint, load_odmo, save_checkpoint, shipped_file
from odmo_cli.cli import app
from odmo_cli.data.demo import demo_folder, load_demo
from odmo_cli.errors import UserError
from odmo_cli.evaluation.composition import peaks, segment_windows, specs
from odmo_cli.generation.compose import START_LABEL, ComposeConfig, compose, parse_spec, read_start
from odmo_cli.generation.seam import fade, heading, ramp, settle_feet, splice_path, turn
from odmo_cli.geometry.skeletons import get_skeleton

pytestmark = pytest.mark.skipif(shipped_file("humanact12") is None or shipped_file("cmu") is None,
                                reason="needs the shipped models in odmo_cli/assets/models")


@pytest.fixture(scope="module")
def human():
    return load_odmo("humanact12")


@pytest.fixture(scope="module")
def cmu():
    return load_odmo("cmu")


def largest_real_root_step(name: str) -> float:
    """The largest frame-to-frame root step (3-D) in the shipped demo clips of a dataset."""
    clips = load_demo(name)
    return max(float(np.linalg.norm(np.diff(m[:, 0], axis=0), axis=-1).max()) for m in clips.motions)


# -- the spec -------------------------------------------------------------------------------------

def test_the_spec_is_read_segment_by_segment():
    segs = parse_spec(" walk 4s, sit,drink#1 2.5s to 1.5,-0.5 , lift dumbbell 80f, run to .5,2")
    assert [s.action for s in segs] == ["walk", "sit", "drink", "lift dumbbell", "run"]
    assert [s.mode for s in segs] == [None, None, 1, None, None]
    assert [s.seconds for s in segs] == [4.0, None, 2.5, None, None]
    assert [s.frames for s in segs] == [None, None, None, 80, None]
    assert [s.end for s in segs] == [None, None, (1.5, -0.5), None, (0.5, 2.0)]


@pytest.mark.parametrize("kw, message", [({"method": "glue"}, "method must be one of primed, paste; got 'glue'"),
                                        ({"prime": 1}, "prime must be at least 2; got 1"),
                                        ({"blend": 8, "longest": 6}, "longest must be at least 8; got 6")])
def test_compose_config_names_the_setting_it_refuses(kw, message):
    from odmo_cli.config import ConfigError

    with pytest.raises(ConfigError, match=re.escape(message)):
        ComposeConfig(**kw)


@pytest.mark.parametrize("spec", ["", "walk 4s; sit", "walk 4x", "walk, , sit", "walk 0s", "walk 2.5f", "#1 walk",
                                  "walk to 1", "walk to 1,a"])
def test_a_spec_it_cannot_read_is_one_user_error(spec):
    with pytest.raises(UserError):
        parse_spec(spec)


# -- segments, continuity, seeds (library) -----------------------------------------------------

def test_segments_have_the_asked_lengths_and_labels(human):
    c = compose(human, "walk 4s, sit, drink 2s, jump 23f", n=3, seed=0)
    assert c.segments.tolist() == [[0, 80], [80, 140], [140, 180], [180, 203]]  # 20 fps, T = 60
    assert c.motions.shape == (3, 203, 24, 3) and c.motions.dtype == np.float32
    assert c.segment_actions.tolist() == ["walk", "sit", "drink", "jump"]
    for (a, b), name in zip(c.segments, c.segment_actions):
        assert set(c.frame_actions[a:b]) == {name}
    assert np.all(np.isfinite(c.motions)) and np.abs(c.motions[:, 0, 0]).max() == 0  # first root at the origin
    modes = c.segment_modes
    assert modes.shape == (3, 4) and all(0 <= m < len(human.action_modes(human.action_index(a)).means)
                                         for row in modes for m, a in zip(row, c.segment_actions))


@pytest.mark.parametrize("name, spec", [("humanact12", "walk 4s, sit, boxing, throw 2s, jump"),
                                        ("cmu", "walk 10s, run, jump, dance 3s")])
def test_the_root_is_continuous_across_every_boundary(name, spec, human, cmu):
    """No root step across a boundary (segment or window) larger than the largest real one; the body
    joins far more smoothly than the cut-and-paste baseline's."""
    loaded = human if name == "humanact12" else cmu
    T = loaded.model.cfg.length
    c = compose(loaded, spec, n=6, seed=3)
    root_step = np.linalg.norm(np.diff(c.motions[:, :, 0], axis=1), axis=-1)  # (K, L-1)
    limit = largest_real_root_step("humanact12" if name == "humanact12" else "cmu_mocap")
    joins = sorted({int(b) for b in c.segments[1:, 0]} | {int(a) + T * i for a, b in c.segments
                                                            for i in range(1, math.ceil((b - a) / T))})
    assert joins and all(root_step[:, j - 1].max() <= limit for j in joins), (root_step[:, [j - 1 for j in joins]], limit)
    paste = compose(loaded, spec, n=6, seed=3, cfg=ComposeConfig(method="paste"))
    body = lambda m: np.linalg.norm(np.diff(m, axis=1), axis=-1).max(-1)  # noqa: E731  (K, L-1) largest joint step
    seams = [int(b) - 1 for b in c.segments[1:, 0]]
    assert body(c.motions)[:, seams].mean() < 0.5 * body(paste.motions)[:, seams].mean()


def test_heading_carries_on_across_a_boundary(human):
    """The body faces where it faced: the turn between the last frame of a segment and the first of the
    next is no larger than the largest turn between two frames inside the segments."""
    sk = get_skeleton("humanact12")
    c = compose(human, "walk, warm up, walk", n=6, seed=1)
    yaw = heading(torch.from_numpy(c.motions), sk).numpy()  # (K, L)
    turn_per_frame = np.abs(np.angle(np.exp(1j * np.diff(yaw, axis=1))))  # (K, L-1)
    seams = [int(b) - 1 for b in c.segments[1:, 0]]
    inside = np.delete(turn_per_frame, seams, axis=1)
    assert turn_per_frame[:, seams].max() <= inside.max()


def test_an_end_point_is_reached(human):
    c = compose(human, "walk 3s to 0.5,0.3, sit, walk 2s to -0.2,0.1", n=4, seed=2)
    reached = c.reached()[:, :, [0, 2]]  # HumanAct12's ground plane: x, z
    assert np.allclose(reached[:, 0], [0.5, 0.3], atol=1e-4) and np.allclose(reached[:, 2], [-0.2, 0.1], atol=1e-4)
    assert np.isnan(c.segment_ends[1]).all() and np.isnan(c.segment_ends[0, 1])  # sit asked none; no height asked


def test_a_real_clip_given_as_start_is_kept_exactly(human, tmp_path):
    clip = sorted(demo_folder("humanact12").glob("*.npy"))[3]
    start = read_start(clip, human)
    raw = np.load(clip).astype(np.float32)
    assert np.array_equal(start, raw)
    c = compose(human, "jump, walk 2s", n=2, seed=0, start=start)
    L0 = len(raw)
    assert c.prefix_frames == L0 and c.motions.shape[1] == L0 + 100
    for k in range(2):
        assert np.array_equal(c.motions[k, :L0], raw - raw[:1, :1])
    assert set(c.frame_actions[:L0]) == {START_LABEL} and c.segments.tolist() == [[L0, L0 + 60], [L0 + 60, L0 + 100]]
    step = np.linalg.norm(np.diff(c.motions[:, L0 - 1:L0 + 1, 0], axis=1), axis=-1)
    assert step.max() <= largest_real_root_step("humanact12")


def test_the_same_seed_gives_the_same_motion_and_another_seed_another(human):
    a = compose(human, "walk 2s, jump", n=2, seed=5)
    b = compose(human, "walk 2s, jump", n=2, seed=5)
    c = compose(human, "walk 2s, jump", n=2, seed=6)
    assert np.array_equal(a.motions, b.motions) and not np.allclose(a.motions, c.motions)
    assert not np.allclose(a.motions[0], a.motions[1])  # --n gives different sequences


def test_a_mode_is_kept_for_the_whole_segment(human):
    c = compose(human, "walk#2 5s, jump#0", n=4, seed=0)
    assert (c.segment_modes[:, 0] == 2).all() and (c.segment_modes[:, 1] == 0).all()


# -- the command ---------------------------------------------------------------------------------

def test_compose_writes_a_samples_file_that_export_and_render_read(tmp_path):
    out = tmp_path / "seq.npz"
    runner = CliRunner()
    res = runner.invoke(app, ["compose", "walk 2s, sit, drink 1s to 0.3,0.2", "--n", "2", "--out", str(out), "--json"])
    assert res.exit_code == 0, res.output
    with np.load(out) as f:
        assert f["motions"].shape == (2, 120, 24, 3)
        assert f["actions"].tolist() == ["walk+sit+drink"] * 2
        assert f["segments"].tolist() == [[0, 40], [40, 100], [100, 120]]
        assert f["frame_actions"].shape == (120,) and f["frame_actions"][39] == "walk" and f["frame_actions"][40] == "sit"
        assert f["segment_actions"].tolist() == ["walk", "sit", "drink"] and f["segment_modes"].shape == (2, 3)
        assert np.allclose(f["segment_end_points"][2, [0, 2]], [0.3, 0.2]) and int(f["prefix_frames"]) == 0
        assert np.allclose(f["end_points"][:, [0, 2]], [0.3, 0.2]) and f["end_mask"][:, [0, 2]].all()
        assert str(f["spec"]) == "walk 2s, sit, drink 1s to 0.3,0.2" and str(f["method"]) == "primed"
    res = runner.invoke(app, ["export", str(out), "--bvh", str(tmp_path / "bvh")])
    assert res.exit_code == 0, res.output
    files = sorted(p.name for p in (tmp_path / "bvh").iterdir())
    assert files == ["000_walk_sit_drink.bvh", "001_walk_sit_drink.bvh"]
    assert "within 0.00 mm" in " ".join(res.stdout.split())  # rigid bones throughout: the BVH is exact
    res = runner.invoke(app, ["render", str(out), "--out", str(tmp_path / "still.png"), "--frame", "50"])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "still.png").stat().st_size > 0


def test_start_from_a_bvh_and_a_samples_file(tmp_path):
    runner = CliRunner()
    first = tmp_path / "first.npz"
    assert runner.invoke(app, ["compose", "walk 2s", "--out", str(first)]).exit_code == 0
    assert runner.invoke(app, ["export", str(first), "--bvh", str(tmp_path / "bvh")]).exit_code == 0
    for given in (first, tmp_path / "bvh" / "000_walk.bvh"):
        out = tmp_path / f"more_{given.suffix[1:]}.npz"
        res = runner.invoke(app, ["compose", "jump", "--start-from", str(given), "--out", str(out)])
        assert res.exit_code == 0, res.output
        with np.load(out) as f, np.load(first) as g:
            assert int(f["prefix_frames"]) == 40 and f["motions"].shape[1] == 100
            # the samples file comes back exactly; the BVH within its export error (it was exact: rigid bones)
            assert np.allclose(f["motions"][0, :40], g["motions"][0], atol=1e-4 if given.suffix == ".bvh" else 0)


def test_same_seed_same_bytes(tmp_path):
    runner = CliRunner()
    paths = [tmp_path / f"{name}.npz" for name in ("a", "b", "c")]
    for path, seed in zip(paths, ("4", "4", "5")):
        res = runner.invoke(app, ["compose", "walk 2s, jump", "--n", "2", "--seed", seed, "--out", str(path)])
        assert res.exit_code == 0, res.output
    assert paths[0].read_bytes() == paths[1].read_bytes() != paths[2].read_bytes()


@pytest.fixture(scope="module")
def without_end_points(tmp_path_factory) -> Path:
    """The shipped HumanAct12 model as if trained without end-point conditioning (the paper's -r_e)."""
    ckpt = load_checkpoint(shipped_file("humanact12"))
    ckpt["config"] = {**ckpt["config"], "use_end_point": False}
    path = tmp_path_factory.mktemp("no_end") / "no_end.pt"
    save_checkpoint(path, ckpt)
    return path


@pytest.mark.parametrize("args, says", [
    (["walk 2s, sitt"], "unknown action 'sitt' in segment 2, 'sitt'; valid: warm_up, walk, run, jump, drink, "
                        "lift_dumbbell, sit, eat, turn_steering_wheel, phone, boxing, throw"),
    (["walk 0.2s, sit"], "segment 1, 'walk 0.2s' lasts 4 frames (0.2 s), shorter than the transition of 6 frames"),
    (["walk 4s; sit"], "cannot read segment 1, 'walk 4s; sit'; write ACTION[#MODE] [DURATION] [to X,Z]"),
    (["walk#9"], "mode 9 in segment 1, 'walk#9' is out of range: walk has"),
    (["walk to 1,0", "--model", "NOEND"], "segment 1, 'walk to 1,0' asks for an end point, but no_end.pt was "
                                           "trained without end-point conditioning"),
    (["walk", "--method", "glue"], "--method must be one of primed, paste; got 'glue'"),
    (["walk", "--start-from", "missing.npz"], "--start-from: file not found"),
    (["walk", "--start-from", "START_TXT"], "--start-from must be a samples .npz, a (frames, joints, 3) .npy or a .bvh"),
    (["walk", "--start-from", "CMU_NPY"], "the motion to start from must be (frames, 24, 3)"),
])
def test_errors_are_one_line_exit_2_and_write_nothing(args, says, tmp_path, monkeypatch, without_end_points):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "in").mkdir()
    text = tmp_path / "in" / "start.txt"
    text.write_text("not a motion")
    cmu_clip = sorted(demo_folder("cmu").glob("*.npy"))[0]
    swap = {"NOEND": str(without_end_points), "START_TXT": str(text), "CMU_NPY": str(cmu_clip)}
    out = tmp_path / "out"
    out.mkdir()
    res = CliRunner().invoke(app, ["compose", *[swap.get(a, a) for a in args], "--out", str(out / "seq.npz")])
    assert res.exit_code == 2, res.output
    assert res.stderr.startswith("error: ") and says in res.stderr, res.stderr
    assert res.stderr.count("\n") == 1 and "Traceback" not in res.output
    assert list(out.iterdir()) == []


def test_a_baseline_model_is_refused(tmp_path):
    from odmo_cli.evaluation.bench import random_checkpoint

    res = CliRunner().invoke(app, ["compose", "walk", "--model", str(random_checkpoint("humanact12", tmp_path)),
                                   "--out", str(tmp_path / "ok.npz")])
    assert res.exit_code == 0, res.output  # an ODMO file of any weights composes
    ckpt = load_checkpoint(tmp_path / "random_humanact12.pt")
    ckpt["kind"] = "dvgan"
    save_checkpoint(tmp_path / "dvgan.pt", ckpt)
    res = CliRunner().invoke(app, ["compose", "walk", "--model", str(tmp_path / "dvgan.pt"), "--out", str(tmp_path / "x.npz")])
    assert res.exit_code == 2 and "needs an ODMO checkpoint" in res.stderr and not (tmp_path / "x.npz").exists()


# -- the seam's geometry --------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["humanact12", "cmu"])
@pytest.mark.parametrize("primed", [False, True])
def test_a_window_cut_short_is_the_whole_windows_first_frames(primed, name, human, cmu):
    # the decoder is causal: drawing only the frames a window keeps changes none of them (bones as drawn;
    # a rigid model's first window takes its body from all T frames, so it is drawn whole)
    from odmo_cli.generation.compose import _Windows

    loaded = human if name == "humanact12" else cmu
    win = _Windows(loaded, ComposeConfig())
    g = torch.Generator().manual_seed(0)
    z = torch.randn(3, loaded.model.cfg.latent_dim, generator=g)
    cond = win._cond(z, torch.tensor([0, 1, 2]))
    path = win._path(cond, torch.zeros(3, 3))
    primer = torch.randn(3, 2, loaded.model.cfg.n_joints, 3, generator=g) if primed else None
    whole = win._decode(cond, path, primer, rigid=False)
    cut = win._decode(cond, path, primer, rigid=False, steps=37)
    assert cut.shape[1] == 37 and whole.shape[1] == path.shape[1]
    torch.testing.assert_close(cut, whole[:, :37])


def test_the_feet_settle_from_the_frames_as_read_out(human, monkeypatch):
    # settle_feet's contract: faded = new + offset * a weight per frame; a rigid model's frames must be
    # compared as its body reads them, or the settled foot jumps where the glide ends
    import odmo_cli.generation.compose as compose_module

    seen = []

    def record(faded, new, offset, *args):
        seen.append((faded - new, offset))
        return settle_feet(faded, new, offset, *args)

    monkeypatch.setattr(compose_module, "settle_feet", record)
    compose(human, "walk, sit 30f", n=3, seed=0)
    (diff, offset), = seen  # (K, m, J, 3), (K, J, 3)
    w = (diff * offset[:, None]).sum((-1, -2)) / (offset * offset).sum((-1, -2))[:, None]  # (K, m)
    torch.testing.assert_close(diff, w[..., None, None] * offset[:, None], atol=1e-5, rtol=0)
    assert float(w[:, 0].min()) > 0.9 and float(w[:, -1].abs().max()) < 1e-6


def test_a_turn_about_the_up_axis_turns_the_heading_and_keeps_lengths():
    sk = get_skeleton("humanact12")  # -y up: the ground plane is x, z
    pose = torch.from_numpy(load_demo("humanact12").motions[0][:1].astype(np.float64))  # (1, J, 3)
    for yaw in (0.3, -2.0, 3.0):
        rot = turn(torch.tensor([yaw], dtype=torch.float64), sk.up_index)
        assert torch.allclose(rot[0] @ rot[0].T, torch.eye(3, dtype=torch.float64)) and torch.det(rot[0]) > 0
        turned = torch.einsum("kjd,kcd->kjc", pose, rot)
        change = (heading(turned, sk) - heading(pose, sk) + math.pi) % (2 * math.pi) - math.pi
        assert abs(float(change) - yaw) < 1e-9
        assert torch.allclose(turned[..., 1], pose[..., 1])  # heights stay


def test_fade_and_ramp():
    w = ramp(10, 4)
    assert torch.all((w[:4] > 0) & (w[:4] < 1)) and torch.all(w[4:] == 1) and torch.all(torch.diff(w) >= 0)
    new = torch.zeros(2, 10, 3, 3)
    offset = torch.ones(2, 3, 3)
    out = fade(new, offset, torch.tensor([2, 6]))  # a length per sequence
    assert torch.all(out[0, 2:] == 0) and torch.all(out[1, 6:] == 0) and torch.all(out[1, :6] > 0)
    smooth = lambda x: x * x * (3 - 2 * x)  # noqa: E731
    assert torch.allclose(out[0, 0], torch.tensor(1 - smooth(1 / 3)))
    assert torch.allclose(out[1, 0], torch.tensor(1 - smooth(1 / 7)))


def test_a_spliced_path_continues_the_primer():
    path = torch.cumsum(torch.full((1, 12, 3), 0.1), dim=1)  # the generator's own: 0.1 a frame on every axis
    primer = torch.zeros(1, 3, 3)
    primer[0, :, 0] = torch.tensor([0.0, 0.5, 1.0])  # moving 0.5 a frame along x
    out = splice_path(path, primer, torch.tensor([0.0]), blend=4, up=1)
    assert torch.equal(out[:, :3], primer)
    step = torch.diff(out[0], dim=0)  # (11, 3)
    assert 0.1 < step[2, 0] < 0.5 and torch.allclose(step[-1, [0, 2]], torch.tensor([0.1, 0.1]))  # x fades in
    assert torch.allclose(out[0, -1, 1], path[0, -1, 1] - path[0, 0, 1])  # height: the path's own over the reference


def test_feet_glide_no_faster_than_half_the_skating_speed_and_keep_their_legs():
    from odmo_cli.measures.plausibility import SLIDE_SPEED

    sk = get_skeleton("humanact12")
    still = torch.from_numpy(load_demo("humanact12").motions[0][:1].astype(np.float32))  # (1, J, 3)
    still = still - still[:, :1]
    new = still[None].expand(1, 30, -1, -1).clone()  # the decoder standing still
    offset = torch.zeros(1, 24, 3)
    offset[..., 0] = 0.1  # the old pose 10 cm to the side (within the standing leg's reach)
    faded = fade(new, offset, 5)
    out = settle_feet(faded, new, offset, sk, fps=20.0, longest=30)
    hip, knee, ankle, toe = sk.legs[0]
    bone = lambda a, b: float(torch.linalg.vector_norm(still[0, a] - still[0, b]))  # noqa: E731
    leg = bone(hip, knee) + bone(knee, ankle)
    slide = torch.linalg.vector_norm(torch.diff(out[0, :, ankle, [0, 2]], dim=0), dim=-1)
    assert slide.max() <= 0.5 * SLIDE_SPEED * leg / 20 + 1e-6 < torch.linalg.vector_norm(
        torch.diff(faded[0, :, ankle, [0, 2]], dim=0), dim=-1).max()
    for a, b in ((hip, knee), (knee, ankle), (ankle, toe)):
        lengths = torch.linalg.vector_norm(out[0, :, a] - out[0, :, b], dim=-1)
        assert torch.allclose(lengths, torch.linalg.vector_norm(still[0, a] - still[0, b]).expand(30), atol=1e-5)


# -- the measurements' arithmetic ---------------------------------------------------------------

def test_peaks_of_a_motion_of_known_speed():
    t = np.arange(10, dtype=np.float64)
    motion = np.zeros((1, 10, 2, 3))
    motion[0, :, 1, 0] = 0.1 * t  # joint 1 at 0.1 a frame
    motion[0, 5:, 1, 0] += 0.2  # and one jump of 0.2 into frame 5
    speed, accel = peaks(motion, fps=20.0)
    assert np.isnan(speed[0, 0]) and np.isnan(accel[0, 0]) and np.isnan(accel[0, -1])
    assert np.allclose(speed[0, [1, 2, 9]], 2.0) and np.isclose(speed[0, 5], 6.0)
    assert np.allclose(accel[0, [1, 2, 8]], 0.0) and np.isclose(accel[0, 4], 80.0) and np.isclose(accel[0, 5], 80.0)


def test_specs_put_every_action_at_every_place():
    plans = specs(7, 3, np.random.default_rng(0))
    assert len(plans) == 7 and all(len(set(p)) == 3 for p in plans)
    for place in range(3):
        assert sorted(p[place] for p in plans) == list(range(7))


def test_segment_windows_are_turned_back_and_start_at_the_origin(human):
    c = compose(human, "walk 66f, jump 66f", n=2, seed=0)  # T + one transition: one window each
    windows, which = segment_windows(c, 60, 6)
    assert windows.shape == (4, 60, 24, 3) and which.tolist() == [0, 0, 1, 1]
    assert np.abs(windows[:, 0, 0]).max() < 1e-6
    # the second segment's window, turned back by its yaw, faces as the model drew it: its heading at its
    # first frame differs from the composition's by exactly that yaw
    sk = get_skeleton("humanact12")
    first = 66 + 6
    drawn = heading(torch.from_numpy(windows[2:, 0]).double(), sk)
    placed = heading(torch.from_numpy(c.motions[:, first]).double(), sk)
    assert np.allclose(np.angle(np.exp(1j * (placed - drawn).numpy())), c.yaw[:, first], atol=1e-4)


def test_bench_times_a_composition_beside_single_clip_sampling(monkeypatch):
    from odmo_cli.evaluation import bench

    monkeypatch.setattr(bench, "COMPOSE_SECONDS", 6)
    monkeypatch.setattr(bench, "COMPOSE_SEQUENCES", 2)
    ours, single, ratio = bench.bench_composition(shipped_file("humanact12"), 2, "", torch.device("cpu"))
    assert ours.name == "`odmo compose` after load: 2 compositions of 6 s (120 frames, 2 segments)"
    assert single.name == "single-clip sampling, 720 frames (1 clips per action)"
    assert ours.unit == single.unit == "frames/s" and len(ours.runs) == len(single.runs) == 2
    assert ratio.runs == pytest.approx([a / b for a, b in zip(ours.runs, single.runs)])
