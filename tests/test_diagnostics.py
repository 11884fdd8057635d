"""The measures training's report and the evaluation share (measures/diagnostics.py) on hand-made
inputs whose answers are known in closed form: APD and mode homogeneity, the body's speed and amplitude
and their ratios, the body and retrieval errors and the noise ceiling."""

from __future__ import annotations

import numpy as np
import pytest

from odmo_cli.measures import diagnostics


def _points_as_motions(points: list[list[float]]) -> np.ndarray:
    """Motions (N, 1, 1, 3) whose single joint sits at the given x coordinates."""
    m = np.zeros((len(points), 1, 1, 3))
    m[:, 0, 0, 0] = [p[0] for p in points]
    return m


# ---------------------------------------------------------------------------------------------
# APD and mode homogeneity


def test_apd_uses_the_distance_between_whole_sequences():
    # m1 differs from the zero motion by (3,0,0) at t=0 and (0,4,0) at t=1: distance
    # sqrt(9 + 16) = 5 (per-frame mean would give 3.5, per-frame sum 7).
    m = np.zeros((3, 2, 1, 3))
    m[1, 0, 0] = [3.0, 0.0, 0.0]
    m[1, 1, 0] = [0.0, 4.0, 0.0]
    # Pairs (0,1)=5, (0,2)=0, (1,2)=5.
    assert diagnostics.apd(m) == pytest.approx(10 / 3)
    with pytest.raises(ValueError):
        diagnostics.apd(m[:1])


def test_mode_apd_and_mode_homogeneity_known_values():
    # Category 0: x = 0, 1, 10, 11. APD = (1+10+11+9+10+1)/6 = 7; modes {0,1}, {10,11}
    # have APD 1 each, mode-APD = (2*1 + 2*1)/4 = 1; relative drop 6/7.
    # Category 1: one mode, drop 0.
    # Category 2: x = 0, 2, 4 with modes {0}, {2,4}: APD = 8/3, mode-APD = (0 + 2*2)/3,
    # drop 1/2 (singleton mode counts as APD 0).
    xs = [[0.0], [1.0], [10.0], [11.0], [0.0], [5.0], [0.0], [2.0], [4.0]]
    labels = np.array([0, 0, 0, 0, 1, 1, 2, 2, 2])
    modes = np.array([3, 3, 8, 8, 0, 0, 0, 1, 1])
    m = _points_as_motions(xs)
    assert diagnostics.mode_apd(m[:4], modes[:4]) == pytest.approx(1.0)
    assert diagnostics.mode_apd(m[6:], modes[6:]) == pytest.approx(4 / 3)
    expected = 100.0 * (6 / 7 + 0.0 + 1 / 2) / 3
    assert diagnostics.mode_homogeneity(m, labels, modes) == pytest.approx(expected)


def test_mode_homogeneity_zero_for_a_single_mode_and_rejects_tiny_categories():
    m = _points_as_motions([[0.0], [1.0], [5.0]])
    assert diagnostics.mode_homogeneity(m, np.zeros(3), np.zeros(3)) == 0.0
    with pytest.raises(ValueError):
        diagnostics.mode_homogeneity(m, np.array([0, 0, 1]), np.zeros(3))



# ---------------------------------------------------------------------------------------------
# damping: body speed, amplitude, their ratios and the noise ceiling


def _swing(n: int = 1, T: int = 60, period: float = 20.0, amp: float = 0.3, phase: float = 0.0,
           stretch: float = 1.0) -> np.ndarray:
    """(n, T, 3, 3): a root walking along z, a still joint above it and a joint swinging along x."""
    t = np.arange(T) / stretch
    m = np.zeros((n, T, 3, 3))
    m[:, :, :, 2] += 0.05 * np.arange(T)[None, :, None]  # the root's trajectory carries every joint
    m[:, :, 1, 1] += 0.5
    m[:, :, 2, 0] += amp * np.sin(2 * np.pi * t / period + phase)
    return m


