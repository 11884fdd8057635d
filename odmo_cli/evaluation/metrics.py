"""The papers' evaluation metrics for action-conditioned motion generation.

Pure functions: numpy in, python floats (or numpy arrays) out, no module state. Every random
choice goes through an explicit `rng: np.random.Generator`, so a seeded generator gives a
reproducible number.

Shape names: N samples, D feature size, C classes, T frames, J joints.

Sources (papers in the project's shared folder):
- Classifier metrics (accuracy, FID, diversity, multimodality): Action2Motion (A2M) §4.2.1 and
  the ODMO supplement §2.5, which follows A2M's sampling protocol.
- n-APD: ODMO §4.2.2, on APD itself and beside mode homogeneity (ODMO §4.3.1), which training
  reports too (measures/diagnostics.py). dist_e: ODMO §4.4.
- Inception score: DVGAN §6.2, eq. 7.
"""

from __future__ import annotations

import warnings
from typing import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import linalg
from scipy.special import rel_entr

from odmo_cli.measures.diagnostics import _as_labels, _as_motions, _blocks, _norm3, apd

# pytorch-fid's tolerance on the imaginary part of sqrtm(S1 S2)'s diagonal.
_IMAG_ATOL = 1e-3
# Relative size of a negative FID we still treat as rounding of a true 0.
_NEG_FID_RTOL = 1e-6


def _as_2d(features: ArrayLike, name: str) -> NDArray[np.float64]:
    x = np.asarray(features, dtype=np.float64)
    if x.ndim != 2 or x.shape[0] == 0:
        raise ValueError(f"{name} must have shape (N, D) with N >= 1, got {x.shape}")
    return x


# ---------------------------------------------------------------------------------------------
# Recognition accuracy


def _hits(logits_or_pred: ArrayLike, labels: ArrayLike) -> tuple[NDArray[np.bool_], NDArray[np.int64]]:
    """(N,) whether each prediction is right, and the (N,) labels."""
    scores = np.asarray(logits_or_pred)
    if scores.ndim == 2:
        pred = scores.argmax(axis=1)  # (N,)
    elif scores.ndim == 1:
        pred = scores
    else:
        raise ValueError(f"logits_or_pred must be (N, C) or (N,), got {scores.shape}")
    if pred.shape[0] == 0:
        raise ValueError("accuracy of an empty set is undefined")
    y = _as_labels(labels, pred.shape[0])
    return pred.astype(np.int64) == y, y


def accuracy(logits_or_pred: ArrayLike, labels: ArrayLike) -> float:
    """Fraction of samples whose predicted class equals the label, in [0, 1].

    `logits_or_pred` is either (N, C) scores (logits or probabilities; the argmax is the
    prediction) or (N,) predicted class indices. `labels` is (N,) true class indices.
    """
    return float(np.mean(_hits(logits_or_pred, labels)[0]))


def accuracy_per_class(logits_or_pred: ArrayLike, labels: ArrayLike, n_classes: int) -> NDArray[np.float64]:
    """Accuracy within each true class, (n_classes,) in [0, 1]; NaN for a class with no sample."""
    hits, y = _hits(logits_or_pred, labels)
    count = np.bincount(y, minlength=n_classes)[:n_classes].astype(np.float64)
    right = np.bincount(y, weights=hits, minlength=n_classes)[:n_classes]
    with np.errstate(invalid="ignore", divide="ignore"):
        return right / count


# ---------------------------------------------------------------------------------------------
# Frechet (inception) distance


