"""ODMO's training (training/odmo.py and `odmo train`): what a run feeds the losses, its options, the
checkpoint and end-of-training report, stages started from another model (--init, --train-parts); resume,
Ctrl-C and the non-finite stop are tested for every trainer in test_training_loop.py."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from odmo_cli.checkpoint import load_model
from odmo_cli.cli import app
from odmo_cli.data.dataset import mirror, mirror_map
from odmo_cli.data.demo import demo_folder
from odmo_cli.errors import UserError
from odmo_cli.measures import diagnostics
from odmo_cli.models.odmo import ODMO, ODMOConfig, widen_pose_decoder
from odmo_cli.training import odmo as odmo_training
from odmo_cli.training.odmo import ODMOTrainer, TrainConfig, model_config_for, reconstruction_error, train_odmo
from conftest import tiny_config




# -- training ---------------------------------------------------------------------------------------

def small_tc(**kw) -> TrainConfig:
    base = dict(epochs=4, batch_size=16, val_every=0, checkpoint_every=0, val_fraction=0.0, seed=3)
    base.update(kw)
    return TrainConfig(**base)


@pytest.mark.parametrize("frame", ["world", "path"])
def test_tiny_training_decreases_the_loss(demo_clips, tmp_path, frame):
    torch.manual_seed(0)
    cfg = model_config_for(demo_clips, {"motion_hidden": 32, "traj_hidden": 32, "pose_frame": frame})
    trainer = ODMOTrainer(demo_clips, cfg, small_tc(epochs=12, tf_start=1.0, tf_end=1.0), tmp_path / "m.pt")
    history = trainer.run()
    first, last = history[0]["total"], np.mean([h["total"] for h in history[-3:]])
    assert last < 0.7 * first, (first, last)
    assert history[-1]["mre"] < history[0]["mre"]


def test_checkpoint_is_safe_and_holds_the_latent_bank(demo_clips, tmp_path):
    result = train_odmo(demo_clips, small_tc(epochs=1, val_fraction=0.25),
                        tmp_path / "m.pt", overrides={"motion_hidden": 16})
    ckpt = torch.load(result.out, weights_only=True)
    bank = ckpt["latent_bank"]
    n_train = len(ckpt["split"]["train"])
    assert bank["codes"].shape == (n_train, 20)
    assert bank["end_points"].shape == (n_train, 3)
    assert len(bank["names"]) == n_train and bank["labels"].max() < 12
    assert ckpt["config"]["motion_hidden"] == 16 and ckpt["dataset"]["length"] == 60
    # the bank's codes are the encoder's means of the first-T-frame crops
    model = ODMO(ODMOConfig.from_dict(ckpt["config"]))
    model.load_state_dict(ckpt["state_dict"])
    from odmo_cli.data.dataset import crops_from_start
    motion, _ = crops_from_start(demo_clips, ckpt["split"]["train"].numpy()[:4], 60)
    assert torch.allclose(model.eval().encode(motion)[0], bank["codes"][:4], atol=1e-5)
    assert result.report["held_out_mpjpe"] > 0
    assert 0 < result.report["held_out_body"] <= result.report["held_out_mpjpe"] + result.report["held_out_end_error"] + 1
    assert result.report["held_out_body_mean_pose"] >= 0  # 0 where every held-out action has one clip
    # the fit on the training clips: the same measure on the clips the bank holds
    fit = reconstruction_error(model, demo_clips, ckpt["split"]["train"].numpy())
    assert result.report["train_body"] == pytest.approx(fit["body"], rel=1e-4)
    assert result.report["train_mpjpe"] == pytest.approx(fit["mpjpe"], rel=1e-4) and fit["mpjpe"] > 0
    real, labels = crops_from_start(demo_clips, ckpt["split"]["train"].numpy(), 60)
    assert result.report["train_body_mean_pose"] == pytest.approx(
        diagnostics.mean_pose_error(real.numpy(), labels.numpy()), rel=1e-5)
    # the held-out bodies against the training clips' own motions: a lookup by code, and the best clip
    val = ckpt["split"]["val"].numpy()
    held, held_labels = crops_from_start(demo_clips, val, 60)
    with torch.no_grad():
        held_codes = model.encode(held)[0]
    retrieved = diagnostics.retrieval_errors(held.numpy(), held_labels.numpy(), held_codes.numpy(), real.numpy(),
                                         labels.numpy(), bank["codes"].numpy())
    assert result.report["held_out_body_nearest_code"] == pytest.approx(retrieved["nearest_code"], rel=1e-4)
    assert 0 < result.report["held_out_body_best_clip"] == pytest.approx(retrieved["best_clip"], rel=1e-4)
    assert result.report["held_out_body_best_clip"] <= result.report["held_out_body_nearest_code"]


def fed_batches(clips, tmp_path, monkeypatch, *settings: dict) -> list[torch.Tensor]:
    """The motions (2B, T, J, 3) one epoch of a one-batch run feeds the losses, for each TrainConfig
    variant in `settings`, each run from the same seeds."""
    seen = []
    terms = odmo_training.odmo_terms
    monkeypatch.setattr(odmo_training, "odmo_terms",
                        lambda out, motion, *a: seen.append(motion) or terms(out, motion, *a))
    for k, extra in enumerate(settings):
        torch.manual_seed(0)
        cfg = model_config_for(clips, {"motion_hidden": 8, "traj_hidden": 8})
        ODMOTrainer(clips, cfg, small_tc(epochs=1, batch_size=1024, **extra), tmp_path / f"fed{k}.pt").run()
    return seen


def test_mirror_feeds_each_crop_or_its_mirror_half_the_time(demo_clips, tmp_path, monkeypatch):
    """TrainConfig.mirror: the epoch's crops are those of a run without it (its coins are drawn after
    them), each as it is or mirrored, about half of them mirrored."""
    plain, flipped = fed_batches(demo_clips, tmp_path, monkeypatch, {"mirror": False}, {"mirror": True})
    skeleton = demo_clips.manifest.skeleton
    mirrored = mirror(plain, mirror_map(skeleton.joint_names), skeleton.ground_axes[0])
    same = (flipped == plain).flatten(1).all(1)
    was_mirrored = (flipped == mirrored).flatten(1).all(1)
    assert bool((same | was_mirrored).all()) and not bool((same & was_mirrored).any())
    assert 0.25 < was_mirrored.float().mean() < 0.75, was_mirrored.float().mean()


def test_first_crops_feed_each_clips_first_frames(demo_clips, tmp_path, monkeypatch):
    """TrainConfig.crops "first": every crop fed is the first T frames of a clip, the crops the latent
    bank encodes; the default draws other starts of the clips longer than T."""
    from odmo_cli.data.dataset import crops_from_start
    first, _ = crops_from_start(demo_clips, np.arange(len(demo_clips.labels)), 60)  # (N, T, J, 3)
    random_fed, first_fed = fed_batches(demo_clips, tmp_path, monkeypatch, {"crops": "random"}, {"crops": "first"})
    def is_first(fed):  # (2B,): each fed crop equal to some clip's first crop
        return (fed[:, None] == first[None]).flatten(2).all(2).any(1)
    assert bool(is_first(first_fed).all())
    assert not bool(is_first(random_fed).all())
    with pytest.raises(UserError, match="crops must be random or first"):
        TrainConfig(crops="last")


def test_weight_decay_trains_with_adamw_and_pulls_the_weights_in(demo_clips, tmp_path):
    def run(weight_decay):
        torch.manual_seed(0)
        cfg = model_config_for(demo_clips, {"motion_hidden": 8, "traj_hidden": 8})
        tc = small_tc(epochs=2, weight_decay=weight_decay)
        trainer = ODMOTrainer(demo_clips, cfg, tc, tmp_path / f"{weight_decay}.pt")
        trainer.run()
        return trainer

    plain, decayed = run(0.0), run(50.0)
    assert type(plain.optimizers["optimizer"]) is torch.optim.Adam  # the default: the paper's and the release's
    opt = decayed.optimizers["optimizer"]
    assert type(opt) is torch.optim.AdamW and opt.param_groups[0]["weight_decay"] == 50.0
    def norm(trainer):
        return sum(float(p.detach().norm() ** 2) for p in trainer.model.parameters())
    assert norm(decayed) < 0.95 * norm(plain)
    with pytest.raises(UserError, match="weight_decay must be a number >= 0"):
        TrainConfig(weight_decay=-1.0)


def test_decoder_dropout_draws_fixed_units_per_clip_at_its_rate(demo_clips, tmp_path, monkeypatch):
    seen = []
    net = ODMO.forward
    monkeypatch.setattr(ODMO, "forward", lambda self, *a, keep=None, **kw: seen.append(keep) or net(self, *a, keep=keep, **kw))
    torch.manual_seed(0)
    cfg = model_config_for(demo_clips, {"motion_hidden": 64, "traj_hidden": 8})
    ODMOTrainer(demo_clips, cfg, small_tc(epochs=1, batch_size=1024), tmp_path / "a.pt").run()
    assert seen == [None]  # off by default: nothing drawn, the paper's decoder
    ODMOTrainer(demo_clips, cfg, small_tc(epochs=1, batch_size=1024, decoder_dropout=0.25), tmp_path / "b.pt").run()
    keep = seen[1]  # (2, 2B, H): one multiplier per cell, clip and unit
    assert keep.shape == (2, 2 * len(demo_clips.labels), 64)  # every clip in one batch (no validation split)
    assert keep.unique().tolist() == pytest.approx([0.0, 1 / 0.75])
    assert 0.2 < float((keep == 0).float().mean()) < 0.3
    for bad in (-0.1, 1.0):
        with pytest.raises(UserError, match=r"decoder_dropout must be in \[0, 1\)"):
            TrainConfig(decoder_dropout=bad)


def test_code_noise_scales_the_posterior_noise_and_leaves_the_other_draws(demo_clips, tmp_path, monkeypatch):
    seen = []
    net = ODMO.forward
    monkeypatch.setattr(ODMO, "forward", lambda self, *a, eps=None, keep=None, **kw:
                        seen.append((eps, keep)) or net(self, *a, eps=eps, keep=keep, **kw))
    cfg = model_config_for(demo_clips, {"motion_hidden": 16, "traj_hidden": 8})
    for i, noise in enumerate((1.0, 0.5, 0.0)):
        torch.manual_seed(0)
        tc = small_tc(epochs=1, batch_size=1024, code_noise=noise, decoder_dropout=0.5)
        ODMOTrainer(demo_clips, cfg, tc, tmp_path / f"{i}.pt").run()
    (full, keep), (half, keep_half), (none, keep_none) = seen
    assert full.abs().min() > 0 and torch.equal(half, full * 0.5) and torch.equal(none, torch.zeros_like(full))
    assert torch.equal(keep, keep_half) and torch.equal(keep, keep_none)  # drawn after the noise: as before
    motion = torch.from_numpy(np.stack([m[:cfg.length] for m in demo_clips.motions[:2]])).float()
    out = ODMO(cfg).forward(motion, torch.tensor([0, 1]), eps=torch.zeros(2, cfg.latent_dim))
    assert torch.equal(out["z"], out["mu"])  # no noise: the decoders see the mean code
    for bad in (-0.5, float("nan"), float("inf")):
        with pytest.raises(UserError, match=f"code_noise must be a (finite )?number( >= 0)?, got {bad}"):
            TrainConfig(code_noise=bad)


def test_free_running_term_starts_once_teacher_forcing_has_decayed():
    assert TrainConfig(epochs=1000, tf_epochs=500).free_start() == 500
    assert TrainConfig(epochs=300).free_start() == 150  # teacher forcing decays over all epochs: from half
    assert TrainConfig(epochs=300, tf_epochs=100, free_from=7).free_start() == 7
    with pytest.raises(UserError, match="free_from must be an epoch"):
        TrainConfig(free_from=-2)


def test_free_running_term_changes_nothing_before_it_starts(demo_clips, tmp_path):
    """Epochs before free_start compute bit for bit what a run without the term computes (so a run
    may be switched to it before that epoch); from free_start on it trains the free-running decode."""
    def run(name, weight, free_from, epochs=2):
        torch.manual_seed(0)
        cfg = model_config_for(demo_clips, {"motion_hidden": 16, "traj_hidden": 16, "free_energy_weight": weight})
        trainer = ODMOTrainer(demo_clips, cfg, small_tc(epochs=epochs, free_from=free_from), tmp_path / name)
        return trainer.run(), trainer.model.state_dict()

    h_off, w_off = run("off.pt", 0.0, -1)
    h_later, w_later = run("later.pt", 2.0, 2)
    assert all(torch.equal(w_off[k], w_later[k]) for k in w_off)
    assert [h["total"] for h in h_off] == [h["total"] for h in h_later]
    assert all(h["free_energy"] == 0.0 for h in h_later)
    h_on, w_on = run("on.pt", 2.0, 1)
    assert h_on[0]["total"] == h_off[0]["total"] and h_on[1]["free_energy"] > 0
    assert not all(torch.equal(w_off[k], w_on[k]) for k in w_off)


def test_teacher_forcing_decays_linearly():
    tc = TrainConfig(epochs=11, tf_start=1.0, tf_end=0.3)
    assert tc.teacher_rate(0) == 1.0
    assert tc.teacher_rate(10) == pytest.approx(0.3)
    assert tc.teacher_rate(5) == pytest.approx(0.65)
    assert TrainConfig(epochs=100, tf_epochs=10).teacher_rate(50) == pytest.approx(0.3)


# -- stages from a finished model -------------------------------------------------------------------

def test_init_starts_a_stage_from_a_finished_model(demo_clips, tmp_path):
    """--init: the weights and model config of a finished file (loss options on top), this run's
    schedule and a fresh optimizer; the checkpoint says where it started. Not with --resume."""
    first = tmp_path / "first.pt"
    small = {"latent_dim": 4, "encoder_fc": 16, "traj_hidden": 16, "motion_hidden": 16, "energy_weight": 0.5}
    train_odmo(demo_clips, TrainConfig(epochs=2, batch_size=8, val_every=0, threads=1), first, overrides=small)
    start = torch.load(first, weights_only=True)
    tc = TrainConfig(epochs=1, batch_size=8, val_every=0, threads=1, lr=1e-9, lr_final=1e-9, tf_start=0.0, tf_end=0.0)
    second = tmp_path / "second.pt"
    train_odmo(demo_clips, tc, second, overrides={"free_energy_weight": 1.0}, init=first)
    ckpt = torch.load(second, weights_only=True)
    assert ckpt["config"] == {**start["config"], "free_energy_weight": 1.0}  # not the preset's scales
    assert ckpt["init"] == {"source": "first.pt", "epoch": 2, "train_config": start["train_config"],
                            "config": start["config"]}
    assert ckpt["epoch"] == 1 and ckpt["train_config"]["tf_end"] == 0.0
    moved = max(float((ckpt["state_dict"][k] - v).abs().max()) for k, v in start["state_dict"].items()
                if v.is_floating_point() and "running" not in k and "num_batches" not in k)
    assert moved < 1e-5  # a learning rate of 1e-9: the first stage's weights, as they were
    fresh = tmp_path / "fresh.pt"
    train_odmo(demo_clips, tc, fresh, overrides=small)
    assert torch.load(fresh, weights_only=True)["state_dict"]["motion.out.weight"].ne(
        ckpt["state_dict"]["motion.out.weight"]).any()
    with pytest.raises(UserError, match="either --init"):
        train_odmo(demo_clips, tc, tmp_path / "x.pt", init=first, resume=second)
    with pytest.raises(UserError, match=r"^--init first.pt's weights do not fit this model: size mismatch"):
        train_odmo(demo_clips, tc, tmp_path / "x.pt", overrides={"traj_hidden": 8}, init=first)
    with pytest.raises(UserError, match=r"^--motion-hidden 8: --init first.pt's pose decoder has 16 units; "
                                        r"it can be widened, not narrowed$"):
        train_odmo(demo_clips, tc, tmp_path / "x.pt", overrides={"motion_hidden": 8}, init=first)
    with pytest.raises(UserError, match=r"^--init first.pt draws poses in the world frame; .* not path$"):
        train_odmo(demo_clips, tc, tmp_path / "x.pt", overrides={"pose_frame": "path"}, init=first)  # as a ship stage could
    assert not (tmp_path / "x.pt").exists()
    res = CliRunner().invoke(app, ["train", "--dataset", str(demo_folder("humanact12")), "--init", str(first),
                                   "--resume", str(second), "--out", str(tmp_path / "y.pt")])
    assert res.exit_code == 2 and "either --init" in res.stderr and "Traceback" not in res.stderr


def test_widened_pose_decoder_draws_the_same_motion_and_grows(demo_clips, tmp_path):
    """widen_pose_decoder: more units, the same function; the new units learn from the first step.
    Through --init and --motion-hidden: the wider stage starts where the narrow file stood."""
    torch.manual_seed(0)
    narrow, wide = ODMO(tiny_config(motion_hidden=6)), ODMO(tiny_config(motion_hidden=10))
    fresh = wide.state_dict()
    state = widen_pose_decoder(narrow.state_dict(), fresh)
    wide.load_state_dict(state)
    assert torch.equal(state["motion.cell0.weight_ih"][6:10], fresh["motion.cell0.weight_ih"][6:10])  # a new unit's gate i
    g = torch.Generator().manual_seed(1)
    motion, labels = torch.randn(5, 8, 4, 3, generator=g), torch.tensor([0, 1, 2, 0, 1])
    with torch.no_grad():
        z, end = torch.randn(5, 5, generator=g), torch.randn(5, 3, generator=g)
        for teacher in (None, torch.tensor([True, False] * 4)):
            a = narrow.decode(z, labels, end, motion, teacher)[1]
            b = wide.decode(z, labels, end, motion, teacher)[1]
            assert torch.allclose(a, b, atol=1e-6)
    out = wide(motion, labels, generator=torch.Generator().manual_seed(2))["motion"]
    (out - motion).square().mean().backward()
    grad = wide.motion.out.weight.grad[:, 6:]  # from the new units: zero weights, not zero gradients
    assert torch.isfinite(grad).all() and grad.abs().max() > 0
    with pytest.raises(ValueError, match="only be widened: 10 hidden units, asked 6"):
        widen_pose_decoder(wide.state_dict(), narrow.state_dict())

    first = tmp_path / "first.pt"
    small = {"latent_dim": 4, "encoder_fc": 16, "traj_hidden": 16, "motion_hidden": 16}
    train_odmo(demo_clips, TrainConfig(epochs=1, batch_size=8, val_every=0, threads=1), first, overrides=small)
    res = CliRunner().invoke(app, ["train", "--dataset", str(demo_folder("humanact12")), "--init", str(first),
                                   "--motion-hidden", "24", "--epochs", "1", "--lr", "1e-9", "--val-every", "0",
                                   "--threads", "1", "--batch-size", "8", "--out", str(tmp_path / "wide.pt"), "--json"])
    assert res.exit_code == 0, res.output
    before, after = (load_model(tmp_path / name).model.eval() for name in ("first.pt", "wide.pt"))
    assert after.cfg.motion_hidden == 24 and before.cfg.motion_hidden == 16
    with torch.no_grad():
        z, labels, end = torch.zeros(3, 4), torch.tensor([0, 1, 2]), torch.zeros(3, 3)
        assert torch.allclose(before.decode(z, labels, end)[1], after.decode(z, labels, end)[1], atol=1e-4)
    res = CliRunner().invoke(app, ["train", "--dataset", str(demo_folder("humanact12")), "--init", str(first),
                                   "--motion-hidden", "0", "--out", str(tmp_path / "bad.pt")])
    assert res.exit_code == 2 and "--motion-hidden must be a positive" in res.stderr and "Traceback" not in res.stderr
    assert not (tmp_path / "bad.pt").exists()


def test_a_stage_keeps_the_split_of_the_file_it_starts_from(demo_clips, tmp_path):
    """A stage run with another --seed draws its own pairs and noise but validates on the earlier
    stages' held-out clips and never trains on them; resuming it keeps that split too."""
    from odmo_cli.data.dataset import split_indices

    small = {"latent_dim": 4, "encoder_fc": 16, "traj_hidden": 16, "motion_hidden": 16}
    first = tmp_path / "first.pt"
    train_odmo(demo_clips, TrainConfig(epochs=1, batch_size=8, val_every=0, threads=1, seed=0, val_fraction=0.34),
               first, overrides=small)  # one clip of each action held out
    held = torch.load(first, weights_only=True)["split"]["val"]
    other = torch.from_numpy(split_indices(demo_clips, 0.34, 3)[1])
    assert len(held) == 12 and not torch.equal(held, other)  # seed 3 alone would hold out other clips
    second = tmp_path / "second.pt"
    tc = TrainConfig(epochs=2, batch_size=8, val_every=0, checkpoint_every=1, threads=1, seed=3)
    train_odmo(demo_clips, replace(tc, epochs=1), second, init=first)
    ckpt = torch.load(second, weights_only=True)
    assert torch.equal(ckpt["split"]["val"], held)
    assert ckpt["train_config"]["seed"] == 3 and ckpt["train_config"]["split_seed"] == 0
    assert ckpt["train_config"]["val_fraction"] == 0.34  # the first file's, not this run's default
    train_odmo(demo_clips, tc, second, resume=second)  # one more epoch, resumed
    assert torch.equal(torch.load(second, weights_only=True)["split"]["val"], held)
    # a run of its own draws its split from its seed
    fresh = tmp_path / "fresh.pt"
    train_odmo(demo_clips, TrainConfig(epochs=1, batch_size=8, val_every=0, threads=1, seed=3, val_fraction=0.34),
               fresh, overrides=small)
    assert torch.equal(torch.load(fresh, weights_only=True)["split"]["val"], other)


