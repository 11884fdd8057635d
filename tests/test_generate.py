"""Sampling, interpolation and end-point customisation (issue: on-demand generation), and the data the mode
mixtures are fitted on; mode discovery itself is tested in test_latent.py."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from odmo_cli.cli import app
from odmo_cli.checkpoint import load_model, load_odmo
from odmo_cli.errors import UserError
from odmo_cli.generation.generate import interpolate, parse_point, sample
from odmo_cli.geometry.skeletons import get_skeleton

# -- parsing ---------------------------------------------------------------------------------

def test_parse_point():
    p, axes = parse_point("1,2", up_axis=1)
    assert axes == (0, 2) and p[0] == 1 and np.isnan(p[1]) and p[2] == 2
    p, axes = parse_point("1,2,3", up_axis=1)
    assert axes == (0, 1, 2) and p.tolist() == [1, 2, 3]


# -- sampling with a trained tiny model ------------------------------------------------------

def test_end_points_are_reached(lines_model):
    loaded = load_odmo(lines_model)
    batch = sample(loaded, ["glide"], 10, seed=0, end="0.6,-0.4")
    assert batch.dist_e() < 0.01, batch.dist_e()
    far = sample(loaded, ["glide"], 10, seed=0, end="-0.6,0.4")
    assert np.linalg.norm(far.reached[:, [0, 2]].mean(0) - [-0.6, 0.4]) < 0.1


def test_root_readout_is_chosen_at_load(lines_model, tmp_path):
    """The default readout puts the root on the trajectory (the end point is the trajectory's);
    --root decoder gives the pose decoder's own root and the same body about it."""
    placed, own = load_odmo(lines_model), load_odmo(lines_model, root="decoder")
    assert placed.model.cfg.root == "trajectory" and own.model.cfg.root == "decoder"
    a = sample(placed, ["glide"], 5, seed=0, end="0.6,-0.4").motions
    b = sample(own, ["glide"], 5, seed=0, end="0.6,-0.4").motions
    assert not np.allclose(a[:, :, 0], b[:, :, 0], atol=1e-4)
    assert np.allclose(a - a[:, :, :1], b - b[:, :, :1], atol=1e-5)
    # ground: the path on the ground plane, the decoder's own height
    ground = load_odmo(lines_model, root="ground")
    c = sample(ground, ["glide"], 5, seed=0, end="0.6,-0.4").motions
    up = get_skeleton(ground.dataset["skeleton"]).up_index
    flat = [i for i in range(3) if i != up]
    assert np.allclose(c[:, :, 0][..., flat], a[:, :, 0][..., flat], atol=1e-5)
    assert np.allclose(c[:, :, 0, up], b[:, :, 0, up], atol=1e-5)
    assert np.allclose(c - c[:, :, :1], a - a[:, :, :1], atol=1e-5)
    res = CliRunner().invoke(app, ["sample", "--model", str(lines_model), "--action", "glide", "--n", "5",
                                   "--end", "0.6,-0.4", "--root", "decoder", "--out", str(tmp_path / "d.npz")])
    assert res.exit_code == 0, res.output
    with np.load(tmp_path / "d.npz") as d:
        assert np.allclose(d["motions"], b, atol=1e-5) and str(d["root"]) == "decoder"  # the file says which
    res = CliRunner().invoke(app, ["interpolate", "--model", str(lines_model), "--action", "glide", "--steps", "3",
                                   "--out", str(tmp_path / "i.npz")])
    assert res.exit_code == 0, res.output
    assert str(np.load(tmp_path / "i.npz")["root"]) == "trajectory"


def test_root_readout_refused_where_it_does_not_apply(lines_model, noise_checkpoint, tmp_path):
    res = CliRunner().invoke(app, ["sample", "--model", str(lines_model), "--action", "glide", "--root", "hips",
                                   "--out", str(tmp_path / "x.npz")])
    assert res.exit_code == 2 and res.stderr.count("\n") == 1
    assert "unknown --root 'hips'; valid: trajectory, decoder" in res.stderr and "Traceback" not in res.stderr
    with pytest.raises(UserError, match="--root is ODMO's"):
        load_model(noise_checkpoint, root="decoder")
    assert not (tmp_path / "x.npz").exists()


def test_end_segment_protocol(lines_model):
    batch = sample(load_odmo(lines_model), ["crouch"], 3, seed=1, end_from="0,0", end_to="1,1", steps=5)
    assert len(batch.motions) == 15
    assert np.allclose(batch.end_points[::3, [0, 2]], np.linspace(0, 1, 5)[:, None].repeat(2, 1))


def test_mode_samples_come_from_that_mode(lines_model):
    loaded = load_odmo(lines_model)
    k = len(loaded.action_modes(0).means)
    for m in range(k):
        batch = sample(loaded, ["glide"], 5, seed=0, mode=m)
        assert (batch.modes == m).all()
        modes = loaded.action_modes(0)
        nearest = np.linalg.norm(batch.codes[:, None] - modes.means[None], axis=-1).argmin(1)
        assert (nearest == m).mean() >= 0.8


def sha(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_same_seed_same_bytes(lines_model, tmp_path):
    runner = CliRunner()
    outs = []
    for name, seed in (("a", "3"), ("b", "3"), ("c", "4")):
        out = tmp_path / f"{name}.npz"
        res = runner.invoke(app, ["sample", "--model", str(lines_model), "--action", "all", "--n", "4",
                                  "--seed", seed, "--out", str(out)])
        assert res.exit_code == 0, res.output
        outs.append(out)
    assert sha(outs[0]) == sha(outs[1]) != sha(outs[2])
    data = np.load(outs[0])
    assert data["motions"].shape == (8, 12, 20, 3) and data["motions"].dtype == np.float32
    assert list(data["actions"]) == ["glide"] * 4 + ["crouch"] * 4
    assert str(data["skeleton"]) == "cmu20" and data["parents"][0] == -1 and len(data["joint_names"]) == 20
    assert data["codes"].shape == (8, 4) and data["end_points"].shape == (8, 3)
    assert float(data["fps"]) == 10 and int(data["seed"]) == 3
    # the first root of every motion sits near the origin
    assert np.abs(data["motions"][:, 0, 0]).max() < 0.3


def test_interpolation_walks_between_modes(lines_model, tmp_path):
    out = tmp_path / "mix.npz"
    res = CliRunner().invoke(app, ["interpolate", "--model", str(lines_model), "--action", "glide",
                                   "--from-code", "0", "--to-code", "3", "--steps", "6", "--out", str(out), "--json"])
    assert res.exit_code == 0, res.output
    data = np.load(out)
    loaded = load_odmo(lines_model)
    bank = loaded.bank["codes"].numpy()
    assert np.allclose(data["codes"][0], bank[0]) and np.allclose(data["codes"][-1], bank[3])
    assert np.allclose(data["codes"][2], bank[0] + 0.4 * (bank[3] - bank[0]), atol=1e-6)
    assert data["motions"].shape[0] == 6


def test_modes_command_reports_and_plots(lines_model, tmp_path):
    plot = tmp_path / "codes.png"
    res = CliRunner().invoke(app, ["modes", "--model", str(lines_model), "--json", "--plot", str(plot), "--colour", "mode"])
    assert res.exit_code == 0, res.output
    import json
    rows = json.loads(res.stdout)["actions"]
    assert [r["action"] for r in rows] == ["glide", "crouch"]
    assert all(r["true_modes"] == 2 and -1 <= r["ari"] <= 1 for r in rows)
    assert plot.stat().st_size > 1000


@pytest.mark.parametrize("args, message", [
    (["--action", "glide", "--mode", "9"], "--mode 9 is out of range"),
    (["--action", "glide", "--mode-weights", "0,0"], "--mode-weights must be non-negative numbers with a positive sum"),
    (["--action", "glide", "--mode-weights", "a,b"], "--mode-weights must be comma-separated numbers"),
    (["--action", "glide", "--end", "1"], "--end must be two (ground plane) or three comma-separated numbers"),
    (["--action", "glide", "--end", "1,x"], "--end must be two"),
    (["--action", "glide", "--n", "0"], "--n must be a positive number of motions, got 0"),
    (["--action", "jump"], "unknown action 'jump'; valid: glide, crouch, all"),
    (["--action", "glide", "--sampling", "odd"], "unknown sampling 'odd'; valid: mode-preserving, conventional"),
    (["--action", "glide", "--end-from", "0,0"], "--end-from and --end-to go together"),
])
def test_sample_bad_input(lines_model, tmp_path, args, message):
    out = tmp_path / "s.npz"
    res = CliRunner().invoke(app, ["sample", "--model", str(lines_model), "--out", str(out), *args])
    assert res.exit_code == 2, res.output
    assert message in res.stderr and res.stderr.count("\n") == 1 and "Traceback" not in res.stderr
    assert list(tmp_path.iterdir()) == []


def test_sample_unwritable_out(lines_model, tmp_path):
    out = tmp_path / "missing" / "s.npz"
    res = CliRunner().invoke(app, ["sample", "--model", str(lines_model), "--action", "glide", "--out", str(out)])
    assert res.exit_code == 2 and "does not exist" in res.stderr
    assert list(tmp_path.iterdir()) == []


def test_sample_without_model_or_with_a_bad_one(tmp_path):
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    res = CliRunner().invoke(app, ["sample", "--model", str(bad), "--action", "jump", "--out", str(tmp_path / "x.npz")])
    assert res.exit_code == 2 and "cannot load checkpoint" in res.stderr
    assert not (tmp_path / "x.npz").exists()


def test_sample_refuses_a_checkpoint_whose_config_is_invalid(lines_model, tmp_path):
    ckpt = torch.load(lines_model, weights_only=True)
    ckpt["config"]["sigma2"] = float("nan")  # a damaged or hand-edited file: nan passes `x > 0` checks
    bad = tmp_path / "bad.pt"
    torch.save(ckpt, bad)
    out = tmp_path / "s.npz"
    res = CliRunner().invoke(app, ["sample", "--model", str(bad), "--action", "glide", "--out", str(out)])
    assert res.exit_code == 2, res.output
    assert "bad.pt holds an invalid ODMO config: sigma2 must be a finite number, got nan" in res.stderr
    assert res.stderr.count("\n") == 1 and "Traceback" not in res.stderr and not out.exists()


def test_lazy_save_streams_the_same_bytes(lines_model, tmp_path):
    loaded = load_odmo(lines_model)
    eager = sample(loaded, ["all"], 7, seed=2, end="0.2,0.1")
    lazy = sample(loaded, ["all"], 7, seed=2, end="0.2,0.1", lazy=True)
    assert lazy.motions is None
    eager.save(tmp_path / "a.npz")
    lazy.save(tmp_path / "b.npz", loaded=loaded)
    a, b = np.load(tmp_path / "a.npz"), np.load(tmp_path / "b.npz")
    assert {k: np.array_equal(a[k], b[k]) for k in a.files} == {k: True for k in a.files}
    assert sha(tmp_path / "a.npz") == sha(tmp_path / "b.npz")
    assert lazy.dist_e() == pytest.approx(eager.dist_e())
    assert np.allclose(lazy.head(3, loaded), eager.motions[:3], atol=1e-5)  # a smaller batch rounds differently


# -- baselines through the same sampler --------------------------------------------------------

class _NoiseModel(torch.nn.Module):
    """A stand-in baseline: each motion is its action index plus seeded noise."""

    def __init__(self, length=5, n_joints=3):
        super().__init__()
        self.cfg = type("Cfg", (), {"length": length, "n_joints": n_joints})()

    def generate(self, labels, generator):
        noise = torch.randn(len(labels), self.cfg.length, self.cfg.n_joints, 3, generator=generator)
        return labels.float()[:, None, None, None] + 0.01 * noise


@pytest.fixture
def noise_checkpoint(tmp_path, monkeypatch):
    from odmo_cli import checkpoint

    monkeypatch.setitem(checkpoint.BASELINES, "fake", lambda ckpt: _NoiseModel(**ckpt["config"]))
    path = tmp_path / "fake.pt"
    checkpoint.save_checkpoint(path, {"kind": "fake", "config": {"length": 5, "n_joints": 3},
                           "dataset": {"name": "toy", "actions": ["walk", "jump"], "skeleton": "humanact12",
                                       "fps": 20.0, "length": 5, "up_axis": "-y"}})
    return path


def test_baseline_checkpoint_samples_through_the_common_sampler(noise_checkpoint):
    from odmo_cli.checkpoint import LoadedBaseline

    loaded = load_model(noise_checkpoint)
    assert isinstance(loaded, LoadedBaseline) and loaded.actions == ["walk", "jump"]
    batch = sample(loaded, ["all"], 4, seed=3)
    assert batch.motions.shape == (8, 5, 3, 3)
    assert list(batch.actions) == ["walk"] * 4 + ["jump"] * 4
    assert np.allclose(batch.motions[:4], 0, atol=0.1) and np.allclose(batch.motions[4:], 1, atol=0.1)
    assert (batch.modes == -1).all() and batch.codes.shape == (8, 0) and batch.dist_e() is None
    again = sample(loaded, ["jump"], 4, seed=3)
    assert not np.array_equal(again.motions, sample(loaded, ["jump"], 4, seed=4).motions)
    assert np.array_equal(again.motions, sample(loaded, ["jump"], 4, seed=3).motions)


@pytest.mark.parametrize("kwargs, flag", [({"mode": 0}, "--mode"), ({"mode_weights": [1.0]}, "--mode-weights"),
                                          ({"sampling": "conventional"}, "--sampling"), ({"end": "1,2"}, "--end")])
def test_baseline_refuses_odmo_only_options(noise_checkpoint, kwargs, flag):
    with pytest.raises(UserError, match=flag):
        sample(load_model(noise_checkpoint), ["walk"], 2, **kwargs)
    with pytest.raises(UserError, match="needs an ODMO checkpoint"):
        load_odmo(noise_checkpoint)


def test_sample_with_a_missing_model_names_the_choices(tmp_path):
    res = CliRunner().invoke(app, ["sample", "--model", str(tmp_path / "missing.pt"), "--action", "jump",
                                   "--out", str(tmp_path / "x.npz")])
    assert res.exit_code == 2
    assert "give a checkpoint file or a shipped name (humanact12, cmu)" in res.stderr
    assert not (tmp_path / "x.npz").exists()


# -- the samples file ----------------------------------------------------------------------------

def test_samples_file_records_units_version_model_and_asked_coordinates(lines_model, tmp_path):
    from odmo_cli.formats.samples import FORMAT_VERSION as SAMPLES_FORMAT_VERSION

    out = tmp_path / "s.npz"
    res = CliRunner().invoke(app, ["sample", "--model", str(lines_model), "--action", "glide", "--n", "3",
                                   "--end", "0.2,0.1", "--out", str(out)])
    assert res.exit_code == 0, res.output
    with np.load(out) as f:
        assert str(f["units"]) == "m" and int(f["format_version"]) == SAMPLES_FORMAT_VERSION == 1
        assert str(f["model"]) == "lines.pt"  # the file's name, not a path of this machine
        assert str(f["up_axis"]) == "+y"  # the lines dataset's own frame
        assert f["end_mask"].tolist() == [[True, False, True]] * 3  # x and z asked, height from the bank
        assert np.allclose(f["end_points"][:, [0, 2]], [0.2, 0.1])
    res = CliRunner().invoke(app, ["sample", "--model", str(lines_model), "--action", "glide", "--n", "2",
                                   "--out", str(out)])
    with np.load(out) as f:
        assert not f["end_mask"].any() and f["end_mask"].shape == (2, 3)


def test_up_y_turns_a_minus_y_dataset_and_reads_back(noise_checkpoint, tmp_path):
    from odmo_cli.formats.samples import read_samples

    batch = sample(load_model(noise_checkpoint), ["all"], 3, seed=0)
    batch.save(tmp_path / "own.npz")
    batch.save(tmp_path / "up.npz", up="y")
    own, up = np.load(tmp_path / "own.npz"), np.load(tmp_path / "up.npz")
    assert str(own["up_axis"]) == "-y" and str(up["up_axis"]) == "+y"
    # -y up: half a turn about x (a proper rotation, so left stays left)
    np.testing.assert_array_equal(up["motions"], own["motions"] * np.array([1, -1, -1], np.float32))
    back = read_samples(tmp_path / "up.npz", optional=("end_points",))
    np.testing.assert_array_equal(back["motions"], own["motions"])
    with pytest.raises(UserError, match="unknown --up 'z'"):
        batch.save(tmp_path / "bad.npz", up="z")
    assert not (tmp_path / "bad.npz").exists()


def test_interpolation_without_ends_blends_the_first_two_modes_or_two_codes(lines_model, tmp_path):
    loaded = load_odmo(lines_model)
    for a, name in enumerate(loaded.actions):
        k = len(loaded.action_modes(a).means)
        batch = interpolate(loaded, name, steps=4)
        assert f"{name} has {k} mode" in batch.note
        if k >= 2:  # the first two modes' means
            means = loaded.action_modes(a).means
            assert np.allclose(batch.codes[0], means[0]) and np.allclose(batch.codes[-1], means[1])
        else:  # the action's first and last latent-bank codes
            own = np.flatnonzero(loaded.bank["labels"].numpy() == a)
            bank = loaded.bank["codes"].numpy()
            assert np.allclose(batch.codes[0], bank[own[0]]) and np.allclose(batch.codes[-1], bank[own[-1]])
    res = CliRunner().invoke(app, ["interpolate", "--model", str(lines_model), "--action", "glide", "--steps", "3",
                                   "--out", str(tmp_path / "b.npz")])
    assert res.exit_code == 0, res.output
    assert "glide has" in res.stdout
    res = CliRunner().invoke(app, ["interpolate", "--model", str(lines_model), "--action", "glide", "--from-mode", "0",
                                   "--out", str(tmp_path / "c.npz")])
    assert res.exit_code == 2 and "or none of them" in res.stderr


# -- the mixtures' data: codes of random crops (the authors' release) -------------------------

def test_crop_bank_draws_class_balanced_distinct_crops_and_encodes_them(make_humanact12, tmp_path):
    from odmo_cli.data.dataset import crop_pad_shift
    from odmo_cli.data.locate import resolve
    from odmo_cli.data.readers import read_dataset
    from odmo_cli.generation.generate import crop_bank
    from odmo_cli.models.odmo import ODMO, ODMOConfig

    clips = read_dataset(*reversed(resolve(make_humanact12(tmp_path / "h", per_action=3, length=75))))
    torch.manual_seed(0)
    model = ODMO(ODMOConfig(length=60, latent_dim=4, encoder_hidden=8, encoder_fc=8, traj_hidden=8, motion_hidden=8))
    idx = np.concatenate([np.flatnonzero(clips.labels == a)[1:] for a in range(12)])  # a subset, every action
    bank = crop_bank(model, clips, idx, passes=1, rng=np.random.default_rng(0), per_pass=12 * 20)
    clip, start = bank["clip"].numpy(), bank["start"].numpy()
    assert len(set(zip(clip, start))) == len(clip)  # every crop once
    assert (start >= 0).all() and (start <= 75 - 60).all()
    assert np.array_equal(bank["labels"].numpy(), clips.labels[idx[clip]])
    # 20 draws per action over its clips' 16 starts each: most are new crops, and no action is left out
    counts = np.bincount(bank["labels"].numpy(), minlength=12)
    assert (counts > 10).all() and (counts <= 20).all()
    for r in (0, len(clip) // 2, len(clip) - 1):
        crop = torch.from_numpy(crop_pad_shift(clips.motions[idx[clip[r]]], 60, int(start[r])))[None]
        with torch.no_grad():
            mu, _ = model.encode(crop)
        assert torch.allclose(bank["codes"][r], mu[0], atol=1e-5)
        assert torch.allclose(bank["end_points"][r], crop[0, -1, 0])
    again = crop_bank(model, clips, idx, passes=1, rng=np.random.default_rng(0), per_pass=12 * 20)
    assert torch.equal(again["codes"], bank["codes"])  # the draw is the seed's


def test_end_points_are_looked_up_in_the_mixtures_data(lines_model):
    loaded = load_odmo(lines_model)
    assert loaded.crops is None and loaded.mixture_bank is loaded.bank  # trained files: one code per clip
    crops = {k: v.clone() if torch.is_tensor(v) else v for k, v in loaded.bank.items()}
    crops["end_points"][:] = torch.tensor([7.0, 0.0, -7.0])
    loaded.crops = crops
    batch = sample(loaded, ["glide"], 4, seed=0, lazy=True)
    assert np.allclose(batch.end_points, [7.0, 0.0, -7.0])
    loaded.crops = None  # one code per clip: the latent bank's real end points
    batch = sample(loaded, ["glide"], 4, seed=0, lazy=True)
    assert not np.allclose(batch.end_points, [7.0, 0.0, -7.0])


def test_modes_refit_switches_the_mixtures_data(lines_model, lines_folder, tmp_path):
    import json
    import shutil

    from odmo_cli import checkpoint
    from odmo_cli.checkpoint import load_checkpoint
    from odmo_cli.models.latent import fit_modes

    path = tmp_path / "copy.pt"
    shutil.copy(lines_model, path)
    res = CliRunner().invoke(app, ["modes", "--model", str(path), "--mixture-data", "crops"])
    assert res.exit_code == 2 and "give --refit too" in res.output and "Traceback" not in res.output
    res = CliRunner().invoke(app, ["modes", "--model", str(path), "--refit", "--mixture-data", "frames"])
    assert res.exit_code == 2 and "valid: crops, clips" in res.output
    assert "crop_bank" not in load_checkpoint(path)  # nothing written
    res = CliRunner().invoke(app, ["modes", "--model", str(path), "--refit", "--mixture-data", "crops",
                                   "--data", str(lines_folder), "--json"])
    assert res.exit_code == 0, res.output
    ckpt = load_checkpoint(path)
    crops = ckpt["crop_bank"]
    assert crops["passes"] == 5 and len(crops["codes"]) == len(ckpt["latent_bank"]["codes"])  # 12-frame clips: one crop each
    refit = fit_modes(crops, 2, seed=0)
    assert all(np.allclose(a["means"], b["means"]) for a, b in zip(refit["actions"], ckpt["modes"]["actions"]))
    assert "crop_bank" in checkpoint.compact(ckpt)  # a compact file keeps what its mixtures were fitted on
    info = json.loads(CliRunner().invoke(app, ["info", "--model", str(path), "--json"]).stdout)
    assert "5 passes" in info["crop_bank"]
    res = CliRunner().invoke(app, ["modes", "--model", str(path), "--refit", "--mixture-data", "clips"])
    assert res.exit_code == 0, res.output
    assert "crop_bank" not in load_checkpoint(path) and load_odmo(path).crops is None


def test_modes_refit_with_the_release_k_rule(lines_model, tmp_path):
    import json
    import shutil

    from odmo_cli.checkpoint import load_checkpoint
    from odmo_cli.models.latent import fit_modes

    path = tmp_path / "copy.pt"
    shutil.copy(lines_model, path)
    before = load_checkpoint(path)["modes"]
    assert before["rule"] == "paper"  # what training fits
    res = CliRunner().invoke(app, ["modes", "--model", str(path), "--k-rule", "release"])
    assert res.exit_code == 2 and "give --refit too" in res.output and "Traceback" not in res.output
    res = CliRunner().invoke(app, ["modes", "--model", str(path), "--refit", "--k-rule", "elbow"])
    assert res.exit_code == 2 and "valid: paper, release" in res.output and len(res.output.strip().splitlines()) == 1
    assert load_checkpoint(path)["modes"]["seed"] == before["seed"]  # nothing written
    res = CliRunner().invoke(app, ["modes", "--model", str(path), "--refit", "--k-rule", "release", "--seed", "3", "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["k_rule"] == "release"
    ckpt = load_checkpoint(path)
    expected = fit_modes(ckpt["latent_bank"], 2, seed=3, rule="release")
    assert ckpt["modes"]["rule"] == "release" and ckpt["modes"]["seed"] == 3
    assert all(np.allclose(a["means"], b["means"]) for a, b in zip(expected["actions"], ckpt["modes"]["actions"]))
    assert all(max(a["ks"]) <= 9 for a in ckpt["modes"]["actions"] if a["ks"])  # the release's k range
    res = CliRunner().invoke(app, ["modes", "--model", str(path), "--refit"])  # a later refit keeps the file's rule
    assert res.exit_code == 0 and "k rule: release" in res.output
    assert load_checkpoint(path)["modes"]["rule"] == "release"
