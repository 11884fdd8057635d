"""ODMO model, loss terms and its training (issue: ODMO model and `odmo train`); resume, Ctrl-C and
the non-finite stop are tested for every trainer in test_training_loop.py."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from odmo_cli.cli import app
from odmo_cli.checkpoint import load_model
from odmo_cli.data.demo import demo_folder
from odmo_cli.data.locate import resolve
from odmo_cli.data.readers import read_dataset
from odmo_cli import metrics
from odmo_cli.errors import UserError
from odmo_cli.models import losses
from odmo_cli.models.odmo import ODMO, ODMOConfig, condition, widen_pose_decoder
from odmo_cli.data.dataset import mirror, mirror_map
from odmo_cli.training import odmo as odmo_training
from odmo_cli.training.odmo import ODMOTrainer, TrainConfig, model_config_for, reconstruction_error, train_odmo


@pytest.fixture(scope="module")
def demo_clips():
    manifest, root = resolve(demo_folder("humanact12"))
    return read_dataset(root, manifest)


def tiny_config(**kw) -> ODMOConfig:
    base = dict(n_joints=4, n_classes=3, length=8, latent_dim=5, encoder_hidden=8, encoder_fc=16,
                traj_hidden=12, motion_hidden=12)
    base.update(kw)
    return ODMOConfig(**base)


# -- loss terms on hand-made inputs ----------------------------------------------------------

def test_contrastive_zero_for_different_classes_beyond_margin():
    mu1 = torch.zeros(2, 3)
    mu2 = torch.tensor([[6.0, 0, 0], [0, 0, 5.5]])
    out = losses.contrastive(mu1, mu2, torch.tensor([False, False]), alpha=5.0)
    assert torch.allclose(out, torch.zeros(2))


def test_contrastive_known_values():
    mu1 = torch.zeros(4, 2)
    mu2 = torch.tensor([[3.0, 4.0], [0.3, 0.0], [1.0, 0.0], [2.0, 0.0]])
    same = torch.tensor([False, True, True, False])
    out = losses.contrastive(mu1, mu2, same, alpha=5.0, deadzone=0.25)
    # d = 5 at the margin; same class inside the dead zone; same class d^2 = 1; different d = 2
    expected = torch.tensor([0.0, 0.0, 0.5 * (1 - 0.25), 0.5 * (5 - 2) ** 2])
    assert torch.allclose(out, expected, atol=1e-4)


def test_variance_prior_zero_at_target_and_closed_form():
    sigma2 = 0.05
    at_target = torch.full((1, 20), math.log(sigma2))
    assert losses.variance_prior(at_target, sigma2).abs().item() < 1e-5
    logvar = torch.zeros(1, 2)  # s^2 = 1
    expected = 0.5 * 2 * (1 / sigma2 - 1 - 0 + math.log(sigma2))
    assert losses.variance_prior(logvar, sigma2).item() == pytest.approx(expected, rel=1e-6)


def test_standard_kl_known_value():
    mu = torch.tensor([[1.0, 0.0]])
    assert losses.standard_kl(mu, torch.zeros(1, 2)).item() == pytest.approx(0.5)


def test_sequence_error_weights_the_up_axis():
    pred = torch.zeros(1, 2, 1, 3)
    target = torch.tensor([[[[1.0, 1.0, 0.0]], [[0.0, 2.0, 0.0]]]])
    w = losses.coordinate_weights(up_axis=1, up_weight=5.0)
    # frame 1: (1 + 5) / 3 = 2; frame 2: (5 * 4) / 3
    assert losses.sequence_error(pred, target, w).item() == pytest.approx(2 + 20 / 3)


def test_terms_vanish_for_a_perfect_reconstruction():
    cfg = tiny_config()
    motion = torch.randn(4, cfg.length, cfg.n_joints, 3)
    motion = motion - motion[:, :1, :1]
    out = {"trajectory": motion[:, :, 0], "motion": motion, "mu": torch.zeros(4, 5),
           "logvar": torch.full((4, 5), math.log(cfg.sigma2))}
    terms = losses.odmo_terms(out, motion, torch.tensor([0, 1, 0, 1]), cfg)
    for k in ("r", "mre", "cons"):
        assert terms[k].item() == pytest.approx(0.0, abs=1e-10)
    # same-class pairs at distance 0 and no prior penalty: L_es is zero too
    assert terms["es"].item() == pytest.approx(0.0, abs=1e-5)


def test_trajectory_loss_position_vs_velocity_known_values():
    """A constant drift of 0.1 per frame along x: positions err by 0.1 t, velocities by 0.1 each step."""
    cfg = tiny_config()
    T = cfg.length
    motion = torch.zeros(1, T, cfg.n_joints, 3)
    drift = torch.zeros(1, T, 3)
    drift[0, :, 0] = 0.1 * torch.arange(1, T + 1)
    out = {"trajectory": drift, "motion": motion, "mu": torch.zeros(1, 5), "logvar": torch.zeros(1, 5)}
    pos = losses.odmo_terms(out, motion, torch.tensor([0]), cfg)["r"].item()
    vel = losses.odmo_terms(out, motion, torch.tensor([0]), tiny_config(traj_loss="velocity"))["r"].item()
    # per frame: the mean over the 3 coordinates of the squared error, summed over time
    assert pos == pytest.approx(sum((0.1 * t) ** 2 / 3 for t in range(1, T + 1)))
    assert vel == pytest.approx(T * 0.1 ** 2 / 3)
    with pytest.raises(ValueError, match="traj_loss"):
        tiny_config(traj_loss="angles")
    with pytest.raises(ValueError, match="sigma2 and recon_weight must be positive"):
        tiny_config(sigma2=0.0)


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


def test_ablation_switches_change_the_total():
    cfg = tiny_config()
    terms = {"mre": torch.tensor(1.0), "es": torch.tensor(2.0), "vae": torch.tensor(3.0),
             "r": torch.tensor(4.0), "cons": torch.tensor(5.0)}
    assert losses.total_loss(terms, cfg).item() == 12.0
    assert losses.total_loss(terms, tiny_config(use_es=False)).item() == 13.0
    assert losses.total_loss(terms, tiny_config(use_traj=False, use_cons=False)).item() == 3.0
    # the release's pair sum weighs every reconstruction term twice, never L_es
    assert losses.total_loss(terms, tiny_config(recon_weight=2.0)).item() == 22.0
    assert losses.total_loss(terms, tiny_config(recon_weight=2.0, use_traj=False)).item() == 14.0


def circling(T: int = 60, J: int = 4, radius: float = 0.2, phase: float = 0.0) -> torch.Tensor:
    """Every non-root joint circles its rest offset with the same radius: (1, T, J, 3)."""
    t = torch.arange(T, dtype=torch.float64) * 2 * math.pi / 30 + phase
    m = torch.zeros(1, T, J, 3, dtype=torch.float64)
    m[0, :, 1:, 0] = radius * torch.cos(t)[:, None] + torch.arange(1, J)
    m[0, :, 1:, 2] = radius * torch.sin(t)[:, None]
    m[0, :, :, 0] += 0.05 * torch.arange(T)[:, None]  # the root's walk is not the body's motion
    return m


def test_body_motion_stats_match_the_metrics():
    from odmo_cli import metrics

    motion = torch.randn(5, 40, 6, 3, dtype=torch.float64).cumsum(1) * 0.01
    speed, amplitude = losses.body_motion_stats(motion)  # (5, 5) each: per clip and joint
    assert speed.shape == (5, 5)
    assert np.allclose(speed.mean(1).numpy(), metrics.body_speed(motion.numpy()), atol=1e-6)
    assert np.allclose(amplitude.mean(1).numpy(), metrics.body_amplitude(motion.numpy()), atol=1e-6)


def test_energy_error_known_values():
    target = circling()
    assert losses.energy_error(target, target).item() == pytest.approx(0.0, abs=1e-9)
    # phase-blind: the same circles half a turn later ask for no change
    assert losses.energy_error(circling(phase=math.pi), target).item() == pytest.approx(0.0, abs=1e-9)
    # circles of half the radius: speed and amplitude both off by half -> 0.25 + 0.25
    assert losses.energy_error(circling(radius=0.1), target).item() == pytest.approx(0.5, rel=1e-6)
    # a body that stands still against one that does not: 1 + 1
    still = circling(radius=0.0)
    assert losses.energy_error(still, target).item() == pytest.approx(2.0, rel=1e-4)  # sqrt(x + 1e-12)
    # a still target is not divided by zero: the floor (0.005 per frame) takes over
    assert torch.isfinite(losses.energy_error(target, still)).all()
    assert losses.energy_error(still, still).item() == pytest.approx(0.0, abs=1e-9)


def test_energy_error_has_finite_gradients_and_pushes_motion_out():
    target = circling()
    pred = circling(radius=0.1).requires_grad_(True)
    losses.energy_error(pred, target).sum().backward()
    assert torch.isfinite(pred.grad).all()
    still = circling(radius=0.0).requires_grad_(True)  # the square root's gradient at zero motion
    losses.energy_error(still, target).sum().backward()
    assert torch.isfinite(still.grad).all()
    # a gradient step grows the small circles: their error goes down
    stepped = (pred - 0.05 * pred.grad).detach()
    assert losses.energy_error(stepped, target).item() < losses.energy_error(pred.detach(), target).item()


def test_energy_weight_enters_the_total():
    terms = {"mre": torch.tensor(1.0), "es": torch.tensor(2.0), "vae": torch.tensor(3.0),
             "r": torch.tensor(4.0), "cons": torch.tensor(5.0), "vel": torch.tensor(0.5),
             "energy": torch.tensor(0.25)}
    assert losses.total_loss(terms, tiny_config()).item() == 12.0
    assert losses.total_loss(terms, tiny_config(energy_weight=4.0)).item() == 13.0
    assert losses.total_loss(terms, tiny_config(energy_weight=4.0, recon_weight=2.0)).item() == 24.0
    with pytest.raises(ValueError, match="energy_weight and free_energy_weight must be non-negative"):
        tiny_config(energy_weight=-1.0)
    terms["free_energy"] = torch.tensor(0.5)
    assert losses.total_loss(terms, tiny_config(free_energy_weight=2.0)).item() == 13.0
    assert losses.total_loss(terms, tiny_config(energy_weight=4.0, free_energy_weight=2.0, recon_weight=2.0)).item() == 26.0
    with pytest.raises(ValueError, match="non-negative, got 0.0, 0.0, -1.0"):
        tiny_config(free_energy_weight=-1.0)


def test_mixed_energy_error_asks_for_the_mixture_of_two_clips():
    big, small = circling(radius=0.2), circling(radius=0.1)
    lam = torch.tensor([0.5], dtype=torch.float64)
    # speed and amplitude grow with the radius: halfway between 0.2 and 0.1 moves like radius 0.15
    assert losses.mixed_energy_error(circling(radius=0.15), big, small, lam).item() == pytest.approx(0.0, abs=1e-9)
    assert losses.mixed_energy_error(big, big, small, lam).item() == pytest.approx(2 * (0.05 / 0.15) ** 2, rel=1e-6)
    # lam = 1 is the first clip's energy_error, lam = 0 the second's; phase-blind as energy_error
    pred = circling(radius=0.12, phase=1.0)
    assert losses.mixed_energy_error(pred, big, small, torch.ones(1, dtype=torch.float64)).item() == pytest.approx(
        losses.energy_error(pred, big).item())
    assert losses.mixed_energy_error(pred, big, small, torch.zeros(1, dtype=torch.float64)).item() == pytest.approx(
        losses.energy_error(pred, small).item())


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
    with pytest.raises(ValueError, match="mix_energy_weight must be non-negative"):
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


# -- model -----------------------------------------------------------------------------------

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


def test_pose_loss_body_counts_the_roots_path_once():
    """pose_loss="body": L_mre compares every joint but the root about the root, and the root itself;
    a path off by d costs d^2 in every joint of the world-frame loss, in the root alone here."""
    cfg = tiny_config()  # J = 4, T = 8, the vertical axis weighted x5
    motion = torch.randn(2, cfg.length, cfg.n_joints, 3)
    about = losses.about_root(motion)
    assert torch.equal(about[:, :, 0], motion[:, :, 0])
    assert torch.allclose(about[:, :, 1:] + motion[:, :, :1], motion[:, :, 1:])
    off = motion + torch.tensor([0.1, 0.0, 0.0])  # the whole body, root included, shifted along x
    out = {"trajectory": motion[:, :, 0], "motion": off, "mu": torch.zeros(2, 5),
           "logvar": torch.full((2, 5), math.log(cfg.sigma2))}
    labels = torch.tensor([0, 0])
    world = losses.odmo_terms(out, motion, labels, cfg)["mre"].item()
    body = losses.odmo_terms(out, motion, labels, replace(cfg, pose_loss="body"))["mre"].item()
    assert world == pytest.approx(cfg.length * 0.01 / 3, rel=1e-5)  # 0.1^2 in one of 3 coordinates, T frames
    assert body == pytest.approx(world / cfg.n_joints, rel=1e-5)  # the root alone
    bent = motion.clone()
    bent[:, :, 1:, 1] += 0.1  # the body off (vertically), the root right: both forms see the same error
    out["motion"] = bent
    world = losses.odmo_terms(out, motion, labels, cfg)["mre"].item()
    assert world == pytest.approx(cfg.length * 5 * 0.01 / 3 * 3 / 4, rel=1e-5)
    assert losses.odmo_terms(out, motion, labels, replace(cfg, pose_loss="body"))["mre"].item() == pytest.approx(world, rel=1e-5)
    with pytest.raises(ValueError, match="pose_loss must be one of world, body"):
        tiny_config(pose_loss="root")


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


# -- training --------------------------------------------------------------------------------

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
                        tmp_path / "m.pt", {"motion_hidden": 16})
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
        metrics.mean_pose_error(real.numpy(), labels.numpy()), rel=1e-5)
    # the held-out bodies against the training clips' own motions: a lookup by code, and the best clip
    val = ckpt["split"]["val"].numpy()
    held, held_labels = crops_from_start(demo_clips, val, 60)
    with torch.no_grad():
        held_codes = model.encode(held)[0]
    retrieved = metrics.retrieval_errors(held.numpy(), held_labels.numpy(), held_codes.numpy(), real.numpy(),
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
    with pytest.raises(UserError, match="--crops must be random or first"):
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
    with pytest.raises(UserError, match="--weight-decay must not be negative"):
        TrainConfig(weight_decay=-1.0)


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
        with pytest.raises(UserError, match=r"--decoder-dropout must be in \[0, 1\)"):
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
        with pytest.raises(UserError, match=f"--code-noise must be a finite number >= 0, got {bad}"):
            TrainConfig(code_noise=bad)


def test_free_running_term_starts_once_teacher_forcing_has_decayed():
    assert TrainConfig(epochs=1000, tf_epochs=500).free_start() == 500
    assert TrainConfig(epochs=300).free_start() == 150  # teacher forcing decays over all epochs: from half
    assert TrainConfig(epochs=300, tf_epochs=100, free_from=7).free_start() == 7
    with pytest.raises(UserError, match="--free-from must be an epoch"):
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


def test_init_starts_a_stage_from_a_finished_model(demo_clips, tmp_path):
    """--init: the weights and model config of a finished file (loss options on top), this run's
    schedule and a fresh optimizer; the checkpoint says where it started. Not with --resume."""
    first = tmp_path / "first.pt"
    small = {"latent_dim": 4, "encoder_fc": 16, "traj_hidden": 16, "motion_hidden": 16, "energy_weight": 0.5}
    train_odmo(demo_clips, TrainConfig(epochs=2, batch_size=8, val_every=0, threads=1), first, small)
    start = torch.load(first, weights_only=True)
    tc = TrainConfig(epochs=1, batch_size=8, val_every=0, threads=1, lr=1e-9, lr_final=1e-9, tf_start=0.0, tf_end=0.0)
    second = tmp_path / "second.pt"
    train_odmo(demo_clips, tc, second, {"free_energy_weight": 1.0}, init=first)
    ckpt = torch.load(second, weights_only=True)
    assert ckpt["config"] == {**start["config"], "free_energy_weight": 1.0}  # not the preset's scales
    assert ckpt["init"] == {"source": "first.pt", "epoch": 2, "train_config": start["train_config"],
                            "config": start["config"]}
    assert ckpt["epoch"] == 1 and ckpt["train_config"]["tf_end"] == 0.0
    moved = max(float((ckpt["state_dict"][k] - v).abs().max()) for k, v in start["state_dict"].items()
                if v.is_floating_point() and "running" not in k and "num_batches" not in k)
    assert moved < 1e-5  # a learning rate of 1e-9: the first stage's weights, as they were
    fresh = tmp_path / "fresh.pt"
    train_odmo(demo_clips, tc, fresh, small)
    assert torch.load(fresh, weights_only=True)["state_dict"]["motion.out.weight"].ne(
        ckpt["state_dict"]["motion.out.weight"]).any()
    with pytest.raises(UserError, match="either --init"):
        train_odmo(demo_clips, tc, tmp_path / "x.pt", init=first, resume=second)
    with pytest.raises(UserError, match=r"^--init first.pt's weights do not fit this model: size mismatch"):
        train_odmo(demo_clips, tc, tmp_path / "x.pt", {"traj_hidden": 8}, init=first)
    with pytest.raises(UserError, match=r"^--motion-hidden 8: --init first.pt's pose decoder has 16 units; "
                                        r"it can be widened, not narrowed$"):
        train_odmo(demo_clips, tc, tmp_path / "x.pt", {"motion_hidden": 8}, init=first)
    with pytest.raises(UserError, match=r"^--init first.pt draws poses in the world frame; .* not path$"):
        train_odmo(demo_clips, tc, tmp_path / "x.pt", {"pose_frame": "path"}, init=first)  # as a ship stage could
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
    train_odmo(demo_clips, TrainConfig(epochs=1, batch_size=8, val_every=0, threads=1), first, small)
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


def test_teacher_forcing_decays_linearly():
    tc = TrainConfig(epochs=11, tf_start=1.0, tf_end=0.3)
    assert tc.teacher_rate(0) == 1.0
    assert tc.teacher_rate(10) == pytest.approx(0.3)
    assert tc.teacher_rate(5) == pytest.approx(0.65)
    assert TrainConfig(epochs=100, tf_epochs=10).teacher_rate(50) == pytest.approx(0.3)


# -- CLI -------------------------------------------------------------------------------------

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
        (["--code-noise", "-1"], "--code-noise must be a finite number >= 0, got -1.0"),
        (["--pose-loss", "root"], "--pose-loss must be one of world, body, got 'root'"),
        (["--mix-energy-weight", "-1"], "--mix-energy-weight must be a finite number >= 0, got -1.0"),
        (["--decoder-dropout", "1"], "--decoder-dropout must be in [0, 1), got 1.0"),
        (["--weight-decay", "-1"], "--weight-decay must not be negative, got -1.0"),
        (["--free-energy-weight", "-1"], "--free-energy-weight must be a finite number >= 0, got -1.0"),
        (["--height-weight", "-1"], "--height-weight must be a finite number >= 0, got -1.0"),
        (["--root", "hips"], "unknown --root 'hips'; valid: trajectory, decoder, ground"),
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


def test_a_stage_keeps_the_split_of_the_file_it_starts_from(demo_clips, tmp_path):
    """A stage run with another --seed draws its own pairs and noise but validates on the earlier
    stages' held-out clips and never trains on them; resuming it keeps that split too."""
    from odmo_cli.data.dataset import split_indices

    small = {"latent_dim": 4, "encoder_fc": 16, "traj_hidden": 16, "motion_hidden": 16}
    first = tmp_path / "first.pt"
    train_odmo(demo_clips, TrainConfig(epochs=1, batch_size=8, val_every=0, threads=1, seed=0, val_fraction=0.34),
               first, small)  # one clip of each action held out
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
               fresh, small)
    assert torch.equal(torch.load(fresh, weights_only=True)["split"]["val"], other)