def test_train_parts_leaves_the_other_networks_as_they_were(demo_clips, tmp_path):
    """--train-parts trajectory: a stage moves the trajectory generator's weights only; an unknown
    part is a one-line user error before any data is read."""
    first = tmp_path / "first.pt"
    small = {"latent_dim": 4, "encoder_fc": 16, "traj_hidden": 16, "motion_hidden": 16}
    train_odmo(demo_clips, TrainConfig(epochs=1, batch_size=8, val_every=0, threads=1), first, overrides=small)
    start = torch.load(first, weights_only=True)["state_dict"]
    tc = TrainConfig(epochs=2, batch_size=8, val_every=0, threads=1, lr=1e-2, train_parts="trajectory")
    second = tmp_path / "second.pt"
    train_odmo(demo_clips, tc, second, overrides={"height_weight": 1.0}, init=first)
    after = torch.load(second, weights_only=True)
    assert after["train_config"]["train_parts"] == "trajectory"
    moved = {k.split(".")[0] for k, v in after["state_dict"].items() if not torch.equal(v, start[k])}
    assert moved == {"trajectory"}
    assert TrainConfig(train_parts="motion, trajectory").parts() == ["motion", "trajectory"]
    assert TrainConfig().parts() == ["encoder", "trajectory", "motion"]
    with pytest.raises(UserError, match=r"^train_parts has unknown part 'decoder'; valid: encoder, trajectory, motion"):
        TrainConfig(train_parts="trajectory,decoder")
    res = CliRunner().invoke(app, ["train", "--dataset", str(demo_folder("humanact12")), "--train-parts", ",",
                                   "--out", str(tmp_path / "y.pt")])
    assert res.exit_code == 2 and "--train-parts has unknown part ','" in res.stderr and "Traceback" not in res.stderr
    assert res.stderr.count("\n") == 1 and not (tmp_path / "y.pt").exists()


