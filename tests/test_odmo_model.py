"""The ODMO network (models/odmo.py): its config and presets, the decodes forward() adds (free-running,
mixed), the trajectory and pose decoders against their step-by-step definition, and the root readouts."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch
from typer.testing import CliRunner

from odmo_cli.cli import app
from odmo_cli.models import losses
from odmo_cli.models.odmo import ODMO, ODMOConfig, condition
from odmo_cli.training.odmo import model_config_for
from conftest import tiny_config




# -- config and presets -----------------------------------------------------------------------------

@pytest.mark.parametrize("name, value", [("sigma2", float("nan")), ("recon_weight", float("inf")),
                                         ("energy_weight", float("nan")), ("height_weight", float("-inf")),
                                         ("alpha", float("nan"))])
def test_config_refuses_nan_and_inf_however_it_is_built(name, value):
    # nan passes every `x < 0` check; a recipe's "model" values and a checkpoint's config reach
    # ODMOConfig through from_dict, not through the CLI's own checks
    with pytest.raises(ValueError, match=f"^{name} must be a finite number, got {value}$"):
        ODMOConfig.from_dict({**ODMOConfig().to_dict(), name: value})
    with pytest.raises(ValueError, match=f"^{name} must be a finite number"):
        tiny_config(**{name: value})


def test_presets_per_dataset():
    from odmo_cli.models.odmo import preset_values

    assert preset_values("paper", "humanact12") == {}
    assert preset_values("release", "humanact12") == {"sigma2": 0.0025, "recon_weight": 2.0, "up_weight": 5.0}
    assert preset_values("release", "cmu_mocap")["up_weight"] == 1.0
    # the default adds L_energy to the release's scales, for every dataset
    assert preset_values("odmo", "cmu_mocap") == {"sigma2": 0.0025, "recon_weight": 2.0, "up_weight": 1.0,
                                                  "energy_weight": 2.0, "free_energy_weight": 2.0}
    assert preset_values("odmo", "my_dataset") == {"sigma2": 0.0025, "recon_weight": 2.0, "energy_weight": 2.0,
                                                   "free_energy_weight": 2.0}
    with pytest.raises(ValueError, match="unknown preset 'best'; valid: paper, release, odmo"):
        preset_values("best", "humanact12")


# -- forward and decode -----------------------------------------------------------------------------

def test_mixed_decode_is_the_free_decode_of_mixed_codes_of_one_action():
    """forward(mix=lam): the pairs of one action (rows k, B/2 + k) are decoded free-running from
    lam z_k + (1 - lam) z_{B/2+k} with the end points mixed alike; the term is the mean over all pairs,
    0 for pairs of two actions, and enters the total with its weight."""
    torch.manual_seed(0)
    cfg = tiny_config(root="decoder", mix_energy_weight=2.0)
    model = ODMO(cfg).eval()
    motion = torch.randn(6, cfg.length, cfg.n_joints, 3).cumsum(1)
    labels = torch.tensor([0, 1, 2, 0, 2, 2])  # pairs (0, 3) and (2, 5) are of one action, (1, 4) is not
    lam = torch.tensor([0.25, 0.5, 0.9])
    out = model(motion, labels, eps=torch.zeros(6, cfg.latent_dim), mix=lam)
    assert out["mix_rows"].tolist() == [0, 2]
    w = torch.tensor([[0.25], [0.9]])
    z = w * out["z"][[0, 2]] + (1 - w) * out["z"][[3, 5]]
    end = w * motion[[0, 2], -1, 0] + (1 - w) * motion[[3, 5], -1, 0]
    with torch.no_grad():
        _, expected = model.decode(z, torch.tensor([0, 2]), end)  # free-running, the decoder's own root
    assert torch.allclose(out["mix_motion"], expected, atol=1e-6)
    terms = losses.odmo_terms(out, motion, labels, cfg)
    per_pair = losses.mixed_energy_error(expected, motion[[0, 2]], motion[[3, 5]], torch.tensor([0.25, 0.9]))
    assert terms["mix_energy"].item() == pytest.approx(per_pair.sum().item() / 3, rel=1e-5)
    assert terms["mix_energy"].item() > 0
    plain = losses.total_loss(terms, replace(cfg, mix_energy_weight=0.0))
    assert losses.total_loss(terms, cfg).item() == pytest.approx(plain.item() + 2.0 * terms["mix_energy"].item(), rel=1e-6)
    # without mix, or with no pair of one action, nothing is mixed and the term is 0
    assert "mix_motion" not in model(motion, labels, eps=torch.zeros(6, cfg.latent_dim))
    apart = model(motion, torch.tensor([0, 1, 2, 1, 2, 0]), eps=torch.zeros(6, cfg.latent_dim), mix=lam)
    assert "mix_motion" not in apart
    assert losses.odmo_terms(apart, motion, torch.tensor([0, 1, 2, 1, 2, 0]), cfg)["mix_energy"].item() == 0.0
    with pytest.raises(ValueError, match="mix_energy_weight must be a number >= 0"):
        tiny_config(mix_energy_weight=-1.0)


def test_free_decode_is_the_sampling_decode_of_the_same_codes():
    """forward(free=True) adds the decode of the same codes without teacher forcing, which is what
    sampling runs; the free-running energy term is then computed on it (and is 0 without it)."""
    torch.manual_seed(0)
    cfg = tiny_config(root="decoder")  # the losses see the pose decoder's own output
    model = ODMO(cfg).eval()
    motion = torch.randn(4, cfg.length, cfg.n_joints, 3).cumsum(1)
    labels = torch.tensor([0, 1, 2, 0])
    teacher = torch.ones(cfg.length, dtype=torch.bool)
    out = model(motion, labels, eps=torch.zeros(4, cfg.latent_dim), teacher=teacher, free=True)
    assert "free_motion" not in model(motion, labels, eps=torch.zeros(4, cfg.latent_dim), teacher=teacher)
    _, sampled = model.decode(out["z"], labels, motion[:, -1, 0])
    assert torch.equal(out["free_motion"], sampled)
    assert not torch.allclose(out["motion"], sampled)  # the teacher-forced pass differs
    terms = losses.odmo_terms(out, motion, labels, cfg)
    assert terms["free_energy"].item() == pytest.approx(losses.energy_error(sampled, motion).mean().item())
    out.pop("free_motion")
    assert losses.odmo_terms(out, motion, labels, cfg)["free_energy"].item() == 0.0


def test_shared_trajectory_gives_the_gradients_of_two_separate_decodes():
    """The free pass reuses the teacher-forced pass's trajectory and trajectory encoding; the
    gradients are those of decoding the same codes twice (up to rounding)."""
    torch.manual_seed(0)
    cfg = tiny_config(root="decoder")
    model = ODMO(cfg).train()
    motion = torch.randn(4, cfg.length, cfg.n_joints, 3).cumsum(1)
    labels = torch.tensor([0, 1, 2, 0])
    teacher = torch.rand(cfg.length) < 0.5
    eps = torch.randn(4, cfg.latent_dim)

    def grads(out):
        model.zero_grad()
        (out["motion"].square().mean() + 2 * out["free_motion"].square().mean()).backward()
        return [p.grad.clone() for p in model.parameters()]

    shared = grads(model(motion, labels, eps=eps, teacher=teacher, free=True))
    out = model(motion, labels, eps=eps, teacher=teacher)
    out["free_motion"] = model.decode(out["z"], labels, motion[:, -1, 0])[1]
    separate = grads(out)
    assert all(torch.allclose(a, b, rtol=1e-4, atol=1e-7) for a, b in zip(shared, separate))
    assert any(a.abs().sum() > 0 for a in shared)


def test_no_forced_step_reuses_the_first_decode_as_the_free_one():
    """Without a teacher-forced step (the later stages' rate 0) the first decode is already the
    sampling decode: it is not run twice, and the loss and gradients are those of running it twice."""
    torch.manual_seed(0)
    cfg = tiny_config(root="decoder")
    model = ODMO(cfg).train()
    motion = torch.randn(4, cfg.length, cfg.n_joints, 3).cumsum(1)
    labels = torch.tensor([0, 1, 2, 0])
    eps = torch.randn(4, cfg.latent_dim)
    for teacher in (None, torch.zeros(cfg.length, dtype=torch.bool), torch.zeros(4, cfg.length, dtype=torch.bool)):
        out = model(motion, labels, eps=eps, teacher=teacher, free=True)
        assert out["free_motion"] is out["motion"]
    assert model(motion, labels, eps=eps, teacher=torch.ones(cfg.length, dtype=torch.bool),
                 free=True)["free_motion"] is not None  # forced steps: a second decode (tested above)

    def grads(out):
        model.zero_grad()
        (out["motion"].square().mean() + 2 * out["free_motion"].square().mean()).backward()
        return [p.grad.clone() for p in model.parameters()]

    reused = grads(model(motion, labels, eps=eps, teacher=None, free=True))
    out = model(motion, labels, eps=eps)
    out["free_motion"] = model.decode(out["z"], labels, motion[:, -1, 0])[1]
    twice = grads(out)
    assert all(torch.allclose(a, b, rtol=1e-4, atol=1e-7) for a, b in zip(reused, twice))
    assert any(a.abs().sum() > 0 for a in reused)


def test_condition_is_the_flattened_outer_product():
    onehot = torch.tensor([[0.0, 1.0, 0.0]])
    z = torch.tensor([[1.0, 2.0]])
    assert condition(onehot, z).tolist() == [[0.0, 0.0, 1.0, 2.0, 0.0, 0.0]]


def test_shapes_and_trajectory_is_cumulative():
    torch.manual_seed(0)
    cfg = tiny_config()
    model = ODMO(cfg).eval()
    motion = torch.randn(3, cfg.length, cfg.n_joints, 3)
    out = model(motion, torch.tensor([0, 1, 2]))
    assert out["motion"].shape == (3, cfg.length, cfg.n_joints, 3)
    assert out["trajectory"].shape == (3, cfg.length, 3)
    assert out["mu"].shape == out["logvar"].shape == (3, cfg.latent_dim)
    onehot = torch.nn.functional.one_hot(torch.tensor([0, 1, 2]), 3).float()
    vel = model.trajectory(condition(onehot, out["z"]), motion[:, -1, 0])
    assert torch.allclose(out["trajectory"], torch.cumsum(vel, 1), atol=1e-6)


def test_root_readout():
    """root="trajectory" places the pose decoder's body (joints about its root, unchanged) on the
    trajectory generator's path; "decoder" keeps the decoder's own root; training sees the latter."""
    torch.manual_seed(0)
    own = ODMO(tiny_config(root="decoder")).eval()
    placed = ODMO(tiny_config()).eval()
    placed.load_state_dict(own.state_dict())
    z, lab, end = torch.randn(3, 5), torch.tensor([0, 1, 2]), torch.randn(3, 3)
    traj_a, a = own.decode(z, lab, end)
    traj_b, b = placed.decode(z, lab, end)
    assert torch.equal(traj_a, traj_b)
    assert torch.allclose(b[:, :, 0], traj_b, atol=1e-6)  # the root is the trajectory, every frame
    assert not torch.allclose(a[:, :, 0], traj_a, atol=1e-3)  # an untrained decoder's root is elsewhere
    assert torch.allclose(b - b[:, :, :1], a - a[:, :, :1], atol=1e-6)  # the same body about the root
    motion = torch.randn(3, 8, 4, 3)
    assert torch.equal(own(motion, lab, eps=torch.zeros(3, 5))["motion"],
                       placed(motion, lab, eps=torch.zeros(3, 5))["motion"])  # training's output: the decoder's
    with pytest.raises(ValueError, match="root must be one of trajectory, decoder"):
        tiny_config(root="warp")


def test_pose_frame_path_draws_the_body_about_the_generated_path():
    """pose_frame="path": the decoder's outputs (and teacher-forced inputs) are measured from the
    trajectory's point at each frame; the same weights give the world-frame output plus the path,
    and a teacher-forced step is fed the real previous pose less that point."""
    torch.manual_seed(0)
    world = ODMO(tiny_config(root="decoder")).eval()
    path = ODMO(tiny_config(root="decoder", pose_frame="path")).eval()
    path.load_state_dict(world.state_dict())
    z, lab, end = torch.randn(3, 5), torch.tensor([0, 1, 2]), torch.randn(3, 3)
    traj, a = world.decode(z, lab, end)
    traj_p, b = path.decode(z, lab, end)
    assert torch.equal(traj, traj_p)
    assert not torch.allclose(a[:, 1:], b[:, 1:], atol=1e-3)  # the free-running inputs differ from frame 1 on
    motion = torch.randn(3, 8, 4, 3).cumsum(1)
    forced = torch.ones(8, dtype=torch.bool)
    eps = torch.zeros(3, 5)
    out_p = path(motion, lab, eps=eps, teacher=forced)
    # every step teacher-forced: the decoder's own outputs are those of the world-frame decoder fed
    # the real poses less the path, and the motion is those outputs placed on the path
    shifted = world.motion(out_p["trajectory"], condition(torch.nn.functional.one_hot(lab, 3).float(), out_p["z"]),
                           (motion - out_p["trajectory"][:, :, None]).flatten(2), forced)
    assert torch.allclose(out_p["motion"], shifted.view(3, 8, 4, 3) + out_p["trajectory"][:, :, None], atol=1e-5)
    with pytest.raises(ValueError, match="pose_frame must be one of world, path"):
        tiny_config(pose_frame="root")
    result = CliRunner().invoke(app, ["train", "--pose-frame", "hips", "--epochs", "1"])
    assert result.exit_code == 2 and "--pose-frame must be one of world, path" in result.output
    result = CliRunner().invoke(app, ["train", "--pose-frame", "path", "--init", "stage.pt", "--epochs", "1"])
    assert result.exit_code == 2 and "keeps its file's" in result.output


def test_minus_re_variant_ignores_the_end_point():
    torch.manual_seed(0)
    model = ODMO(tiny_config(use_end_point=False)).eval()
    z, lab = torch.randn(2, 5), torch.tensor([0, 1])
    a, _ = model.decode(z, lab, torch.zeros(2, 3))
    b, _ = model.decode(z, lab, torch.full((2, 3), 3.0))
    assert torch.equal(a, b)
    model = ODMO(tiny_config()).eval()
    a, _ = model.decode(z, lab, torch.zeros(2, 3))
    b, _ = model.decode(z, lab, torch.full((2, 3), 3.0))
    assert not torch.allclose(a, b)


def test_ground_root_keeps_the_path_and_the_decoders_height():
    torch.manual_seed(0)
    cfg = tiny_config(root="decoder")
    model = ODMO(cfg).eval()
    z, labels, end = torch.randn(3, cfg.latent_dim), torch.tensor([0, 1, 2]), torch.randn(3, 3)
    with torch.no_grad():
        traj, own = model.decode(z, labels, end)
        model.cfg = replace(cfg, root="ground")
        _, ground = model.decode(z, labels, end)
    up = cfg.up_axis
    flat = [a for a in range(3) if a != up]
    assert torch.allclose(ground[:, :, 0][..., flat], traj[..., flat])  # on the trajectory's path
    assert torch.allclose(ground[:, :, 0, up], own[:, :, 0, up])  # at the decoder's height
    assert torch.allclose(ground - ground[:, :, :1], own - own[:, :, :1], atol=1e-6)  # the same body


# -- the pose decoder step by step ------------------------------------------------------------------

def _naive_decoder(gen, trajectory, cond, target, teacher):
    """The decoder written step by step from the paper: embed([prev, cond, t/T]) each step."""
    B, T = trajectory.shape[:2]
    _, (h, c) = gen.traj_rnn(gen.traj_act(gen.traj_embed(trajectory)))
    s0, s1 = (h[0], c[0]), (h[1], c[1])
    prev = torch.zeros(B, target.shape[-1])
    outs = []
    for t in range(T):
        if teacher[t]:
            prev = target[:, t - 1] if t > 0 else torch.zeros_like(prev)
        x = torch.cat([prev, cond, torch.full((B, 1), (t + 1) / T)], -1)
        s0 = gen.cell0(gen.act(gen.embed(x)), s0)
        s1 = gen.cell1(s0[0], s1)
        prev = gen.out(s1[0])
        outs.append(prev)
    return torch.stack(outs, 1)


@pytest.mark.parametrize("pattern", ["all", "none", "mixed"])
def test_decoder_matches_the_step_by_step_definition(pattern):
    torch.manual_seed(1)
    cfg = tiny_config()
    gen = ODMO(cfg).motion
    B, T, P = 3, cfg.length, cfg.n_joints * 3
    trajectory, cond = torch.randn(B, T, 3), torch.randn(B, cfg.n_classes * cfg.latent_dim)
    target = torch.randn(B, T, P)
    teacher = {"all": torch.ones(T, dtype=torch.bool), "none": torch.zeros(T, dtype=torch.bool),
               "mixed": torch.arange(T) % 3 == 0}[pattern]
    fast = gen(trajectory, cond, target, teacher)
    slow = _naive_decoder(gen, trajectory, cond, target, teacher)
    assert torch.allclose(fast, slow, atol=1e-5)
    # and so do the gradients, which the precomputed per-step inputs must route back unchanged
    weights = torch.randn(B, T, P)
    grads = [torch.autograd.grad((out * weights).sum(), list(gen.parameters())) for out in (fast, slow)]
    for g_fast, g_slow in zip(*grads):
        assert torch.allclose(g_fast, g_slow, atol=1e-5)
    assert any(g.abs().sum() > 0 for g in grads[0])


def test_decoder_dropout_masks_what_the_cells_pass_on(demo_clips):
    """keep of ones is no dropout; a dropped second cell leaves the output layer its bias alone."""
    torch.manual_seed(0)
    cfg = model_config_for(demo_clips, {"motion_hidden": 8, "traj_hidden": 8})
    gen = ODMO(cfg).motion
    traj, cond = torch.randn(3, 60, 3), torch.randn(3, cfg.n_classes * cfg.latent_dim)
    plain = gen(traj, cond)
    assert torch.equal(gen(traj, cond, keep=torch.ones(2, 3, 8)), plain)
    keep = torch.ones(2, 3, 8)
    keep[1, 0] = 0  # clip 0: every unit of the second cell dropped
    out = gen(traj, cond, keep=keep)
    assert torch.allclose(out[0], gen.out.bias.expand(60, -1)) and torch.equal(out[1:], plain[1:])
    keep = torch.ones(2, 3, 8)
    keep[0, 2, :4] = 0  # clip 2: half the first cell's outputs dropped, through every later step
    out = gen(traj, cond, keep=keep)
    assert torch.equal(out[:2], plain[:2]) and not torch.allclose(out[2], plain[2])
