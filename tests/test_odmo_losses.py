"""ODMO's loss terms (models/losses.py) on hand-made inputs with known values, and their
differentiable statistics against the network-free measures they twin (measures/diagnostics.py)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from odmo_cli.measures import diagnostics
from odmo_cli.models import losses
from conftest import tiny_config



# -- the terms and their total ----------------------------------------------------------------------

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
    with pytest.raises(ValueError, match="sigma2 must be a number > 0"):
        tiny_config(sigma2=0.0)


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


# -- the energy terms: the body's speed and amplitude about its root --------------------------------

def circling(T: int = 60, J: int = 4, radius: float = 0.2, phase: float = 0.0) -> torch.Tensor:
    """Every non-root joint circles its rest offset with the same radius: (1, T, J, 3)."""
    t = torch.arange(T, dtype=torch.float64) * 2 * math.pi / 30 + phase
    m = torch.zeros(1, T, J, 3, dtype=torch.float64)
    m[0, :, 1:, 0] = radius * torch.cos(t)[:, None] + torch.arange(1, J)
    m[0, :, 1:, 2] = radius * torch.sin(t)[:, None]
    m[0, :, :, 0] += 0.05 * torch.arange(T)[:, None]  # the root's walk is not the body's motion
    return m


def test_body_motion_stats_match_the_metrics():
    motion = torch.randn(5, 40, 6, 3, dtype=torch.float64).cumsum(1) * 0.01
    speed, amplitude = losses.body_motion_stats(motion)  # (5, 5) each: per clip and joint
    assert speed.shape == (5, 5)
    assert np.allclose(speed.mean(1).numpy(), diagnostics.body_speed(motion.numpy()), atol=1e-6)
    assert np.allclose(amplitude.mean(1).numpy(), diagnostics.body_amplitude(motion.numpy()), atol=1e-6)


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
    with pytest.raises(ValueError, match="energy_weight must be a number >= 0"):
        tiny_config(energy_weight=-1.0)
    terms["free_energy"] = torch.tensor(0.5)
    assert losses.total_loss(terms, tiny_config(free_energy_weight=2.0)).item() == 13.0
    assert losses.total_loss(terms, tiny_config(energy_weight=4.0, free_energy_weight=2.0, recon_weight=2.0)).item() == 26.0
    with pytest.raises(ValueError, match="free_energy_weight must be a number >= 0, got -1.0"):
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


# -- the pose loss about the root -------------------------------------------------------------------

def test_pose_loss_body_counts_the_roots_path_once():
    """pose_loss="body": L_mre compares every joint but the root about the root, and the root itself;
    a path off by d costs d^2 in every joint of the world-frame loss, in the root alone here."""
    cfg = tiny_config()  # J = 4, T = 8, the vertical axis weighted x5
    motion = torch.randn(2, cfg.length, cfg.n_joints, 3, generator=torch.Generator().manual_seed(0))
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


# -- the root's height ------------------------------------------------------------------------------

def hopping(T: int = 60, height: float = 0.2, phase: float = 0.0) -> torch.Tensor:
    """A rigid 3-joint body whose root bobs vertically (y) while it walks along x: (1, T, 3, 3)."""
    t = torch.arange(T, dtype=torch.float64) * 2 * math.pi / 20 + phase
    m = torch.zeros(1, T, 3, 3, dtype=torch.float64)
    m[0, :, :, 0] = 0.05 * torch.arange(T)[:, None] + torch.arange(3)
    m[0, :, :, 1] = height * torch.sin(t)[:, None]
    return m


def test_root_height_stats_match_the_metrics():
    motion = torch.randn(5, 40, 4, 3, dtype=torch.float64).cumsum(1) * 0.01
    speed, amplitude = losses.root_height_stats(motion, up_axis=1)
    m_speed, m_amp = diagnostics.root_height_speed_and_amplitude(motion.numpy(), up_axis=1)
    assert np.allclose(speed.numpy(), m_speed, atol=1e-9) and np.allclose(amplitude.numpy(), m_amp, atol=1e-6)
    # a root that keeps its height has neither, whatever it does on the ground plane
    flat = hopping(height=0.0)
    assert diagnostics.root_height_speed_and_amplitude(flat.numpy(), 1)[1][0] == pytest.approx(0.0, abs=1e-12)
    # nor does a steady sink: amplitude is the spread about the height's line over time
    sinking = flat.clone()
    sinking[..., 1] -= 0.01 * torch.arange(flat.shape[1], dtype=torch.float64)[:, None]
    speed, amplitude = diagnostics.root_height_speed_and_amplitude(sinking.numpy(), 1)
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
    with pytest.raises(ValueError, match="height_weight must be a number >= 0"):
        tiny_config(height_weight=-1.0)


def test_energy_on_drawn_measures_the_motion_after_rigid_bones():
    # a still body whose last hand bone only changes length: the decoder's joints move, the rigid
    # readout (each bone at its median length, the same direction) does not
    cfg = tiny_config(n_joints=24, skeleton="humanact12", energy_weight=1.0, free_energy_weight=1.0, bones="rigid")
    gen = torch.Generator().manual_seed(0)
    pose = torch.randn(24, 3, generator=gen, dtype=torch.float64) * 0.3
    still = pose.expand(2, cfg.length, 24, 3).clone()  # (2, T, J, 3)
    stretched = still.clone()
    bone = pose[23] - pose[21]
    scale = 1.0 + 0.5 * torch.sin(torch.arange(cfg.length, dtype=torch.float64))  # (T,)
    stretched[:, :, 23] = pose[21] + scale[:, None] * bone
    out = {"trajectory": still[:, :, 0], "motion": stretched, "free_motion": stretched,
           "mu": torch.zeros(2, 5, dtype=torch.float64), "logvar": torch.full((2, 5), math.log(cfg.sigma2),
                                                                                dtype=torch.float64)}
    # the one pair of one action mixed halfway: its decode stretches the same bone, on its own path
    out.update(mix_motion=stretched[:1], mix_trajectory=still[:1, :, 0] + 1.0, mix_rows=torch.tensor([0]),
               mix_lam=torch.tensor([0.5], dtype=torch.float64))
    labels = torch.tensor([0, 0])
    decoder = losses.odmo_terms(out, still, labels, cfg)
    drawn = losses.odmo_terms(out, still, labels, replace(cfg, energy_on="drawn"))
    assert decoder["energy"].item() > 0.01 and decoder["free_energy"].item() > 0.01
    assert decoder["mix_energy"].item() > 0.01 and drawn["mix_energy"].item() == pytest.approx(0.0, abs=1e-9)
    assert drawn["energy"].item() == pytest.approx(0.0, abs=1e-9)
    assert drawn["free_energy"].item() == pytest.approx(0.0, abs=1e-9)
    # with free bones the readout is the decoder's joints: the same reading either way
    free = losses.odmo_terms(out, still, labels, replace(cfg, energy_on="drawn", bones="free"))
    assert free["energy"].item() == pytest.approx(decoder["energy"].item(), rel=1e-9)
    with pytest.raises(ValueError, match="energy_on must be one of decoder, drawn"):
        tiny_config(energy_on="rigid")
    with pytest.raises(ValueError, match="energy_on drawn needs the skeleton"):
        tiny_config(energy_on="drawn")


def test_ground_error_known_values_and_the_path_sampling_draws():
    T = 12
    t = torch.arange(T, dtype=torch.float64)
    straight = torch.zeros(1, T, 3, dtype=torch.float64)
    straight[..., 0] = 0.01 * t  # 1 cm a frame along x, y up
    assert losses.ground_speed(straight, 1).item() == pytest.approx(0.01, rel=1e-6)
    # a zigzag about the same line: the same displacement, a longer way
    zigzag = straight.clone()
    zigzag[..., 2] = 0.03 * (t % 2)
    smoothed = zigzag[0, :, [0, 2]].unfold(0, 3, 1).mean(-1)  # what the 3-frame average leaves of it
    expect = smoothed.diff(dim=0).norm(dim=-1).mean().item()
    assert losses.ground_speed(zigzag, 1).item() == pytest.approx(expect, rel=1e-6) and expect > 0.0105
    clip = torch.zeros(1, T, 4, 3, dtype=torch.float64)
    clip[:, :, 0] = 2 * straight  # the real clip travels 2 cm a frame
    assert losses.ground_error(straight, clip, 1).item() == pytest.approx(math.log(0.012 / 0.022) ** 2, rel=1e-6)
    assert losses.ground_error(2 * straight, clip, 1).item() == pytest.approx(0.0, abs=1e-9)
    # the height does not count
    lifted = 2 * straight
    lifted[..., 1] = 0.05 * torch.sin(t)
    assert losses.ground_error(lifted, clip, 1).item() == pytest.approx(0.0, abs=1e-9)
    # in the terms: on the trajectory generator's path, weighted into the total
    cfg = tiny_config(ground_weight=2.0, root="ground")
    target = torch.cat([clip.float().expand(2, -1, -1, -1)[:, :cfg.length]], dim=0)  # (2, T, 4, 3)
    out = {"trajectory": straight.float().expand(2, -1, -1)[:, :cfg.length], "motion": target, "free_motion": target,
           "mu": torch.zeros(2, 5), "logvar": torch.full((2, 5), math.log(cfg.sigma2))}
    terms = losses.odmo_terms(out, target, torch.tensor([0, 0]), cfg)
    assert terms["ground"].item() == pytest.approx(math.log(0.012 / 0.022) ** 2, rel=1e-4)
    decoder = losses.odmo_terms(out, target, torch.tensor([0, 0]), replace(cfg, root="decoder"))
    assert decoder["ground"].item() == pytest.approx(0.0, abs=1e-6)  # the decoder's own root is the clip's
    base = {k: torch.tensor(1.0) for k in ("mre", "es", "vae", "r", "cons")}
    assert losses.total_loss({**base, "ground": torch.tensor(0.5)}, cfg).item() == 5.0
    with pytest.raises(ValueError, match="ground_weight must be a number >= 0"):
        tiny_config(ground_weight=-1.0)
