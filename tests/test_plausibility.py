"""The network-free plausibility measures on motions with known answers: planted and sliding feet, a
root at constant height against a bouncing one, bones that keep or change their length, kinetic
features of a joint at constant velocity, and coverage of sets that repeat or span the real one."""

from __future__ import annotations

import numpy as np
import pytest

from odmo_cli.evaluation import metrics
from odmo_cli.measures import plausibility as P
from odmo_cli.geometry.skeletons import get_skeleton

FPS = 20.0
# a 3-joint chain, y up: root, knee, foot; the foot is the one foot joint; leg 1 unit
FRAME = P.Frame(up=1, up_sign=1.0, feet=(2,), fps=FPS, leg=1.0)
PARENTS = (-1, 0, 1)


def chain(T: int = 40) -> np.ndarray:
    """(1, T, 3, 3): root at height 1, knee at 0.5, foot on the floor, nothing moving."""
    m = np.zeros((1, T, 3, 3))
    m[:, :, 0, 1], m[:, :, 1, 1] = 1.0, 0.5
    return m


def test_a_planted_foot_is_in_contact_and_does_not_skate():
    contact, steps, skate = P.foot_contacts(chain(), FRAME)
    assert contact.tolist() == [40] and steps.tolist() == [39] and skate.tolist() == [0]


@pytest.mark.parametrize("speed, skates", [(0.5 * P.SLIDE_SPEED, 0), (2.0 * P.SLIDE_SPEED, 39)])
def test_a_foot_sliding_on_the_floor_skates_only_above_the_threshold(speed, skates):
    m = chain()
    m[0, :, 2, 0] = np.arange(40) * speed / FPS  # leg lengths per second along x, on the floor
    contact, steps, skate = P.foot_contacts(m, FRAME)
    assert contact.tolist() == [40] and skate.tolist() == [skates]
    assert P.share(skate, steps) == skates / 39


def test_a_lifted_foot_is_not_in_contact_and_cannot_skate():
    m = chain()
    m[0, 10:30, 2, 1] = 0.3  # lifted well above CONTACT_HEIGHT for 20 frames, moving fast meanwhile
    m[0, 10:30, 2, 0] = np.arange(20) * 0.2
    contact, steps, skate = P.foot_contacts(m, FRAME)
    assert contact.tolist() == [20] and skate.tolist() == [0]
    # 9 steps before the lift, 9 after
    assert steps.tolist() == [18]


def test_share_pools_and_is_nan_without_a_whole():
    assert P.share([1, 2], [4, 4]) == pytest.approx(3 / 8)
    assert np.isnan(P.share([0], [0]))


def test_root_speeds_see_a_bounce_and_a_walk():
    T = 83  # 80 steps after the 3-frame average: whole periods of 1 Hz at 20 fps
    still, bounce = chain(T), chain(T)
    t = np.arange(T) / FPS
    amp, freq = 0.05, 1.0  # 5 cm at 1 Hz
    bounce[0, :, :, 1] += amp * np.sin(2 * np.pi * freq * t)[:, None]
    walk = chain(T)
    walk[0, :, :, 0] += 1.3 * t[:, None]  # 1.3 units a second along x
    up, ground = P.root_speeds(np.concatenate([still, bounce, walk]), FRAME)
    assert up[0] == 0 and ground[0] == 0
    # RMS of d/dt (A sin wt) is A w / sqrt(2), times the 3-frame average's gain (1 + 2 cos(w/fps)) / 3
    # and the frame difference's sin(w / 2fps) / (w / 2fps)
    w = 2 * np.pi * freq
    gain = (1 + 2 * np.cos(w / FPS)) / 3 * np.sin(w / (2 * FPS)) / (w / (2 * FPS))
    assert up[1] == pytest.approx(amp * w / np.sqrt(2) * gain, rel=1e-3)
    assert ground[2] == pytest.approx(1.3) and up[2] == pytest.approx(0, abs=1e-12)


def test_kinetic_features_of_a_joint_at_constant_velocity():
    m = chain(30)
    m[0, :, 1, 0] += 2.0 * np.arange(30) / FPS  # the knee moves at 2 units/s along x
    f = P.kinetic_features(m, FRAME)[0]
    J = 3
    ke_h, ke_v, spend = f[:J], f[J:2 * J], f[2 * J:3 * J]
    assert ke_h.tolist() == pytest.approx([0, 0.5 * 2.0 ** 2, 0])
    assert ke_v.tolist() == pytest.approx([0, 0, 0]) and spend.tolist() == pytest.approx([0, 0, 0], abs=1e-9)
    assert f.shape == (9 * J,)


