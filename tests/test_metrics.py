"""The papers' metrics (evaluation/metrics.py) on hand-made inputs whose answers are known in closed form."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import linalg
from scipy.stats import special_ortho_group

from odmo_cli.evaluation import metrics
from odmo_cli.measures.diagnostics import BLOCK


def _simplex(n_points: int, edge: float, dim: int | None = None, offset: float = 0.0) -> np.ndarray:
    """n_points features (n_points, dim) whose distinct pairs are all exactly `edge` apart."""
    dim = n_points if dim is None else dim
    x = np.zeros((n_points, dim))
    x[np.arange(n_points), np.arange(n_points)] = edge / math.sqrt(2.0)
    return x + offset


# ---------------------------------------------------------------------------------------------
# accuracy


def test_accuracy_from_logits_and_from_labels():
    logits = np.array([[2.0, 1.0], [0.0, 3.0], [5.0, -1.0]])  # argmax 0, 1, 0
    labels = np.array([0, 1, 1])
    assert metrics.accuracy(logits, labels) == pytest.approx(2 / 3)
    assert metrics.accuracy(np.array([0, 1, 0]), labels) == pytest.approx(2 / 3)
    assert metrics.accuracy(np.array([0, 1, 1]), labels) == 1.0
    assert metrics.accuracy(np.array([1, 0, 0]), labels) == 0.0


def test_accuracy_per_class_known_values():
    logits = np.array([[2.0, 1.0, 0.0], [0.0, 3.0, 0.0], [5.0, -1.0, 0.0], [0.0, 0.0, 1.0]])  # argmax 0, 1, 0, 2
    labels = np.array([0, 1, 1, 1])
    per = metrics.accuracy_per_class(logits, labels, 4)
    np.testing.assert_allclose(per[:3], [1.0, 1 / 3, np.nan])  # class 2 was predicted but never true
    assert np.isnan(per[3]) and per.shape == (4,)
    # the mean over samples weights classes by their counts
    assert metrics.accuracy(logits, labels) == pytest.approx((1 * 1 + 3 * (1 / 3)) / 4)


def test_accuracy_rejects_mismatched_lengths():
    with pytest.raises(ValueError):
        metrics.accuracy(np.array([0, 1]), np.array([0, 1, 1]))


# ---------------------------------------------------------------------------------------------
# feature statistics and FID


def test_feature_stats_known_values():
    f = np.array([[0.0, 0.0], [2.0, 0.0], [0.0, 2.0], [2.0, 2.0]])
    mu, sigma = metrics.feature_stats(f)
    np.testing.assert_allclose(mu, [1.0, 1.0])
    # Unbiased: sum of squared deviations 4 over N - 1 = 3.
    np.testing.assert_allclose(sigma, [[4 / 3, 0.0], [0.0, 4 / 3]])
    mu1, sigma1 = metrics.feature_stats(np.array([[1.0], [3.0]]))
    assert sigma1.shape == (1, 1) and sigma1[0, 0] == pytest.approx(2.0)


def test_fid_of_a_set_with_itself_is_zero():
    f = np.random.default_rng(0).normal(size=(300, 5))
    assert metrics.fid_from_features(f, f) == pytest.approx(0.0, abs=1e-8)


MU1, VAR1 = np.array([0.0, 1.0, 2.0]), np.array([1.0, 4.0, 9.0])
MU2, VAR2 = np.array([1.0, 1.0, 0.0]), np.array([4.0, 1.0, 1.0])
# ||mu1 - mu2||^2 = 1 + 0 + 4; sum (sqrt(v1) - sqrt(v2))^2 = 1 + 1 + 4.
FID_CLOSED_FORM = float(np.sum((MU1 - MU2) ** 2) + np.sum((np.sqrt(VAR1) - np.sqrt(VAR2)) ** 2))


def test_fid_closed_form_for_diagonal_gaussians():
    assert FID_CLOSED_FORM == 11.0
    got = metrics.fid(MU1, np.diag(VAR1), MU2, np.diag(VAR2))
    assert got == pytest.approx(FID_CLOSED_FORM, abs=1e-9)


def test_fid_is_invariant_to_a_common_rotation():
    # Rotating both Gaussians the same way makes sigma1 sigma2 non-diagonal but keeps FID.
    q = special_ortho_group.rvs(3, random_state=1)
    got = metrics.fid(q @ MU1, q @ np.diag(VAR1) @ q.T, q @ MU2, q @ np.diag(VAR2) @ q.T)
    assert got == pytest.approx(FID_CLOSED_FORM, abs=1e-8)


def test_fid_from_large_samples_approaches_closed_form():
    rng = np.random.default_rng(2)
    f1 = MU1 + rng.normal(size=(100_000, 3)) * np.sqrt(VAR1)
    f2 = MU2 + rng.normal(size=(100_000, 3)) * np.sqrt(VAR2)
    assert metrics.fid_from_features(f1, f2) == pytest.approx(FID_CLOSED_FORM, rel=0.01)


@pytest.mark.filterwarnings("ignore::scipy.linalg.LinAlgWarning")
def test_fid_with_singular_covariances_is_finite():
    # sigma1 sigma2 = 0, so the root term vanishes: FID = ||mu diff||^2 + 1 + 1.
    got = metrics.fid([0.0, 0.0], np.diag([1.0, 0.0]), [3.0, 0.0], np.diag([0.0, 1.0]))
    assert got == pytest.approx(9.0 + 2.0, abs=1e-6)
    # Fewer samples than dimensions: rank-deficient sample covariance.
    rng = np.random.default_rng(3)
    got = metrics.fid_from_features(rng.normal(size=(5, 10)), rng.normal(size=(200, 10)))
    assert np.isfinite(got) and got > 0.0


def test_fid_of_a_tiny_set_is_quiet_and_zero_against_itself(recwarn):
    # 2 samples in 30 dimensions (a small evaluation set): the covariances have rank 1, and scipy's
    # "singular matrix" warning must not reach a command's output.
    few = np.random.default_rng(0).normal(size=(2, 30))
    assert metrics.fid_from_features(few, few) == pytest.approx(0.0, abs=1e-6)
    assert np.isfinite(metrics.fid_from_features(few, np.random.default_rng(5).normal(size=(50, 30))))
    assert not [w for w in recwarn if issubclass(w.category, linalg.LinAlgWarning)]


def test_fid_retries_with_offset_when_sqrtm_is_not_finite(monkeypatch):
    real_sqrtm = linalg.sqrtm
    calls = []

    def flaky_sqrtm(a):
        calls.append(a)
        return np.full_like(a, np.inf) if len(calls) == 1 else real_sqrtm(a)

    monkeypatch.setattr(metrics.linalg, "sqrtm", flaky_sqrtm)
    got = metrics.fid(MU1, np.diag(VAR1), MU2, np.diag(VAR2), eps=1e-6)
    assert len(calls) == 2
    # The retry shifts both covariances by eps on the diagonal.
    np.testing.assert_allclose(calls[1], np.diag((VAR1 + 1e-6) * (VAR2 + 1e-6)))
    assert got == pytest.approx(FID_CLOSED_FORM, abs=1e-4)


def test_fid_tiny_imaginary_part_dropped_large_one_raises(monkeypatch):
    real_sqrtm = linalg.sqrtm
    monkeypatch.setattr(metrics.linalg, "sqrtm", lambda a: real_sqrtm(a) + 1e-9j)
    assert metrics.fid(MU1, np.diag(VAR1), MU2, np.diag(VAR2)) == pytest.approx(FID_CLOSED_FORM)
    monkeypatch.setattr(metrics.linalg, "sqrtm", lambda a: real_sqrtm(a) + 0.1j * np.eye(3))
    with pytest.raises(ValueError, match="imaginary"):
        metrics.fid(MU1, np.diag(VAR1), MU2, np.diag(VAR2))


def test_fid_never_reports_rounding_noise_as_negative():
    sigma = np.diag([1e-3, 2.0, 7.0])
    assert metrics.fid(MU1, sigma, MU1, sigma) == pytest.approx(0.0, abs=1e-12)
    assert metrics.fid(MU1, sigma, MU1, sigma) >= 0.0


# ---------------------------------------------------------------------------------------------
# diversity and multimodality


def test_diversity_exact_on_a_simplex():
    # All distinct pairs are 3 apart, so the answer is 3 * (fraction of draws with a != b),
    # with the draws replayed from an identically seeded generator.
    feats = _simplex(4, edge=3.0)
    got = metrics.diversity(feats, n_pairs=200, rng=np.random.default_rng(7))
    replay = np.random.default_rng(7)
    first, second = replay.integers(0, 4, 200), replay.integers(0, 4, 200)
    assert got == pytest.approx(3.0 * np.mean(first != second), abs=1e-12)
    assert 0 < np.sum(first == second) < 200  # the construction exercises both cases


def test_diversity_statistics_and_degenerate_sets():
    feats = _simplex(4, edge=3.0)
    big = metrics.diversity(feats, n_pairs=40_000, rng=np.random.default_rng(8))
    assert big == pytest.approx(3.0 * 3 / 4, rel=0.02)  # P(a != b) = 3/4
    assert metrics.diversity(np.ones((10, 3)), rng=np.random.default_rng(0)) == 0.0
    with pytest.raises(ValueError):
        metrics.diversity(np.ones((1, 3)), rng=np.random.default_rng(0))


def test_diversity_is_reproducible_with_the_same_seed():
    feats = np.random.default_rng(0).normal(size=(50, 8))
    a = metrics.diversity(feats, rng=np.random.default_rng(11))
    b = metrics.diversity(feats, rng=np.random.default_rng(11))
    c = metrics.diversity(feats, rng=np.random.default_rng(12))
    assert a == b and a != c


def test_multimodality_exact_per_action_simplices():
    # Action 0: 3 points 2 apart; action 1: 2 points 5 apart, far from action 0 (cross-action
    # distances must not leak in); action 2: one sample, skipped. Rows are interleaved.
    a0 = _simplex(3, edge=2.0, dim=6)
    a1 = np.zeros((2, 6))
    a1[0, 3], a1[1, 4] = 5.0 / math.sqrt(2.0), 5.0 / math.sqrt(2.0)
    a1 += 100.0
    a2 = np.full((1, 6), -50.0)
    feats = np.stack([a0[0], a1[0], a0[1], a2[0], a1[1], a0[2]])
    labels = np.array([0, 1, 0, 2, 1, 0])

    got = metrics.multimodality(feats, labels, n_pairs=20, rng=np.random.default_rng(5))
    replay = np.random.default_rng(5)
    f0, s0 = replay.integers(0, 3, 20), replay.integers(0, 3, 20)
    f1, s1 = replay.integers(0, 2, 20), replay.integers(0, 2, 20)
    expected = (2.0 * np.mean(f0 != s0) + 5.0 * np.mean(f1 != s1)) / 2
    assert got == pytest.approx(expected, abs=1e-12)


def test_multimodality_needs_an_action_with_two_samples():
    with pytest.raises(ValueError):
        metrics.multimodality(np.eye(3), np.array([0, 1, 2]), rng=np.random.default_rng(0))


# ---------------------------------------------------------------------------------------------
# n-APD


def _points_as_motions(points: list[list[float]]) -> np.ndarray:
    """Motions (N, 1, 1, 3) whose single joint sits at the given x coordinates."""
    m = np.zeros((len(points), 1, 1, 3))
    m[:, 0, 0, 0] = [p[0] for p in points]
    return m


def test_n_apd_averages_per_category_ratios():
    real = _points_as_motions([[0.0], [1.0], [3.0], [0.0], [4.0]])
    real_labels = np.array([0, 0, 0, 1, 1])
    # Category 0 generated twice as spread out (ratio 2), category 1 the same (ratio 1).
    gen = _points_as_motions([[0.0], [2.0], [6.0], [10.0], [14.0]])
    gen_labels = np.array([0, 0, 0, 1, 1])
    assert metrics.n_apd(gen, gen_labels, real, real_labels) == pytest.approx(1.5)
    with pytest.raises(ValueError):
        metrics.n_apd(gen, np.array([0, 0, 0, 2, 2]), real, real_labels)


# ---------------------------------------------------------------------------------------------
# dist_e and bone-length consistency


def test_dist_e_known_values():
    asked = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    reached = np.array([[3.0, 4.0, 0.0], [1.0, 1.0, 1.0]])
    assert metrics.dist_e(asked, reached) == pytest.approx(12.5)  # (25 + 0) / 2
    assert metrics.dist_e([[0.0, 0.0], [2.0, 0.0]], [[1.0, 1.0], [2.0, 3.0]]) == pytest.approx(5.5)
    with pytest.raises(ValueError):
        metrics.dist_e(np.zeros((2, 3)), np.zeros((2, 2)))


def test_bone_length_consistency_zero_for_rigid_motion():
    rng = np.random.default_rng(4)
    rest = rng.normal(size=(4, 3))  # (J, 3)
    rotations = special_ortho_group.rvs(3, size=6, random_state=5)  # (T, 3, 3)
    moves = rng.normal(size=(6, 1, 3)) * 10
    motion = np.einsum("tij,kj->tki", rotations, rest) + moves  # (T, J, 3)
    value = metrics.bone_length_consistency(motion[None], parents=[-1, 0, 1, 1])
    assert value == pytest.approx(0.0, abs=1e-12)


def test_bone_length_consistency_linear_stretch():
    # Bone 0->1 grows as 1 + 0.5 t for t = 0..4: std = 0.5 * sqrt((T^2 - 1) / 12) = 0.5 * sqrt(2).
    # Bone 0->2 is rigid, so the mean over the two bones is half of that.
    t = np.arange(5)
    motion = np.zeros((1, 5, 3, 3))
    motion[0, :, 1, 0] = 1.0 + 0.5 * t
    motion[0, :, 2, 1] = 2.0
    expected = 0.5 * math.sqrt(2.0) / 2
    assert metrics.bone_length_consistency(motion, parents=[-1, 0, 0]) == pytest.approx(expected)
    # A second, rigid motion halves it again (mean over motions).
    both = np.concatenate([motion, np.zeros_like(motion) + [1.0, 0.0, 0.0]])
    assert metrics.bone_length_consistency(both, [-1, 0, 0]) == pytest.approx(expected / 2)


def test_bone_length_consistency_does_not_depend_on_the_block_size():
    """Block by block (diagnostics.BLOCK motions) in float64: exactly what the whole set at once in
    float64, with numpy's own norm, gives."""
    rng = np.random.default_rng(3)
    m = rng.normal(size=(2 * BLOCK + 5, 12, 4, 3)).cumsum(1).astype(np.float32)  # spans 3 blocks
    m64 = m.astype(np.float64)
    lengths = np.linalg.norm(m64[:, :, 1:] - m64[:, :, [0, 1, 1]], axis=-1)  # (N, T, 3)
    assert metrics.bone_length_consistency(m, [-1, 0, 1, 1]) == float(lengths.std(axis=1).mean())