def hopping(T: int = 60, height: float = 0.2, phase: float = 0.0) -> torch.Tensor:
    """A rigid 3-joint body whose root bobs vertically (y) while it walks along x: (1, T, 3, 3)."""
    t = torch.arange(T, dtype=torch.float64) * 2 * math.pi / 20 + phase
    m = torch.zeros(1, T, 3, 3, dtype=torch.float64)
    m[0, :, :, 0] = 0.05 * torch.arange(T)[:, None] + torch.arange(3)
    m[0, :, :, 1] = height * torch.sin(t)[:, None]
    return m


def test_root_height_stats_match_the_metrics():
    from odmo_cli import metrics

    motion = torch.randn(5, 40, 4, 3, dtype=torch.float64).cumsum(1) * 0.01
    speed, amplitude = losses.root_height_stats(motion, up_axis=1)
    m_speed, m_amp = metrics.root_height_speed_and_amplitude(motion.numpy(), up_axis=1)
    assert np.allclose(speed.numpy(), m_speed, atol=1e-9) and np.allclose(amplitude.numpy(), m_amp, atol=1e-6)
    # a root that keeps its height has neither, whatever it does on the ground plane
    flat = hopping(height=0.0)
    assert metrics.root_height_speed_and_amplitude(flat.numpy(), 1)[1][0] == pytest.approx(0.0, abs=1e-12)
    # nor does a steady sink: amplitude is the spread about the height's line over time
    sinking = flat.clone()
    sinking[..., 1] -= 0.01 * torch.arange(flat.shape[1], dtype=torch.float64)[:, None]
    speed, amplitude = metrics.root_height_speed_and_amplitude(sinking.numpy(), 1)
    assert amplitude[0] == pytest.approx(0.0, abs=1e-9) and speed[0] == pytest.approx(0.01)
    assert losses.root_height_stats(sinking, 1)[1].item() == pytest.approx(0.0, abs=1e-5)  # sqrt(x + 1e-12)


