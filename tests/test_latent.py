"""Mode discovery over a latent bank, ODMO's "M" (models/latent.py): the silhouette rules that choose k,
the mixtures' components, code sampling, KNN end points and the agreement of found modes with true ones."""

from __future__ import annotations

import numpy as np
import pytest

from odmo_cli.models.latent import ActionModes, adjusted_rand, choose_k, discover_modes, knn_end_points, sample_codes


def blobs(k, per=40, seed=0):
    """k tight blobs at the corners of a simplex (all centres 10 apart)."""
    rng = np.random.default_rng(seed)
    d = max(k, 4)
    centres = np.eye(d)[:k] * 10 / np.sqrt(2)
    return np.concatenate([c + rng.normal(0, 0.3, (per, d)) for c in centres]), np.repeat(np.arange(k), per)


@pytest.mark.parametrize("k", [3, 5, 7])
def test_silhouette_rule_finds_the_number_of_blobs(k):
    codes, _ = blobs(k, seed=k)
    modes = discover_modes(codes, seed=0)
    assert len(modes.means) == k
    assert sorted(modes.counts.tolist()) == [40] * k


def test_choose_k_rule():
    # S_3 > 0.95 S_4 holds first at 3
    assert choose_k({3: 0.6, 4: 0.61, 5: 0.9}) == 3
    # 3 -> 4 and 4 -> 5 improve by more than 5 %, 5 -> 6 does not
    assert choose_k({3: 0.3, 4: 0.5, 5: 0.8, 6: 0.81}) == 5
    assert choose_k({3: 0.1, 4: 0.2, 5: 0.3}) == 5


def test_choose_k_release_rule():
    # the release's rule goes on while S does not fall by more than 5 %: a flat curve is climbed
    flat = {3: 0.20, 4: 0.20, 5: 0.19, 6: 0.10, 7: 0.30}
    assert choose_k(flat, "paper") == 3  # S_3 > 0.95 S_4 already
    assert choose_k(flat, "release") == 5  # S_6 < 0.95 S_5 stops it at 5, whatever comes after
    assert choose_k({3: 0.3, 4: 0.5, 5: 0.8, 6: 0.81}, "release") == 6  # rising to the end: the largest k
    assert choose_k({3: 0.5, 4: 0.1}, "release") == 3
    with pytest.raises(ValueError, match="valid: paper, release"):
        choose_k(flat, "elbow")


def test_the_release_rule_climbs_only_to_nine_modes():
    codes, _ = blobs(10, per=30, seed=10)
    assert len(discover_modes(codes, seed=0).means) == 10  # the paper's k range reaches 11
    release = discover_modes(codes, seed=0, rule="release")
    assert len(release.means) == 9 and max(release.silhouettes) == 9  # k 3..9: two blobs share a mode
    assert release.counts.sum() == 300
    with pytest.raises(ValueError, match="valid: paper, release"):
        discover_modes(codes, rule="elbow")


def test_small_components_are_dropped_and_small_actions_fall_back():
    codes, _ = blobs(3, per=40)
    noise = np.random.default_rng(1).normal(30, 0.1, (4, 4))  # a far-away cluster of 4 codes
    modes = discover_modes(np.concatenate([codes, noise]), seed=0)
    assert all(c >= 10 for c in modes.counts) and modes.counts.sum() == 120
    few = discover_modes(codes[:12], seed=0)
    assert len(few.means) == 1 and "too few" in few.note


def test_sampling_from_one_mode_stays_in_it():
    codes, _ = blobs(3)
    modes = discover_modes(codes, seed=0)
    samples, ids = sample_codes(modes, 200, np.random.default_rng(0), mode=1)
    assert (ids == 1).all()
    nearest = np.linalg.norm(samples[:, None] - modes.means[None], axis=-1).argmin(1)
    assert (nearest == 1).all()


def test_mode_preserving_and_user_weights():
    modes = ActionModes(np.eye(2) * 10, np.stack([np.eye(2)] * 2), np.array([30, 10]))
    _, ids = sample_codes(modes, 4000, np.random.default_rng(0))
    assert abs((ids == 0).mean() - 0.75) < 0.03
    _, ids = sample_codes(modes, 4000, np.random.default_rng(0), weights=np.array([0.2, 0.8]))
    assert abs((ids == 1).mean() - 0.8) < 0.03


def test_knn_end_points():
    bank = np.array([[0.0, 0.0], [10.0, 0.0]])
    ends = np.array([[1.0, 0, 0], [2.0, 0, 0]])
    assert knn_end_points(bank, ends, np.array([[9.0, 0.0], [1.0, 0.0]])).tolist() == [[2, 0, 0], [1, 0, 0]]
    assert knn_end_points(bank, ends, np.array([[9.0, 0.0]]), k=2).tolist() == [[1.5, 0, 0]]


def test_adjusted_rand():
    assert adjusted_rand([0, 0, 1, 1], [1, 1, 0, 0]) == pytest.approx(1.0)
    # Pairs: 6 total, 2 together in truth, 1 together in prediction, 1 shared.
    # ARI = (1 - 2*1/6) / ((2 + 1)/2 - 2*1/6) = 4/7.
    assert adjusted_rand([0, 0, 1, 1], [0, 0, 1, 2]) == pytest.approx(4 / 7)