# ---------------------------------------------------------------------------------------------
# inception score, confidence interval


def test_inception_score_extremes_and_a_worked_example():
    one_hot = np.eye(4)[np.repeat(np.arange(4), 5)]  # confident, 5 samples per class
    assert metrics.inception_score(one_hot) == pytest.approx(4.0)
    same = np.tile([0.1, 0.2, 0.3, 0.4], (10, 1))
    assert metrics.inception_score(same) == pytest.approx(1.0)
    # p(y) = [0.75, 0.25]; KL terms by hand.
    probs = np.array([[1.0, 0.0], [0.5, 0.5]])
    kl1 = math.log(1 / 0.75)
    kl2 = 0.5 * math.log(0.5 / 0.75) + 0.5 * math.log(0.5 / 0.25)
    assert metrics.inception_score(probs) == pytest.approx(math.exp((kl1 + kl2) / 2))
    with pytest.raises(ValueError):
        metrics.inception_score(np.array([[2.0, -1.0]]))  # logits, not probabilities


def test_mean_ci95_known_values():
    mean, half = metrics.mean_ci95([1.0, 2.0, 3.0, 4.0])
    assert mean == pytest.approx(2.5)
    assert half == pytest.approx(1.96 * math.sqrt(1.25) / 2)  # population std, ddof=0
    _, half1 = metrics.mean_ci95([1.0, 2.0, 3.0, 4.0], ddof=1)
    assert half1 == pytest.approx(1.96 * math.sqrt(5 / 3) / 2)
    assert metrics.mean_ci95([7.0]) == (7.0, 0.0)
    with pytest.raises(ValueError):
        metrics.mean_ci95([])