# -- the command line -------------------------------------------------------------------------------

def test_cli_train_and_info(tmp_path):
    runner = CliRunner()
    out = tmp_path / "m.pt"
    res = runner.invoke(app, ["train", "--dataset", str(demo_folder("humanact12")), "--epochs", "1",
                              "--batch-size", "8", "--out", str(out), "--json", "--sigma2", "0.0025",
                              "--recon-weight", "2", "--energy-weight", "1.5", "--free-energy-weight", "0.5",
                              "--free-from", "3", "--mirror", "--weight-decay", "0.5", "--decoder-dropout", "0.1",
                              "--crops", "first", "--pose-loss", "body", "--mix-energy-weight", "0.7",
                              "--code-noise", "0.25"])
    assert res.exit_code == 0, res.output
    saved = torch.load(out, weights_only=True)
    config = saved["config"]
    assert config["sigma2"] == 0.0025 and config["recon_weight"] == 2.0 and config["energy_weight"] == 1.5
    assert config["pose_loss"] == "body" and config["mix_energy_weight"] == 0.7
    assert saved["history"][-1]["mix_energy"] > 0  # trained and logged
    assert config["free_energy_weight"] == 0.5 and saved["train_config"]["free_from"] == 3
    assert saved["train_config"]["mirror"] is True and saved["train_config"]["weight_decay"] == 0.5
    assert saved["train_config"]["decoder_dropout"] == 0.1 and saved["train_config"]["crops"] == "first"
    assert saved["train_config"]["code_noise"] == 0.25
    refused = [  # an option's bad value: one line, exit 2
        (["--crops", "last"], "--crops must be random or first, got 'last'"),
        (["--code-noise", "-1"], "--code-noise must be a number >= 0, got -1.0"),
        (["--pose-loss", "root"], "--pose-loss must be one of world, body, got 'root'"),
        (["--mix-energy-weight", "-1"], "--mix-energy-weight must be a number >= 0, got -1.0"),
        (["--decoder-dropout", "1"], "--decoder-dropout must be in [0, 1), got 1.0"),
        (["--weight-decay", "-1"], "--weight-decay must be a number >= 0, got -1.0"),
        (["--free-energy-weight", "-1"], "--free-energy-weight must be a number >= 0, got -1.0"),
        (["--height-weight", "-1"], "--height-weight must be a number >= 0, got -1.0"),
        (["--root", "hips"], "--root must be one of trajectory, decoder, ground, got 'hips'"),
    ]
    for args, message in refused:
        res = runner.invoke(app, ["train", "--dataset", str(demo_folder("humanact12")), *args])
        assert res.exit_code == 2 and res.stderr == f"error: {message}\n", args
    # a stage with the height term, read with the ground readout: both stored, the validation reports the height
    staged = tmp_path / "h.pt"
    res = runner.invoke(app, ["train", "--dataset", str(demo_folder("humanact12")), "--init", str(out), "--epochs", "1",
                              "--batch-size", "8", "--height-weight", "2", "--root", "ground", "--val-every", "1",
                              "--out", str(staged), "--json"])
    assert res.exit_code == 0, res.output
    saved = torch.load(staged, weights_only=True)
    assert saved["config"]["height_weight"] == 2.0 and saved["config"]["root"] == "ground"
    assert saved["config"]["energy_weight"] == 1.5  # the rest of the file's config stands
    logged = saved["history"][-1]
    assert logged["height"] > 0 and np.isfinite(logged["val_height"]) and logged["val_height"] > 0
    res = runner.invoke(app, ["info", "--model", str(out), "--json"])
    assert res.exit_code == 0 and '"kind": "odmo"' in res.stdout and '"weights": "float32"' in res.stdout