def test_height_error_known_values():
    target = hopping()
    assert losses.height_error(target, target, 1).item() == pytest.approx(0.0, abs=1e-9)
    # phase-blind: the same hops half a period later ask for no change
    assert losses.height_error(hopping(phase=math.pi), target, 1).item() == pytest.approx(0.0, abs=1e-6)
    # hops of half the height, floors 0 -> speed and amplitude both log(1/2)^2; twice the height: the same
    half = losses.height_error(hopping(height=0.1), target, 1, speed_floor=0.0, amplitude_floor=0.0).item()
    assert half == pytest.approx(2 * math.log(2) ** 2, rel=1e-6)
    assert losses.height_error(hopping(height=0.4), target, 1, 0.0, 0.0).item() == pytest.approx(half, rel=1e-6)
    # the floors keep a root that hardly moves from weighing like a jump: a 1 mm bob against 2 mm
    small = losses.height_error(hopping(height=0.001), hopping(height=0.002), 1).item()
    assert small < 0.02 < 0.2 < losses.height_error(hopping(height=0.1), target, 1).item()
    # the body about its root is the same in all three: the energy term cannot tell them apart
    assert losses.energy_error(hopping(height=0.0), target).item() == pytest.approx(0.0, abs=1e-9)
    flat = hopping(height=0.0).requires_grad_(True)
    err = losses.height_error(flat, target, 1)
    (st, at), (s0, a0) = losses.root_height_stats(target, 1), losses.root_height_stats(flat.detach(), 1)
    expect = math.log((s0.item() + 0.002) / (st.item() + 0.002)) ** 2 + math.log((a0.item() + 0.01) / (at.item() + 0.01)) ** 2
    assert err.item() == pytest.approx(expect, rel=1e-6) and err.item() > 3.0
    err.sum().backward()
    assert torch.isfinite(flat.grad).all()
    assert torch.isfinite(losses.height_error(target, hopping(height=0.0), 1)).all()  # floored, not divided by 0