def test_body_speed_and_amplitude_known_values():
    m = np.zeros((1, 11, 3, 3))
    m[0, :, 1, 0] = 0.1 * np.arange(11)  # joint 1 moves 0.1 per frame about the root, joint 2 is still
    m[0, :, :, 2] += 3.0 * np.arange(11)[:, None]  # the root's own motion does not count
    assert diagnostics.body_speed(m, smooth=1)[0] == pytest.approx(0.05)
    assert diagnostics.body_speed(m, smooth=3)[0] == pytest.approx(0.05)  # a moving average keeps a straight line
    sq = np.zeros((1, 10, 2, 3))
    sq[0, ::2, 1, 0] = 2.0  # x alternates 2, 0, 2, 0: mean 1, deviation 1 at every frame
    assert diagnostics.body_amplitude(sq, smooth=1)[0] == pytest.approx(1.0)
    assert diagnostics.body_speed(sq, smooth=1)[0] == pytest.approx(2.0)
    assert diagnostics.body_speed(sq, smooth=2)[0] == pytest.approx(0.0)  # jitter averages away


def test_per_motion_statistics_do_not_depend_on_the_block_size():
    """The statistics run block by block (diagnostics.BLOCK motions) in float64: each motion's figure is
    exactly what the whole set at once in float64, with numpy's own norm, gives."""
    rng = np.random.default_rng(3)
    m = rng.normal(size=(2 * diagnostics.BLOCK + 5, 12, 4, 3)).cumsum(1).astype(np.float32)  # spans 3 blocks
    body = m.astype(np.float64)[:, :, 1:] - m.astype(np.float64)[:, :, :1]
    body = (body[:, :-2] + body[:, 1:-1] + body[:, 2:]) / 3  # the 3-frame moving average
    speed = np.linalg.norm(np.diff(body, axis=1), axis=-1).mean(axis=(1, 2))
    dev = body - body.mean(axis=1, keepdims=True)
    amplitude = np.sqrt((dev ** 2).sum(-1).mean(axis=1)).mean(axis=1)
    got_speed, got_amplitude = diagnostics.body_speed_and_amplitude(m)
    assert got_speed.shape == (len(m),) and np.array_equal(got_speed, speed)
    assert np.array_equal(got_amplitude, amplitude)
    assert diagnostics.body_speed_and_amplitude(m[:0])[0].shape == (0,)


def test_body_error_counts_the_pose_not_the_place():
    rng = np.random.default_rng(0)
    real = rng.normal(size=(3, 5, 4, 3))
    moved = real + rng.normal(size=(3, 5, 1, 3))  # every frame's whole body shifted: the same poses
    assert diagnostics.body_error(moved, real) == pytest.approx(0.0, abs=1e-12)
    bent = real.copy()
    bent[:, :, 1:] += np.array([0.0, 0.3, 0.4])  # every non-root joint 0.5 off, about the root
    assert diagnostics.body_error(bent, real) == pytest.approx(0.5 * 3 / 4)
    with pytest.raises(ValueError, match="differ in shape"):
        diagnostics.body_error(real[:2], real)


def test_retrieval_errors_take_the_nearest_code_and_the_best_clip_of_the_same_action():
    def clip(x, root=0.0):  # (1, 2, 3): a root and one joint x to its side; body error |dx| / 2
        return [[[root, 0.0, 0.0], [root + x, 0.0, 0.0]]]

    bank = np.array([clip(0.0), clip(1.0), clip(3.0), clip(5.0)])
    bank_labels, bank_codes = [0, 0, 0, 1], [[0.0], [10.0], [20.0], [0.0]]
    # action 0: its nearest code is the x = 0 clip (error 1.25), its best clip x = 3 (0.25); action 1:
    # one clip (0.5 both ways), the motion's place does not count; action 2: no bank clip, left out
    motions = np.array([clip(2.5), clip(4.0, root=7.0), clip(9.0)])
    got = diagnostics.retrieval_errors(motions, [0, 1, 2], [[0.1], [7.0], [0.0]], bank, bank_labels, bank_codes)
    assert got["nearest_code"] == pytest.approx((1.25 + 0.5) / 2)
    assert got["best_clip"] == pytest.approx((0.25 + 0.5) / 2)
    none = diagnostics.retrieval_errors(motions[2:], [2], [[0.0]], bank, bank_labels, bank_codes)
    assert np.isnan(none["nearest_code"]) and np.isnan(none["best_clip"])