def walking_chain(T: int = 40) -> np.ndarray:
    """chain(T) whose root bounces and travels while the foot slides, then plants, then slides again."""
    m = chain(T)
    t = np.arange(T) / FPS
    m[0, :, :2, 1] += 0.05 * np.sin(2 * np.pi * t)[:, None]
    m[0, :, :2, 0] += 1.3 * t[:, None]
    m[0, :, 2, 0] = np.where(np.arange(T) % 12 < 6, 1.3 * t, 1.3 * (t // 0.6) * 0.6)
    return m


def test_padded_frames_are_left_out_as_if_the_motion_ended_there():
    # a real crop of a 25-frame clip padded to 40 with copies of its last frame (data.dataset.crop_pad_shift)
    clip = walking_chain(40)[:, :25]
    padded = np.concatenate([clip, np.repeat(clip[:, -1:], 15, axis=1)], axis=1)
    mine, alone = P.measure(padded, FRAME, PARENTS, lengths=[25]), P.measure(clip, FRAME, PARENTS)
    for key in ("contact", "steps", "skate", "slots"):
        assert mine[key].tolist() == alone[key].tolist(), key
    for key in ("root_up", "root_ground", "kinetic"):
        np.testing.assert_allclose(mine[key], alone[key], rtol=1e-12, err_msg=key)
    # without lengths the copies count: a still body with a planted foot
    whole = P.measure(padded, FRAME, PARENTS)
    assert whole["contact"][0] > alone["contact"][0] and whole["root_up"][0] < alone["root_up"][0]
    assert mine["skate"][0] > 0 and mine["root_up"][0] > 0  # the clip itself moves


def test_a_crop_too_short_for_a_step_is_left_out_of_the_root_and_kinetic_measures():
    m = np.concatenate([walking_chain(40), walking_chain(40)])
    s = P.measure(m, FRAME, PARENTS, lengths=[40, 3])  # 3 frames: one smoothed frame, no step
    assert np.isnan(s["root_up"][1]) and np.isnan(s["kinetic"][1]).all() and np.isfinite(s["kinetic"][0]).all()
    full = P.measure(m[:1], FRAME, PARENTS)
    out = P.compare(s, [0, 0], full, [0], P.standardizer(full["kinetic"]))
    assert out["root_up"] == pytest.approx(1) and out["root_ground"] == pytest.approx(1)


def test_bone_variation_is_zero_for_a_rigid_body_and_the_stretch_otherwise():
    m = np.concatenate([chain(), chain()])
    m[1, :, 2, 1] = np.linspace(0, -0.1, 40)  # the shin grows from 0.5 to 0.6
    assert P.bone_variation(m, PARENTS).tolist() == pytest.approx([0.0, 0.1])


def test_leg_length_of_the_chain():
    assert P.leg_length(chain(), 0, 1, 2) == pytest.approx(1.0)


def test_frechet_known_answers():
    rng = np.random.default_rng(0)
    x = rng.standard_normal((4000, 3))
    assert P.frechet(x, x) == pytest.approx(0, abs=1e-9)
    assert P.frechet(x, x + [2.0, 0, 0]) == pytest.approx(4.0, rel=1e-6)
    y = rng.standard_normal((500, 3)) * 2 + 1
    assert P.frechet(x, y) == pytest.approx(metrics.fid_from_features(x, y), rel=1e-6)
    # fewer samples than features: singular covariances still give a finite number
    assert np.isfinite(P.frechet(rng.standard_normal((5, 20)), rng.standard_normal((5, 20))))


def test_coverage_and_density_known_answers():
    rng = np.random.default_rng(1)
    real = rng.standard_normal((300, 4))
    cov, den = P.coverage_density(real, real)
    # every real point is its own generated twin; each ball holds itself and, strictly inside its radius,
    # k - 1 neighbours (the k-th lies on it)
    assert cov == 1.0 and den == pytest.approx(1.0)
    cov, den = P.coverage_density(real, np.repeat(real[:1], 300, axis=0))  # one real clip, repeated
    assert cov <= 0.05  # its own ball and those of a few neighbours: near (k + 1) / 300
    cov, den = P.coverage_density(real, rng.standard_normal((300, 4)))  # another draw of the same law
    assert cov > 0.85 and 0.7 < den < 1.3
    cov, _ = P.coverage_density(real, rng.standard_normal((300, 4)) + 10)  # somewhere else
    assert cov == 0.0


def test_coverage_counts_repeated_real_crops_once():
    # clips no longer than the crop give the same crop every draw: six copies of one point would be each
    # other's nearest neighbours, a radius of 0 that no generated motion, not even the crop itself, enters
    rng = np.random.default_rng(3)
    distinct = rng.standard_normal((40, 4))
    real = np.concatenate([distinct, np.repeat(distinct[:1], 6, axis=0)])
    cov, den = P.coverage_density(real, distinct)
    assert cov == 1.0 and den == pytest.approx(1.0)  # as for the 40 distinct points alone
    assert P.coverage_density(real, distinct) == P.coverage_density(distinct, distinct)
    cov, _ = P.coverage_density(real, distinct[:1])  # the repeated crop itself, once: its ball and a few
    assert 1 / 40 <= cov <= 0.15


def test_compare_a_real_set_with_itself():
    rng = np.random.default_rng(2)
    m = np.concatenate([chain(40) for _ in range(24)])
    m[:, :, :, 1] += 0.05 * rng.standard_normal((24, 1, 1)) * np.sin(np.arange(40) / 3)[None, :, None]
    m[:, :, :, 0] += rng.uniform(0.5, 1.5, (24, 1, 1)) * np.arange(40)[None, :, None] / FPS
    labels = np.repeat([0, 1], 12)
    s = P.measure(m, FRAME, PARENTS)
    out = P.compare(s, labels, s, labels, P.standardizer(s["kinetic"]))
    assert out["root_up"] == pytest.approx(1) and out["root_ground"] == pytest.approx(1)
    assert out["coverage"] == 1.0 and out["kinetic_fd"] == pytest.approx(0, abs=1e-6)
    assert out["bone_var"] == pytest.approx(0, abs=1e-9)
    assert {"root_up/0", "root_up/1", "coverage/0", "coverage/1", "foot_skate/0"} <= set(out)


def test_every_shipped_skeleton_names_its_feet():
    for name, feet in (("humanact12", (7, 10, 8, 11)), ("cmu20", (14, 15, 18, 19))):
        sk = get_skeleton(name)
        assert sk.feet == feet
        assert all("ankle" in sk.joint_names[leg[2]] and "hip" in sk.joint_names[leg[0]] for leg in sk.legs)


# -- L_foot: the training term on the same contact --------------------------------------------------------

def test_l_foot_is_zero_for_planted_feet_and_the_squared_slide_otherwise():
    import torch

    from odmo_cli.models.losses import contact_labels, foot_contact_error

    sk = get_skeleton("humanact12")
    rng = np.random.default_rng(3)
    real = torch.from_numpy(rng.normal(0, 0.01, (2, 20, 24, 3)))  # jittering in place; up is -y
    real[:, :, 0, 1], real[:, :, 4, 1], real[:, :, 7, 1] = -1.0, -0.5, 0.0  # hip (root) 1, knee 0.5, ankle 0 high
    real[:, :, 1] = real[:, :, 0]  # the left hip on the root: leg length 1
    real[:, :, [10, 8, 11], 1] = 0.0
    planted, leg = contact_labels(real, list(sk.feet), sk.legs[0][:3], 1, -1.0)
    # the same contact as the evaluation's (plausibility.foot_contacts) on the same clips
    frame = P.Frame(1, -1.0, sk.feet, 20.0, 1.0)
    assert planted.sum(dim=(1, 2)).tolist() == P.foot_contacts(real.numpy(), frame)[1].tolist()
    assert torch.allclose(leg, torch.ones(2, dtype=leg.dtype), atol=0.05)
    still = real.clone()
    still[:, :, list(sk.feet)] = real[:, :1, list(sk.feet)]  # feet that do not move at all
    assert torch.allclose(foot_contact_error(still, real, list(sk.feet), sk.legs[0][:3], 1, -1.0),
                          torch.zeros(2, dtype=real.dtype))
    slide = still.clone()
    slide[:, :, list(sk.feet), 0] += 0.1 * torch.arange(20, dtype=real.dtype)[None, :, None]  # 0.1 a frame along x
    expected = planted.sum(dim=(1, 2)).to(real.dtype) * (0.1 / leg) ** 2 / 19
    assert torch.allclose(foot_contact_error(slide, real, list(sk.feet), sk.legs[0][:3], 1, -1.0), expected)


def test_cons_ground_leaves_the_decoders_root_height_free():
    import torch

    from odmo_cli.models.losses import odmo_terms
    from odmo_cli.models.odmo import ODMOConfig

    motion = torch.zeros(4, 6, 24, 3)
    out = {"mu": torch.zeros(4, 2), "logvar": torch.zeros(4, 2), "trajectory": torch.zeros(4, 6, 3),
           "motion": motion.clone()}
    out["motion"][:, :, 0, 1] = 0.3  # the decoder's root 0.3 above the trajectory, on its path
    labels = torch.tensor([0, 1, 0, 1])
    assert float(odmo_terms(out, motion, labels, ODMOConfig(cons="all"))["cons"]) > 0
    assert float(odmo_terms(out, motion, labels, ODMOConfig(cons="ground"))["cons"]) == 0


def test_l_foot_on_all_axes_also_holds_a_planted_foots_height():
    import torch

    from odmo_cli.models.losses import foot_contact_error

    sk = get_skeleton("cmu20")  # up is +y
    real = torch.zeros(1, 10, 20, 3)
    real[:, :, 0, 1], real[:, :, 12, 1], real[:, :, 13, 1] = 1.0, 1.0, 0.5  # root and hip at 1, knee 0.5: leg 1
    bob = real.clone()
    bob[:, :, list(sk.feet), 1] += 0.01 * (torch.arange(10) % 2)[None, :, None]  # planted feet bobbing 1 cm
    args = (real, list(sk.feet), sk.legs[0][:3], 1, 1.0)
    assert float(foot_contact_error(bob, *args)) == 0.0
    assert float(foot_contact_error(bob, *args, vertical=True)) == pytest.approx(4 * 9 * 0.01 ** 2 / 9, rel=1e-4)