def test_height_weight_enters_the_total_on_the_root_sampling_draws():
    cfg = tiny_config(height_weight=2.0, root="ground")
    target = hopping(T=cfg.length).float().expand(2, -1, -1, -1)
    target = torch.cat([target, torch.zeros(2, cfg.length, cfg.n_joints - 3, 3)], dim=2)  # (2, T, J, 3)
    out = {"trajectory": target[:, :, 0], "motion": target, "free_motion": target.clone(),
           "mu": torch.zeros(2, 5), "logvar": torch.full((2, 5), math.log(cfg.sigma2))}
    out["free_motion"][..., 1] = 0.0  # the free-running decode does not leave the ground
    terms = losses.odmo_terms(out, target, torch.tensor([0, 0]), cfg)
    assert terms["height"].item() == pytest.approx(losses.height_error(out["free_motion"], target, 1).mean().item())
    assert terms["height"].item() > 1.0  # the free decode's, not the first's (which is perfect)
    # with the trajectory's root drawn, the trajectory's height is what the term reads
    on_path = losses.odmo_terms(out, target, torch.tensor([0, 0]), replace(cfg, root="trajectory"))
    assert on_path["height"].item() == pytest.approx(0.0, abs=1e-9)
    out["trajectory"] = out["trajectory"].clone()
    out["trajectory"][..., 1] = 0.0  # a path that does not leave the ground
    on_path = losses.odmo_terms(out, target, torch.tensor([0, 0]), replace(cfg, root="trajectory"))
    assert on_path["height"].item() == pytest.approx(terms["height"].item(), rel=1e-6)
    base = {k: torch.tensor(1.0) for k in ("mre", "es", "vae", "r", "cons")}
    assert losses.total_loss({**base, "height": torch.tensor(0.5)}, cfg).item() == 5.0
    assert losses.total_loss({**base, "height": torch.tensor(0.5)}, tiny_config()).item() == 4.0
    with pytest.raises(ValueError, match="height_weight must be non-negative"):
        tiny_config(height_weight=-1.0)


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