def test_mean_pose_error_is_the_spread_about_each_actions_mean_body():
    m = np.zeros((3, 1, 2, 3))  # root at 0, one joint
    m[0, 0, 1] = [1, 0, 0]
    m[1, 0, 1] = [-1, 0, 0]  # action 0: mean body puts the joint at 0, 1 from each
    m[2, 0, 1] = [0, 2, 0]  # action 1, alone: its own mean
    m += np.array([5.0, 0, 0])  # where the motions are does not count
    assert diagnostics.mean_pose_error(m, [0, 0, 1]) == pytest.approx((0.5 + 0.5 + 0.0) / 3)
    assert diagnostics.mean_pose_error(m, [0, 1, 2]) == 0.0


def test_damping_ratios_see_slowed_and_shrunk_motion():
    real = _swing(2)
    labels = np.array([0, 1])
    same = diagnostics.damping_ratios(real, labels, real, labels)
    assert same["speed"] == pytest.approx(1.0) and same["amplitude"] == pytest.approx(1.0)
    shrunk = diagnostics.damping_ratios(_swing(2, amp=0.15), labels, real, labels)
    assert shrunk["speed"] == pytest.approx(0.5, rel=1e-6) and shrunk["amplitude"] == pytest.approx(0.5, rel=1e-6)
    # the same swing played at half speed over whole periods (a 3-frame average barely touches either)
    slowed = diagnostics.damping_ratios(_swing(2, T=120, stretch=2.0), labels, _swing(2, T=120), labels)
    assert slowed["speed"] == pytest.approx(0.5, abs=0.03)  # half the speed at the same swing
    assert slowed["amplitude"] == pytest.approx(1.0, abs=0.03)
    mixed = diagnostics.damping_ratios(np.concatenate([_swing(1), _swing(1, amp=0.15)]), labels, real, labels)
    assert mixed["speed_by_class"] == pytest.approx({0: 1.0, 1: 0.5})
    assert mixed["speed"] == pytest.approx(0.75)


def test_class_ratios_nan_where_nothing_to_compare():
    r = diagnostics.class_ratios([1.0, 2.0, 3.0], [0, 1, 2], [2.0, 0.0], [0, 1])
    assert r[0] == pytest.approx(0.5)
    assert np.isnan(r[1]) and np.isnan(r[2])  # real mean 0; no real motions at all
    assert diagnostics.mean_finite(r.values()) == pytest.approx(0.5)
    assert np.isnan(diagnostics.mean_finite([float("nan")]))


def test_noise_ceiling_from_exact_codes_to_class_average():
    # two clips of one class swinging in antiphase: their average does not move at all
    m = np.concatenate([_swing(1), _swing(1, phase=np.pi)])
    labels = np.array([0, 0])
    codes = np.array([[0.0, 0.0], [1.0, 0.0]])
    rng = np.random.default_rng(0)
    sharp = diagnostics.noise_ceiling(codes, np.full((2, 2), 1e-3), m, labels, rng)
    assert sharp["speed"] == pytest.approx(1.0, abs=1e-6)  # the code names its clip: nothing is averaged
    assert sharp["body"] == pytest.approx(0.0, abs=1e-6)
    blurred = diagnostics.noise_ceiling(codes, np.full((2, 2), 1e3), m, labels, rng)
    assert blurred["speed"] < 0.01 and blurred["amplitude"] < 0.01
    # every clip drawn as the class average: the body error of the action-mean body
    assert blurred["body"] == pytest.approx(diagnostics.mean_pose_error(m, labels), rel=1e-3)
    assert blurred["body"] > 0.05  # antiphase swings: their average stands still
    # clips of other classes never mix in, however close their codes
    other = diagnostics.noise_ceiling(codes, np.full((2, 2), 1e3), m, np.array([0, 1]), rng)
    assert other["speed"] == pytest.approx(1.0, abs=1e-6)