def feature_stats(features: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Features (N, D) -> (mean (D,), covariance (D, D)).

    The covariance is the unbiased one (np.cov, ddof=1), as in A2M and pytorch-fid.
    """
    x = _as_2d(features, "features")
    if x.shape[0] < 2:
        raise ValueError("feature_stats needs at least 2 samples for a covariance")
    mu = x.mean(axis=0)  # (D,)
    # atleast_2d: np.cov returns a 0-d array when D == 1.
    sigma = np.atleast_2d(np.cov(x, rowvar=False))  # (D, D)
    return mu, sigma


def _quiet_sqrtm(m: NDArray[np.float64]) -> NDArray:
    """linalg.sqrtm without its singular-matrix warning: fewer samples than feature dimensions make
    the product singular, and the caller checks (and retries) the root, so the warning is noise in a
    command's output, not news."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", linalg.LinAlgWarning)
        return linalg.sqrtm(m)


def _sqrtm_product(sigma1: NDArray[np.float64], sigma2: NDArray[np.float64], eps: float) -> NDArray:
    covmean = _quiet_sqrtm(sigma1 @ sigma2)
    if not np.all(np.isfinite(covmean)):
        # A (nearly) singular product can have no finite square root; shifting both
        # covariances by eps*I makes it well defined, as pytorch-fid does.
        offset = np.eye(sigma1.shape[0]) * eps
        covmean = _quiet_sqrtm((sigma1 + offset) @ (sigma2 + offset))
    if np.iscomplexobj(covmean):
        # S1 S2 is similar to a PSD matrix, so its root is real in exact arithmetic; only a
        # tiny imaginary part is rounding.
        max_imag = np.max(np.abs(np.diagonal(covmean).imag))
        if max_imag > _IMAG_ATOL:
            raise ValueError(f"sqrtm(sigma1 @ sigma2) has imaginary component {max_imag:.3g}")
        covmean = covmean.real
    return covmean


def fid(
    mu1: ArrayLike, sigma1: ArrayLike, mu2: ArrayLike, sigma2: ArrayLike, eps: float = 1e-6
) -> float:
    """Frechet distance between N(mu1, sigma1) and N(mu2, sigma2).

        FID = ||mu1 - mu2||^2 + Tr(sigma1 + sigma2 - 2 sqrt(sigma1 sigma2))

    mu1, mu2 are (D,); sigma1, sigma2 are (D, D). If sqrtm is not finite, it is retried with
    eps*I added to both covariances. A negative result from rounding is clamped to 0; a
    clearly negative one raises ValueError, as it means the inputs are not covariances.
    """
    m1 = np.atleast_1d(np.asarray(mu1, dtype=np.float64))  # (D,)
    m2 = np.atleast_1d(np.asarray(mu2, dtype=np.float64))  # (D,)
    s1 = np.atleast_2d(np.asarray(sigma1, dtype=np.float64))  # (D, D)
    s2 = np.atleast_2d(np.asarray(sigma2, dtype=np.float64))  # (D, D)
    d = m1.shape[0]
    if m2.shape != (d,) or s1.shape != (d, d) or s2.shape != (d, d):
        raise ValueError(
            f"shape mismatch: mu1 {m1.shape}, mu2 {m2.shape}, sigma1 {s1.shape}, sigma2 {s2.shape}"
        )

    diff = m1 - m2  # (D,)
    covmean = _sqrtm_product(s1, s2, eps)  # (D, D)
    value = float(diff @ diff + np.trace(s1) + np.trace(s2) - 2.0 * np.trace(covmean))
    if value < 0.0:
        scale = float(diff @ diff + np.trace(s1) + np.trace(s2)) + 1e-12
        if -value > _NEG_FID_RTOL * scale:
            raise ValueError(f"FID came out negative ({value:.3g}); are sigma1/sigma2 PSD?")
        value = 0.0
    return value


def fid_from_features(features1: ArrayLike, features2: ArrayLike, eps: float = 1e-6) -> float:
    """FID between two feature sets (N1, D) and (N2, D), via their means and covariances."""
    mu1, sigma1 = feature_stats(features1)
    mu2, sigma2 = feature_stats(features2)
    return fid(mu1, sigma1, mu2, sigma2, eps=eps)


# ---------------------------------------------------------------------------------------------
# Diversity and multimodality (A2M §4.2.1, ODMO supplement §2.5)


def _mean_pair_distance(
    x: NDArray[np.float64], n_pairs: int, rng: np.random.Generator
) -> float:
    # A2M draws two independent index sets with replacement and pairs them index-wise, so a
    # pair may repeat a sample (distance 0); we keep that to match the published numbers.
    first = rng.integers(0, x.shape[0], size=n_pairs)  # (n_pairs,)
    second = rng.integers(0, x.shape[0], size=n_pairs)  # (n_pairs,)
    return float(np.linalg.norm(x[first] - x[second], axis=1).mean())


def diversity(features: ArrayLike, n_pairs: int = 200, *, rng: np.random.Generator) -> float:
    """Mean Euclidean distance over `n_pairs` random pairs drawn across the whole set.

    features: (N, D), N >= 2. Pairs are (x[a_i], x[b_i]) with a = rng.integers(0, N, n_pairs)
    drawn first, then b the same way (A2M eq. 10, S_d = 200).
    """
    x = _as_2d(features, "features")
    if x.shape[0] < 2:
        raise ValueError("diversity needs at least 2 samples")
    if n_pairs < 1:
        raise ValueError(f"n_pairs must be >= 1, got {n_pairs}")
    return _mean_pair_distance(x, n_pairs, rng)


def multimodality(
    features: ArrayLike, labels: ArrayLike, n_pairs: int = 20, *, rng: np.random.Generator
) -> float:
    """Within-action diversity, averaged over actions (A2M eq. 11, S_l = 20).

    features: (N, D); labels: (N,) action ids. For each action, in increasing id order, draw
    `n_pairs` pairs inside that action as in `diversity` and take their mean distance; the
    result is the unweighted mean over actions. Actions with fewer than 2 samples are
    skipped (no pair of distinct motions exists); ValueError if no action has 2.
    """
    x = _as_2d(features, "features")
    y = _as_labels(labels, x.shape[0])
    if n_pairs < 1:
        raise ValueError(f"n_pairs must be >= 1, got {n_pairs}")
    per_action = [
        _mean_pair_distance(x[y == action], n_pairs, rng)
        for action in np.unique(y)
        if np.count_nonzero(y == action) >= 2
    ]
    if not per_action:
        raise ValueError("multimodality needs an action with at least 2 samples")
    return float(np.mean(per_action))


# ---------------------------------------------------------------------------------------------
# Normalised APD (ODMO §4.2.2)


def class_apd(motions: ArrayLike, labels: ArrayLike, cap: int | None = None) -> dict[int, float]:
    """{category: APD of its motions} for every category of `labels` with at least 2 motions
    (the first `cap` of each, when given). motions (N, T, J, 3), labels (N,)."""
    m = _as_motions(motions, dtype=None)
    y = _as_labels(labels, m.shape[0])
    out = {}
    for c in np.unique(y).tolist():
        own = np.asarray(m[y == c][:cap], dtype=np.float64)
        if own.shape[0] >= 2:
            out[c] = apd(own)
    return out


def apd_ratio(gen_apd: dict[int, float], real_apd: dict[int, float]) -> float:
    """n-APD from per-category APDs (class_apd): the mean over gen_apd's categories of generated
    over real APD. ValueError if a category has no real APD or a real APD of 0."""
    ratios = []
    for c in sorted(gen_apd):
        real = real_apd.get(c, 0.0)
        if real == 0.0:
            raise ValueError(f"category {c}: real motions need >= 2 distinct sequences")
        ratios.append(gen_apd[c] / real)
    if not ratios:
        raise ValueError("n-APD needs a category with at least 2 generated motions")
    return float(np.mean(ratios))


def n_apd(
    gen_motions: ArrayLike,
    gen_labels: ArrayLike,
    real_motions: ArrayLike,
    real_labels: ArrayLike,
    cap: int | None = None,
) -> float:
    """Normalised APD of a model (ODMO §4.2.2).

        n-APD(I) = (1 / |C|) * sum_i APD(M_I(C_i)) / APD(M_G(C_i))

    The APD of the generated motions of each category, divided by the APD of that category's
    real motions (APD varies a lot between actions), averaged over the categories present in
    `gen_labels`; with `cap`, each category's first `cap` motions on either side. gen_motions
    (N, T, J, 3) with gen_labels (N,); real_motions (M, T', J, 3) with real_labels (M,).
    ValueError if a category has fewer than 2 motions on either side, or its real motions are
    all identical. (The protocol computes the real side once: apd_ratio(class_apd(...), real).)
    """
    gm = _as_motions(gen_motions, "gen_motions")
    gy = _as_labels(gen_labels, gm.shape[0], "gen_labels")
    if gm.shape[0] == 0:
        raise ValueError("n_apd needs generated motions")
    gen = class_apd(gm, gy, cap)
    few = sorted(set(np.unique(gy).tolist()) - set(gen))
    if few:
        raise ValueError(f"category {few[0]}: n-APD needs at least 2 generated motions")
    return apd_ratio(gen, class_apd(real_motions, real_labels, cap))


# ---------------------------------------------------------------------------------------------
# Trajectory customisation and skeleton quality


def dist_e(asked: ArrayLike, reached: ArrayLike) -> float:
    """Goal error dist_e between asked and reached end locations (ODMO §4.4).

    asked, reached: (N, 3) or (N, 2). The paper says "mean squared error"; ODMO's code
    (compute_control_error) sums the squared error over coordinates and averages over
    samples, so this is mean_i ||asked_i - reached_i||^2 (not divided by the dimension).
    """
    a = _as_2d(asked, "asked")
    r = _as_2d(reached, "reached")
    if a.shape != r.shape or a.shape[1] not in (2, 3):
        raise ValueError(
            f"asked and reached must both be (N, 2) or (N, 3), got {a.shape}, {r.shape}"
        )
    return float(np.sum((a - r) ** 2, axis=1).mean())


def bone_length_consistency(motions: ArrayLike, parents: Sequence[int]) -> float:
    """Std over time of each bone's length, averaged over bones and motions (0 = rigid).

    motions: (N, T, J, 3); parents: J ints, parents[j] the parent joint of j, -1 for the root.
    Each j with a parent defines one bone. The std is the population std (ddof=0) over T.
    """
    m = _as_motions(motions, dtype=None)  # converted to float64 block by block
    par = np.asarray(parents, dtype=np.int64)
    if par.shape != (m.shape[2],):
        raise ValueError(f"parents must have one entry per joint ({m.shape[2]}), got {par.shape}")
    child = np.flatnonzero(par >= 0)  # (B,)
    if child.size == 0:
        raise ValueError("parents defines no bone")
    std = [_norm3(c[:, :, child] - c[:, :, par[child]]).std(axis=1) for c in _blocks(m)]  # (n, B) each
    return float(np.concatenate(std).mean())


# ---------------------------------------------------------------------------------------------
# Inception score (DVGAN)


def inception_score(probs: ArrayLike) -> float:
    """Inception score from class probabilities (DVGAN §6.2, eq. 7).

        IS = exp( mean_x KL(p(y|x) || p(y)) ),  p(y) = mean_x p(y|x)

    probs: (N, C), rows are softmax outputs (non-negative, summing to 1). Ranges from 1
    (every sample gets the same distribution) to C (confident and evenly spread classes).
    """
    p = _as_2d(probs, "probs")
    if np.any(p < 0) or not np.allclose(p.sum(axis=1), 1.0, atol=1e-4):
        raise ValueError("probs rows must be probability distributions (softmax, not logits)")
    marginal = p.mean(axis=0, keepdims=True)  # (1, C)
    # rel_entr takes 0 * log(0 / q) = 0, so classes never predicted cost nothing.
    kl = rel_entr(p, marginal).sum(axis=1)  # (N,)
    return float(np.exp(kl.mean()))


# ---------------------------------------------------------------------------------------------
# Reporting over repeats


def mean_ci95(values: ArrayLike, ddof: int = 0) -> tuple[float, float]:
    """Mean and 95% confidence-interval half-width of a metric over R repeats.

        half_width = 1.96 * std(values, ddof) / sqrt(R)

    values: (R,). The default ddof=0 (population std, np.std) is what A2M's evaluation code
    and its descendants use (`get_metric_statistics`), so numbers compare with theirs. Pass
    ddof=1 for the sample std. (ODMO's own released script differs again: sample std over
    sqrt(R - 1).) One repeat gives half-width 0 with ddof=0.
    """
    v = np.asarray(values, dtype=np.float64).ravel()  # (R,)
    if v.size == 0:
        raise ValueError("mean_ci95 needs at least one value")
    if v.size <= ddof:
        raise ValueError(f"need more than ddof={ddof} values, got {v.size}")
    half_width = 1.96 * v.std(ddof=ddof) / np.sqrt(v.size)
    return float(v.mean()), float(half_width)