def test_train_parts_leaves_the_other_networks_as_they_were(demo_clips, tmp_path):
    """--train-parts trajectory: a stage moves the trajectory generator's weights only; an unknown
    part is a one-line user error before any data is read."""
    first = tmp_path / "first.pt"
    small = {"latent_dim": 4, "encoder_fc": 16, "traj_hidden": 16, "motion_hidden": 16}
    train_odmo(demo_clips, TrainConfig(epochs=1, batch_size=8, val_every=0, threads=1), first, small)
    start = torch.load(first, weights_only=True)["state_dict"]
    tc = TrainConfig(epochs=2, batch_size=8, val_every=0, threads=1, lr=1e-2, train_parts="trajectory")
    second = tmp_path / "second.pt"
    train_odmo(demo_clips, tc, second, {"height_weight": 1.0}, init=first)
    after = torch.load(second, weights_only=True)
    assert after["train_config"]["train_parts"] == "trajectory"
    moved = {k.split(".")[0] for k, v in after["state_dict"].items() if not torch.equal(v, start[k])}
    assert moved == {"trajectory"}
    assert TrainConfig(train_parts="motion, trajectory").parts() == ["motion", "trajectory"]
    assert TrainConfig().parts() == ["encoder", "trajectory", "motion"]
    with pytest.raises(UserError, match=r"^unknown part 'decoder' to train; valid: encoder, trajectory, motion"):
        TrainConfig(train_parts="trajectory,decoder")
    res = CliRunner().invoke(app, ["train", "--dataset", str(demo_folder("humanact12")), "--train-parts", ",",
                                   "--out", str(tmp_path / "y.pt")])
    assert res.exit_code == 2 and "unknown part ',' to train" in res.stderr and "Traceback" not in res.stderr
    assert res.stderr.count("\n") == 1 and not (tmp_path / "y.pt").exists()
