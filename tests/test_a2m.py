"""Action2Motion baseline: the paper's architecture and defaults, both representations, training,
sampling through the common generator interface, checkpoints and the CLI (tiny models, demo clips).
Resume, Ctrl-C and the non-finite stop: test_training_loop.py, for every trainer."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from odmo_cli.cli import app
from odmo_cli.data.demo import demo_folder
from odmo_cli.data.locate import resolve
from odmo_cli.data.readers import read_dataset
from odmo_cli.checkpoint import describe_checkpoint, load_checkpoint
from odmo_cli.data.dataset import crops_from_start
from odmo_cli.errors import UserError
from odmo_cli.geometry.lie import bone_lengths_from_pose, forward_kinematics, inverse_kinematics
from odmo_cli.evaluation.metrics import bone_length_consistency
from odmo_cli.models.a2m import A2M, A2MConfig, fold_root, paper_lambda_kl
from odmo_cli.training.a2m import A2MTrainConfig, A2MTrainer, a2m_config_for, train_a2m

TINY = {"length": 10, "hidden": 32, "z_dim": 4, "bank_size": 4}


@pytest.fixture(scope="module")
def clips():
    """Six demo HumanAct12 clips (several actions)."""
    manifest, root = resolve(demo_folder("humanact12"))
    return read_dataset(root, manifest).subset(list(range(0, 36, 6)))


def tiny_tc(**kw) -> A2MTrainConfig:
    base = dict(epochs=2, batch_size=8, lr=1e-2, val_fraction=0.0, val_every=0, checkpoint_every=0)
    return A2MTrainConfig(**{**base, **kw})


def tiny_model(clips, representation: str, seed: int = 0) -> A2MTrainer:
    cfg = a2m_config_for(clips, representation, TINY)
    return A2MTrainer(clips, cfg, tiny_tc(seed=seed), "unused.pt")


# -- the paper's model ---------------------------------------------------------------------

def test_lie_model_is_table_3():
    model = A2M(A2MConfig())  # HumanAct12: 24 joints, 12 actions
    sizes = {n: tuple(p.shape) for n, p in model.named_parameters()}
    assert sizes["posterior.encoder.weight"] == (128, 85) and sizes["prior.encoder.weight"] == (128, 85)
    assert sizes["generator.encoder.weight"] == (128, 115) and sizes["generator.decoder.weight"] == (72, 128)
    assert sizes["generator.lie_output.weight"] == (69, 69) and sizes["posterior.mu_net.weight"] == (30, 128)
    assert len(model.generator.gru) == 2 and len(model.prior.gru) == 1
    per_part = [sum(p.numel() for p in part.parameters()) for part in (model.posterior, model.prior, model.generator)]
    assert per_part == [117_820, 117_820, 227_110]


def test_defaults_are_the_papers():
    tc = A2MTrainConfig()
    assert (tc.lr, tc.weight_decay, tc.teacher_rate, tc.batch_size) == (2e-4, 1e-5, 0.6, 128)
    assert paper_lambda_kl("humanact12") == 0.01 and paper_lambda_kl("cmu_mocap") == 0.1
    cfg = A2MConfig()
    assert (cfg.hidden, cfg.z_dim, cfg.gen_layers, cfg.representation) == (128, 30, 2, "lie")


def test_optimizer_and_lambda_follow_the_config(clips):
    trainer = tiny_model(clips, "lie")
    group = trainer.optimizers["optimizer"].param_groups[0]
    assert isinstance(trainer.optimizers["optimizer"], torch.optim.Adam) and group["weight_decay"] == 1e-5
    assert group["betas"] == (0.9, 0.999) and trainer.lambda_kl == 0.01 == trainer.tc.lambda_kl
    cfg = a2m_config_for(clips, "lie", TINY)
    assert A2MTrainer(clips, cfg, tiny_tc(lambda_kl=0.5), "unused.pt").lambda_kl == 0.5


def test_bad_representation_is_a_user_error():
    with pytest.raises(UserError, match="representation must be one of xyz, lie, got 'quat'"):
        A2MConfig(representation="quat")


# -- representations -----------------------------------------------------------------------

@pytest.mark.parametrize("representation", ["xyz", "lie"])
def test_pose_vectors_give_back_the_motion(clips, representation):
    model = A2M(a2m_config_for(clips, representation))
    motion, _ = crops_from_start(clips, np.arange(len(clips)), 60)  # (6, 60, 24, 3)
    poses = model.pose_vectors(motion)
    assert poses.shape == (6, 60, 72)
    back = model.positions(poses, bone_lengths_from_pose(motion, model.sk))
    assert torch.allclose(back, motion, atol=1e-5)


def test_folding_the_root_rotation_keeps_the_pose(clips):
    motion = torch.from_numpy(clips.motions[0][:20]).double()  # (20, 24, 3)
    sk = clips.manifest.skeleton
    root, lie = inverse_kinematics(motion, sk)
    folded = fold_root(lie, sk.parents)
    assert torch.all(folded[:, 0] == 0) and not torch.allclose(folded[:, 1], lie[:, 1])
    lengths = bone_lengths_from_pose(motion, sk)
    assert torch.allclose(forward_kinematics(root, folded, lengths, sk), motion, atol=1e-10)


# -- training ------------------------------------------------------------------------------

@pytest.mark.parametrize("representation", ["xyz", "lie"])
def test_tiny_training_decreases_the_loss(clips, representation, tmp_path):
    cfg = a2m_config_for(clips, representation, TINY)
    history = A2MTrainer(clips, cfg, tiny_tc(epochs=20), tmp_path / "a2m.pt").run()
    losses = [h["loss"] for h in history]
    assert all(np.isfinite(losses))
    assert np.mean(losses[-3:]) < 0.5 * np.mean(losses[:3])
    assert {"mse", "kl", "loss"} <= set(history[-1])


# -- sampling ------------------------------------------------------------------------------

@pytest.mark.parametrize("representation", ["xyz", "lie"])
def test_generate_shapes_origin_and_seeds(clips, representation):
    model = tiny_model(clips, representation).model.eval()
    labels = torch.tensor([0, 3, 3, 11])
    out = model.generate(labels, torch.Generator().manual_seed(1))
    assert out.shape == (4, 10, 24, 3) and out.dtype == torch.float32
    assert torch.all(out[:, 0, 0] == 0) and torch.isfinite(out).all()
    assert torch.equal(out, model.generate(labels, torch.Generator().manual_seed(1)))
    assert not torch.allclose(out, model.generate(labels, torch.Generator().manual_seed(2)))


def test_lie_outputs_keep_a_bank_body_and_xyz_outputs_drift(clips):
    sk = clips.manifest.skeleton
    lie = tiny_model(clips, "lie").model.eval()
    motions = lie.generate(torch.arange(12), torch.Generator().manual_seed(0))  # (12, 10, 24, 3)
    lengths = bone_lengths_from_pose(motions.double(), sk)  # (12, 10, 24)
    assert (lengths.std(1) < 1e-5).all()  # constant over time, to float32 rounding
    bank = lie.bone_bank.double()  # (K, 24) real bodies
    assert bank[:, 1:].min() > 0.01 and bank[:, 1:].max() < 1.0  # metres
    gap = (lengths[:, :1, None, 1:] - bank[None, None, :, 1:]).abs().amax(-1)  # (12, 1, K)
    assert (gap.amin(-1) < 1e-5).all()  # every motion uses one of the bank's bodies
    xyz = tiny_model(clips, "xyz").model.eval()
    drifting = xyz.generate(torch.arange(12), torch.Generator().manual_seed(0)).numpy()
    assert bone_length_consistency(motions.numpy(), sk.parents) < 1e-6
    assert bone_length_consistency(drifting, sk.parents) > 1e-3


def test_checkpoint_samples_through_the_common_sampler(clips, tmp_path):
    from odmo_cli.checkpoint import LoadedBaseline, load_model
    from odmo_cli.generation.generate import sample

    out = tmp_path / "a2m.pt"
    result = train_a2m(clips, tiny_tc(epochs=1, val_fraction=0.2), out, representation="lie", overrides=TINY)
    assert result.report["representation"] == "lie" and result.report["held_out_clips"] > 0
    ckpt = load_checkpoint(out)  # weights_only
    assert ckpt["kind"] == "a2m" and ckpt["config"]["representation"] == "lie"
    assert ckpt["state_dict"]["bone_bank"].shape == (4, 24) and ckpt["epoch"] == 1
    assert ckpt["dataset"]["name"] == "humanact12" and "optimizer" in ckpt and "rng" in ckpt
    loaded = load_model(out)
    assert isinstance(loaded, LoadedBaseline) and loaded.kind == "a2m"
    batch = sample(loaded, ["jump", "walk"], 3, seed=5)
    assert batch.motions.shape == (6, 10, 24, 3) and list(batch.actions) == ["jump"] * 3 + ["walk"] * 3
    assert np.array_equal(batch.motions, sample(loaded, ["jump", "walk"], 3, seed=5).motions)
    with pytest.raises(UserError, match="--mode needs an ODMO model"):
        sample(loaded, ["jump"], 2, mode=0)
    desc = describe_checkpoint(out)
    assert desc["kind"] == "a2m" and desc["bone_bank"].startswith("4 real bone-length sets")
    assert "latent_bank" not in desc


# -- CLI -----------------------------------------------------------------------------------

def test_cli_trains_samples_and_describes_a2m(tmp_path):
    runner = CliRunner()
    out, samples = tmp_path / "a2m.pt", tmp_path / "s.npz"
    res = runner.invoke(app, ["train", "a2m", "--representation", "xyz", "--dataset",
                              str(demo_folder("humanact12")), "--epochs", "1", "--batch-size", "64",
                              "--out", str(out), "--json"])
    assert res.exit_code == 0, res.output
    res = runner.invoke(app, ["sample", "--model", str(out), "--action", "jump", "--n", "2", "--out", str(samples)])
    assert res.exit_code == 0, res.output
    with np.load(samples) as f:
        assert f["motions"].shape == (2, 60, 24, 3) and list(f["actions"]) == ["jump", "jump"]
    res = runner.invoke(app, ["sample", "--model", str(out), "--action", "jump", "--mode", "0"])
    assert res.exit_code == 2 and "--mode needs an ODMO model" in res.stderr
    res = runner.invoke(app, ["info", "--model", str(out), "--json"])
    assert res.exit_code == 0 and '"kind": "a2m"' in res.stdout and '"representation": "xyz"' in res.stdout


def test_cli_eval_compares_xyz_and_lie_models_in_one_table(tmp_path):
    """`odmo eval --compare` takes baselines: Lie outputs keep their bones, xyz outputs drift."""
    runner, folder = CliRunner(), str(demo_folder("humanact12"))
    paths = {}
    for rep in ("xyz", "lie"):
        paths[rep] = tmp_path / f"a2m-{rep}.pt"
        res = runner.invoke(app, ["train", "a2m", "--representation", rep, "--dataset", folder,
                                  "--epochs", "1", "--batch-size", "64", "--out", str(paths[rep]), "--json"])
        assert res.exit_code == 0, res.output
    report = tmp_path / "eval.json"
    # the spelling: `odmo eval --compare a.pt b.pt ...` (extra checkpoints are positional)
    res = runner.invoke(app, ["eval", "--model", str(paths["xyz"]), str(paths["lie"]), "--dataset",
                              folder, "--repeats", "2", "--per-action", "4", "--out", str(report)])
    assert res.exit_code == 0, res.output
    rows = {r["name"]: r["metrics"] for r in json.loads(report.read_text())["rows"]}
    assert list(rows) == ["Real motions", "a2m-xyz.pt", "a2m-lie.pt"]
    assert rows["a2m-lie.pt"]["bone_std"][0] < 1e-5 < rows["a2m-xyz.pt"]["bone_std"][0]
    assert all(np.isfinite(m["fid"][0]) for m in rows.values())


def test_cmu_skeleton_lie_model(tmp_path):
    manifest, root = resolve(demo_folder("cmu"))
    cmu = read_dataset(root, manifest)
    trainer = A2MTrainer(cmu, a2m_config_for(cmu, "lie", TINY), tiny_tc(epochs=1), tmp_path / "a2m.pt")
    assert trainer.lambda_kl == 0.1 and trainer.model.cfg.pose_dim == 60
    trainer.run()
    motions = trainer.model.eval().generate(torch.arange(len(manifest.actions)), torch.Generator().manual_seed(0))
    assert motions.shape == (len(manifest.actions), 10, 20, 3)
    assert bone_length_consistency(motions.numpy(), manifest.skeleton.parents) < 1e-6
