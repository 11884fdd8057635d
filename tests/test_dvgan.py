"""DVGAN baseline: networks, WGAN-GP pieces, training, checkpoints, completion, CLI (issue 8).
Resume, Ctrl-C and the non-finite stop: test_training_loop.py, for every trainer."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from odmo_cli import checkpoint
from odmo_cli.cli import app
from odmo_cli.checkpoint import load_checkpoint
from odmo_cli.errors import UserError
from odmo_cli.generation import generate
from odmo_cli.models.dvgan import (DVGAN, DVGANConfig, LanguageModel, final_cut, gradient_penalty,
                                   model_from_checkpoint, temporal_shift)
from odmo_cli.training.dvgan import DVGANTrainConfig, train_dvgan

TINY = {"hidden": 16, "lm_hidden": 8, "word_dim": 8, "rnn_latent": 8, "length": 16}
ACTIONS = ("warm_up", "walk", "lift_dumbbell")


pytestmark = pytest.mark.usefixtures("one_thread")



def tiny_model(generator: str, **kw) -> DVGAN:
    torch.manual_seed(0)
    cfg = DVGANConfig(n_joints=4, length=10, actions=ACTIONS, generator=generator,
                      **{**{k: v for k, v in TINY.items() if k != "length"}, **kw})
    return DVGAN(cfg).eval()


def tiny_tc(**kw) -> DVGANTrainConfig:
    base = dict(epochs=2, batch_size=12, n_critic=2, checkpoint_every=0, seed=0, threads=1)
    base.update(kw)
    return DVGANTrainConfig(**base)


@pytest.fixture(scope="module")
def trained(demo_clips, tmp_path_factory):
    """Tiny DVGANs (cnn, rnn) trained 2 epochs on the demo clips: generator -> (checkpoint, result)."""
    out = {}
    for g in ("cnn", "rnn"):
        path = tmp_path_factory.mktemp("dvgan") / f"{g}.pt"
        out[g] = (path, train_dvgan(demo_clips, tiny_tc(), path, generator=g, overrides=TINY))
    return out


# -- networks ---------------------------------------------------------------------------------

@pytest.mark.parametrize("generator", ["cnn", "rnn"])
def test_output_shapes_and_the_first_root_at_the_origin(generator):
    model = tiny_model(generator)
    labels = torch.tensor([0, 1, 2, 1, 0])
    txt = model.g_text(labels)
    assert txt.shape == (5, 16)  # [h; c] of an 8-unit LSTM
    tape = model.generator(txt, torch.Generator().manual_seed(0))
    assert tape.shape == (5, 20, 12)  # 2T frames of J*3 features before the final cut
    motions = model.generate(labels, torch.Generator().manual_seed(0))
    assert motions.shape == (5, 10, 4, 3) and motions.dtype == torch.float32
    assert torch.equal(motions[:, 0, 0], torch.zeros(5, 3))
    assert torch.isfinite(motions).all() and motions[:, 1:].abs().sum() > 0
    assert model.critic(model.fake(labels, torch.Generator()), labels).shape == (5,)


def test_cnn_generator_handles_a_length_that_is_not_a_power_of_two():
    model = tiny_model("cnn")
    assert model.generator.levels == 5  # 2^5 = 32 >= 2T = 20, cut to 20
    model.cfg.final_cut = False
    assert model.fake(torch.tensor([0]), torch.Generator()).shape == (1, 10, 12)


def test_final_cut_takes_a_uniform_window_inside_the_tape():
    tape = torch.arange(20.0)[None, :, None].expand(4000, 20, 2)  # frame t holds t
    window, starts = final_cut(tape, 10, torch.Generator().manual_seed(0))
    assert window.shape == (4000, 10, 2)
    assert starts.min() == 0 and starts.max() == 10  # both ends of [0, 2T - T] occur
    assert torch.equal(window[:, :, 0], starts[:, None].float() + torch.arange(10.0))
    counts = torch.bincount(starts, minlength=11).float()
    assert counts.min() > 0.7 * counts.mean()  # 11 positions, each about 1/11 of the draws


def test_temporal_shift_moves_by_at_most_half_the_length_and_pads_with_zeros():
    t = 10
    x = (torch.arange(t, dtype=torch.float32) + 1)[None, :, None].expand(3000, t, 2)  # frame i holds i+1
    y = temporal_shift(x, torch.Generator().manual_seed(0))
    assert torch.equal(y[:, :, 0], y[:, :, 1])
    seen = set()
    for row in y[:, :, 0]:
        known = row > 0
        first = int(torch.nonzero(known)[0])
        shift = first - int(row[first] - 1)  # out[i] = x[i - shift]
        assert -t // 2 <= shift <= t // 2
        assert torch.equal(row[known], torch.arange(t, dtype=torch.float32)[known] - shift + 1)
        assert known.sum() == t - abs(shift)
        seen.add(shift)
    assert seen == set(range(-5, 6))


def test_gradient_penalty_equals_the_closed_form_on_a_linear_critic():
    w = torch.tensor([[0.5, -2.0], [1.0, 3.0], [0.0, 0.25]])  # ||w|| = sqrt(14.3125)
    critic = lambda x: (x * w).sum(dim=(1, 2))  # noqa: E731
    gen = torch.Generator().manual_seed(0)
    real, fake = torch.randn(6, 3, 2, generator=gen), torch.randn(6, 3, 2, generator=gen)
    gp = gradient_penalty(critic, real, fake, gen, lam=10.0)
    assert float(gp) == pytest.approx(10.0 * (14.3125 ** 0.5 - 1) ** 2, rel=1e-6)
    unit = lambda x: (x * w / w.norm()).sum(dim=(1, 2))  # noqa: E731
    assert float(gradient_penalty(unit, real, fake, gen)) == pytest.approx(0.0, abs=1e-10)


def test_discriminator_combines_the_scales_with_convex_weights():
    model = tiny_model("cnn")
    disc = model.discriminator
    assert disc.levels == 4  # 10 -> 5 -> 3 -> 2 -> 1 frames: five validated resolutions
    with torch.no_grad():
        disc.weights.copy_(torch.tensor([2.0, -1.0, 0.5, 3.0, -4.0]))
    w = disc.convex_weights()
    w = w.detach()
    assert float(w.sum()) == pytest.approx(1.0, abs=1e-6) and (w > 0).all()
    labels = torch.tensor([0, 2])
    x = torch.randn(2, 10, 12, generator=torch.Generator().manual_seed(1))
    scores = disc.scores(x, model.d_text(labels))
    assert scores.shape == (2, 5)
    assert torch.allclose(model.critic(x, labels), (scores * w).sum(dim=1), atol=1e-6)


def test_the_condition_reads_the_action_name_as_words():
    cfg = DVGANConfig(n_joints=4, length=10, actions=ACTIONS, hidden=8, lm_hidden=4, word_dim=4)
    assert cfg.vocab == ("dumbbell", "lift", "up", "walk", "warm")
    lm = LanguageModel(cfg)
    assert lm.tokens.tolist() == [[5, 3], [4, 0], [2, 1]] and lm.lengths.tolist() == [2, 1, 2]
    # the padded name's code is its last real word's state: the same as reading it alone
    alone = DVGANConfig(n_joints=4, length=10, actions=("walk",), vocab=cfg.vocab, hidden=8, lm_hidden=4, word_dim=4)
    single = LanguageModel(alone)
    single.load_state_dict({k: v for k, v in lm.state_dict().items() if k not in ("tokens", "lengths")}, strict=False)
    assert torch.allclose(lm(torch.tensor([1])), single(torch.tensor([0])), atol=1e-6)


def test_completion_keeps_the_prefix_exactly_and_continues_it():
    model = tiny_model("rnn")
    prefix = torch.randn(1, 4, 4, 3, generator=torch.Generator().manual_seed(2)).expand(3, -1, -1, -1).clone()
    prefix -= prefix[:, :1, :1].clone()
    out = model.complete(prefix, torch.tensor([0, 1, 2]), torch.Generator().manual_seed(0))
    assert out.shape == (3, 10, 4, 3)
    assert torch.equal(out[:, :4], prefix)
    assert torch.isfinite(out).all() and not torch.allclose(out[0, 4:], out[1, 4:])
    again = model.complete(prefix, torch.tensor([0, 1, 2]), torch.Generator().manual_seed(0))
    assert torch.equal(out, again)
    with pytest.raises(UserError, match="needs a DVGAN-RNN model"):
        tiny_model("cnn").complete(prefix, torch.tensor([0, 1, 2]), torch.Generator())


def test_rnn_steps_add_differences_to_the_previous_frame():
    model = tiny_model("rnn")
    txt = model.g_text(torch.tensor([0, 1]))
    x = model.generator(txt, torch.Generator().manual_seed(0), steps=6)
    gen = model.generator
    with torch.no_grad():  # replay eq. 4 for the second frame with the same noise
        z = torch.randn(2, 6, 8, generator=torch.Generator().manual_seed(0))
        p1 = gen.plot_out(torch.relu(gen.plot_z(z[:, 1]) + gen.plot_txt(txt)))
        d, _ = gen.lstm(torch.cat([gen.frame_in(x[:, 0]), p1], -1)[:, None])
        assert torch.allclose(x[:, 1], x[:, 0] + gen.diff(d[:, 0]), atol=1e-6)


# -- training and checkpoints -----------------------------------------------------------------

@pytest.mark.parametrize("generator", ["cnn", "rnn"])
def test_tiny_training_stays_finite_and_moves_both_networks(trained, generator):
    path, result = trained[generator]
    history = result.history
    assert [h["epoch"] for h in history] == [1, 2]
    assert sum(h["generator_steps"] for h in history) == 3  # 3 critic steps an epoch (36 clips / 12), n_critic 2
    for h in history:
        for k in ("d_loss", "wasserstein", "gp"):
            assert np.isfinite(h[k]), (k, h)
    assert all(np.isfinite(h["g_loss"]) for h in history if "g_loss" in h)
    ckpt = load_checkpoint(path)
    torch.manual_seed(0)  # the trainer's initialisation
    fresh = DVGAN(DVGANConfig.from_dict(ckpt["config"])).state_dict()
    for part in ("generator.", "discriminator."):
        moved = [k for k in fresh if k.startswith(part) and not torch.equal(fresh[k], ckpt["state_dict"][k])]
        assert moved, part
    assert all(torch.isfinite(v).all() for v in ckpt["state_dict"].values() if v.is_floating_point())


def test_checkpoint_holds_plain_values_and_round_trips_through_the_sampler(trained, demo_clips):
    path, _ = trained["rnn"]
    ckpt = torch.load(path, weights_only=True)
    assert ckpt["kind"] == "dvgan" and ckpt["config"]["generator"] == "rnn" and ckpt["epoch"] == 2
    assert ckpt["config"]["vocab"][:3] == ["boxing", "drink", "dumbbell"]
    assert ckpt["dataset"]["actions"] == list(demo_clips.manifest.action_names)
    assert {"optimizer_g", "optimizer_d", "rng", "history", "format_version", "train_config"} <= set(ckpt)
    assert ckpt["train_config"]["n_critic"] == 2 and ckpt["train_config"]["gp_lambda"] == 10.0
    loaded = checkpoint.load_model(path)
    assert isinstance(loaded, checkpoint.LoadedBaseline) and loaded.kind == "dvgan"
    batch = generate.sample(loaded, ["walk", "jump"], 3, seed=5)
    assert batch.motions.shape == (6, 16, 24, 3) and list(batch.actions) == ["walk"] * 3 + ["jump"] * 3
    assert np.all(batch.motions[:, 0, 0] == 0) and np.isfinite(batch.motions).all()
    direct = model_from_checkpoint(ckpt).eval().generate(torch.tensor([1, 1, 1, 3, 3, 3]),
                                                         torch.Generator().manual_seed(5))
    assert np.array_equal(batch.motions, direct.numpy())


@pytest.mark.parametrize("generator", ["cnn", "rnn"])
def test_same_seed_same_samples(trained, generator):
    loaded = checkpoint.load_model(trained[generator][0])
    a = generate.sample(loaded, ["all"], 2, seed=1).motions
    assert np.array_equal(a, generate.sample(loaded, ["all"], 2, seed=1).motions)
    assert not np.allclose(a, generate.sample(loaded, ["all"], 2, seed=2).motions)


# -- generate.complete and the CLI ------------------------------------------------------------

def test_complete_checks_the_prefix(trained):
    loaded = checkpoint.load_model(trained["rnn"][0])
    good = np.random.default_rng(0).normal(size=(8, 24, 3)).astype(np.float32)
    batch = generate.complete(loaded, good, 5, ["walk"], 2, seed=0)
    assert batch.motions.shape == (2, 16, 24, 3)
    assert np.array_equal(batch.motions[:, :5], np.broadcast_to(good[:5] - good[:1, :1], (2, 5, 24, 3)))
    cases = [(good[:, :20], 5, "the prefix has 20 joints; the model's skeleton humanact12 has 24"),
             (good[:3], 5, "the prefix has 3 frames; --frames 5 needs at least 5"),
             (good, 16, "--frames must be between 1 and 15"), (good, 0, "--frames must be between 1 and 15")]
    for prefix, frames, message in cases:
        with pytest.raises(UserError, match=message.replace("-", r"\-")):
            generate.complete(loaded, prefix, frames, ["walk"], 2)
    with pytest.raises(UserError, match="is DVGAN-CNN, which does not complete; completion needs a DVGAN-RNN model"):
        generate.complete(checkpoint.load_model(trained["cnn"][0]), good, 5, ["walk"], 2)


def test_odmo_does_not_complete(demo_clips, tmp_path):
    from odmo_cli.training.odmo import TrainConfig, train_odmo

    tc = TrainConfig(epochs=1, batch_size=8, pairs_per_epoch=8, val_fraction=0.0, val_every=0, checkpoint_every=0)
    path = train_odmo(demo_clips, tc, tmp_path / "odmo.pt",
                      overrides={"motion_hidden": 8, "traj_hidden": 8, "encoder_fc": 8}).out
    with pytest.raises(UserError, match="is ODMO, which does not complete; completion needs a DVGAN-RNN model"):
        generate.complete(checkpoint.load_model(path), np.zeros((30, 24, 3), np.float32), 5, ["walk"], 2)


def test_cli_train_sample_and_complete(tmp_path, make_motion_folder):
    folder = make_motion_folder(tmp_path / "data", per_action=1, length=70)
    runner = CliRunner()
    model = tmp_path / "rnn.pt"
    res = runner.invoke(app, ["train", "dvgan", "--generator", "rnn", "--dataset", str(folder),
                              "--epochs", "1", "--batch-size", "6", "--n-critic", "2", "--out", str(model),
                              "--threads", "1", "--json"])
    assert res.exit_code == 0, res.output
    assert '"generator": "rnn"' in res.stdout and load_checkpoint(model)["kind"] == "dvgan"
    # 12 clips (one per action) at batch 6: 2 critic steps, so n_critic 2 gives one generator step
    assert load_checkpoint(model)["train_config"]["n_critic"] == 2 and '"generator_steps": 1' in res.stdout
    res = runner.invoke(app, ["sample", "--model", str(model), "--action", "walk", "--n", "3",
                              "--out", str(tmp_path / "s.npz")])
    assert res.exit_code == 0, res.output
    samples = np.load(tmp_path / "s.npz")
    assert samples["motions"].shape == (3, 60, 24, 3) and str(samples["skeleton"]) == "humanact12"
    prefix = tmp_path / "clip.npy"
    np.save(prefix, samples["motions"][0])
    res = runner.invoke(app, ["complete", "--model", str(model), "--prefix", str(prefix), "--frames", "20",
                              "--n", "2", "--action", "jump", "--out", str(tmp_path / "done.npz"), "--seed", "3"])
    assert res.exit_code == 0, res.output
    done = np.load(tmp_path / "done.npz")
    assert done["motions"].shape == (2, 60, 24, 3) and list(done["actions"]) == ["jump", "jump"]
    assert np.array_equal(done["motions"][:, :20], np.broadcast_to(samples["motions"][0][:20], (2, 20, 24, 3)))
    assert int(done["prefix_frames"]) == 20 and int(done["seed"]) == 3
    np.save(tmp_path / "bad.npy", samples["motions"][0][:, :22])
    res = runner.invoke(app, ["complete", "--model", str(model), "--prefix", str(tmp_path / "bad.npy"),
                              "--out", str(tmp_path / "bad.npz")])
    assert res.exit_code == 2 and "the prefix has 22 joints" in res.stderr and res.stderr.count("\n") == 1
    assert not (tmp_path / "bad.npz").exists()


def test_cli_complete_refuses_a_cnn_model(trained, tmp_path):
    prefix = tmp_path / "p.npy"
    np.save(prefix, np.zeros((30, 24, 3), dtype=np.float32))
    res = CliRunner().invoke(app, ["complete", "--model", str(trained["cnn"][0]), "--prefix", str(prefix),
                                   "--out", str(tmp_path / "x.npz")])
    assert res.exit_code == 2 and "completion needs a DVGAN-RNN model" in res.stderr
    assert not (tmp_path / "x.npz").exists()


@pytest.mark.parametrize("kind, message", [("garbage", "cannot read prefix"), ("truncated", "cannot read prefix"),
                                           ("nan", "holds NaN or infinite values"),
                                           ("shape", r"must be a \(frames, joints, 3\) array"),
                                           ("strings", r"must be a \(frames, joints, 3\) array")])
def test_read_prefix_refuses_bad_files(tmp_path, spoil_clip, kind, message):
    path = tmp_path / "p.npy"
    np.save(path, np.zeros((10, 24, 3), dtype=np.float32))
    assert generate.read_prefix(path).shape == (10, 24, 3)
    spoil_clip(path, kind)
    with pytest.raises(UserError, match=message):
        generate.read_prefix(path)
    with pytest.raises(UserError, match="prefix not found"):
        generate.read_prefix(tmp_path / "missing.npy")
