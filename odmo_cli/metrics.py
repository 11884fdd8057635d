"""Evaluation metrics for action-conditioned motion generation.

Pure functions: numpy in, python floats (or numpy arrays) out, no module state. Every random
choice goes through an explicit `rng: np.random.Generator`, so a seeded generator gives a
reproducible number.

Shape names: N samples, D feature size, C classes, T frames, J joints.

Sources (papers in the project's shared folder):
- Classifier metrics (accuracy, FID, diversity, multimodality): Action2Motion (A2M) §4.2.1 and
  the ODMO supplement §2.5, which follows A2M's sampling protocol.
- APD / n-APD: ODMO §4.2.2. Mode homogeneity: ODMO §4.3.1. dist_e: ODMO §4.4.
- Inception score: DVGAN §6.2, eq. 7.
"""

from __future__ import annotations

import warnings
from typing import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import linalg
from scipy.spatial.distance import pdist
from scipy.special import rel_entr

# pytorch-fid's tolerance on the imaginary part of sqrtm(S1 S2)'s diagonal.
_IMAG_ATOL = 1e-3
# Relative size of a negative FID we still treat as rounding of a true 0.
_NEG_FID_RTOL = 1e-6


def _as_2d(features: ArrayLike, name: str) -> NDArray[np.float64]:
    x = np.asarray(features, dtype=np.float64)
    if x.ndim != 2 or x.shape[0] == 0:
        raise ValueError(f"{name} must have shape (N, D) with N >= 1, got {x.shape}")
    return x


def _as_motions(motions: ArrayLike, name: str = "motions", dtype=np.float64) -> NDArray:
    """motions checked to be (N, T, J, 3), as `dtype` (None: as they are, without a copy)."""
    m = np.asarray(motions, dtype=dtype)
    if m.ndim != 4 or m.shape[-1] != 3:
        raise ValueError(f"{name} must have shape (N, T, J, 3), got {m.shape}")
    return m


BLOCK = 64  # motions per block in the per-motion statistics: small enough to stay in the CPU's cache


def _blocks(motions: ArrayLike):
    """(N, T, J, 3) motions as float64 blocks of at most BLOCK motions (at least one block)."""
    m = _as_motions(motions, dtype=None)
    for b in range(0, max(len(m), 1), BLOCK):
        yield np.asarray(m[b:b + BLOCK], dtype=np.float64)


def _norm3(x: NDArray[np.float64]) -> NDArray[np.float64]:
    """Euclidean norm over a last axis of 3, (..., 3) -> (...): np.linalg.norm's sum in its order,
    without its temporaries."""
    return np.sqrt(x[..., 0] * x[..., 0] + x[..., 1] * x[..., 1] + x[..., 2] * x[..., 2])


def _as_labels(labels: ArrayLike, n: int, name: str = "labels") -> NDArray[np.int64]:
    y = np.asarray(labels)
    if y.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},), got {y.shape}")
    return y.astype(np.int64)


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
# Average pairwise distance (ODMO §4.2.2) and mode homogeneity (ODMO §4.3.1)


def apd(motions: ArrayLike) -> float:
    """Average pairwise distance of a set of N motions (N, T, J, 3), N >= 2 (ODMO §4.2.2).

        APD(A) = 1 / (N (N - 1)) * sum_i sum_{j != i} ( sum_t ||m_t^(i) - m_t^(j)||^2 )^(1/2)

    with m_t the pose at frame t flattened to J*3 coordinates: the Euclidean distance between
    whole flattened sequences, averaged over ordered pairs (equal to the mean over unordered
    pairs). Lower APD means a more homogeneous set.
    """
    m = _as_motions(motions)
    if m.shape[0] < 2:
        raise ValueError("apd needs at least 2 motions")
    return float(pdist(m.reshape(m.shape[0], -1)).mean())


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


def mode_apd(motions: ArrayLike, modes: ArrayLike) -> float:
    """Size-weighted mean APD of the modes of one category (ODMO §4.3.1).

        mode-APD(G_c) = (1 / |G_c|) * sum_k |G(c, k)| * APD(G(c, k))

    motions: (N, T, J, 3), the category's motions G_c; modes: (N,) mode index of each.
    A single-motion mode counts as APD 0 (it is perfectly homogeneous), as in ODMO's code.
    """
    m = _as_motions(motions)
    k = _as_labels(modes, m.shape[0], "modes")
    if m.shape[0] == 0:
        raise ValueError("mode_apd needs at least 1 motion")
    total = 0.0
    for mode in np.unique(k):
        members = m[k == mode]  # (|G(c,k)|, T, J, 3)
        if members.shape[0] >= 2:
            total += members.shape[0] * apd(members)
    return total / m.shape[0]


def mode_homogeneity(motions: ArrayLike, labels: ArrayLike, modes: ArrayLike) -> float:
    """Mode homogeneity in percent (ODMO §4.3.1, Table 3; higher = purer modes).

        mode-homogeneity = 100 * (1 / |C|) * sum_c (APD(G_c) - mode-APD(G_c)) / APD(G_c)

    i.e. the mean relative drop in APD when each category's real motions G_c are split into
    the modes a model's latent clustering found. motions: (N, T, J, 3) real motions;
    labels: (N,) category ids; modes: (N,) mode id within the category (ids are only compared
    inside a category). Splitting into modes at random gives about 0; putting all of a
    category in one mode gives exactly 0. ValueError if a category has fewer than 2 motions
    or all its motions are identical (APD(G_c) = 0).
    """
    m = _as_motions(motions)
    y = _as_labels(labels, m.shape[0])
    k = _as_labels(modes, m.shape[0], "modes")
    if m.shape[0] == 0:
        raise ValueError("mode_homogeneity needs motions")

    drops = []
    for c in np.unique(y):
        in_c = y == c
        if np.count_nonzero(in_c) < 2:
            raise ValueError(f"category {c} has fewer than 2 motions")
        whole = apd(m[in_c])
        if whole == 0.0:
            raise ValueError(f"category {c}: all motions identical, relative APD undefined")
        drops.append((whole - mode_apd(m[in_c], k[in_c])) / whole)
    return 100.0 * float(np.mean(drops))


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
# Inception score (DVGAN) and clustering agreement


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


def adjusted_rand(labels_true: ArrayLike, labels_pred: ArrayLike) -> float:
    """Adjusted Rand index between two clusterings (N,) (sklearn.metrics.adjusted_rand_score)."""
    from sklearn.metrics import adjusted_rand_score

    return float(adjusted_rand_score(np.asarray(labels_true), np.asarray(labels_pred)))


# ---------------------------------------------------------------------------------------------
# Damping: how much the body moves (speed and amplitude about the root), generated over real


def _body(motions: ArrayLike, smooth: int) -> NDArray[np.float64]:
    """Joints about the root (N, T, J-1, 3), after a centred `smooth`-frame moving average over time.

    Real captures carry frame-to-frame jitter worth 15-30% of their raw speed that no squared-error
    model reproduces; averaging both sets over a few frames compares the motion, not the jitter.
    """
    m = _as_motions(motions)
    body = m[:, :, 1:] - m[:, :, :1]  # (N, T, J-1, 3)
    if smooth > 1 and body.shape[1] >= smooth:
        T = body.shape[1] - smooth + 1
        body = sum(body[:, k:k + T] for k in range(smooth)) / smooth  # (N, T - smooth + 1, J-1, 3)
    return body


def body_speed(motions: ArrayLike, smooth: int = 3) -> NDArray[np.float64]:
    """Mean body-relative joint speed of each motion (N,), in units per frame: the norm of the
    frame-to-frame change of every joint about the root, averaged over joints and frames."""
    return body_speed_and_amplitude(motions, smooth)[0]


def body_amplitude(motions: ArrayLike, smooth: int = 3) -> NDArray[np.float64]:
    """Mean amplitude of each motion (N,): the standard deviation over time of every joint's
    position about the root (root-mean-square distance from its mean position), averaged over joints."""
    return body_speed_and_amplitude(motions, smooth)[1]


def body_speed_and_amplitude(motions: ArrayLike, smooth: int = 3) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(body_speed, body_amplitude) of each motion, smoothing the motions once for both."""
    speed, amplitude = [], []
    for block in _blocks(motions):  # each motion's figures alone: the same numbers as all at once
        body = _body(block, smooth)
        speed.append(_speed(body))
        amplitude.append(_amplitude(body))
    return np.concatenate(speed), np.concatenate(amplitude)


def root_height_speed_and_amplitude(motions: ArrayLike, up_axis: int, smooth: int = 3
                                    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per motion (N,), (N,): mean absolute frame-to-frame change, and standard deviation about its
    least-squares line over time (a steady climb or sink is no amplitude), of the root's height
    (coordinate `up_axis`), after a centred `smooth`-frame moving average. What the body about the
    root cannot show: a jump's rise and fall."""
    h = _as_motions(motions)[:, :, 0, up_axis]  # (N, T)
    if smooth > 1 and h.shape[1] >= smooth:
        T = h.shape[1] - smooth + 1
        h = sum(h[:, k:k + T] for k in range(smooth)) / smooth
    if h.shape[1] < 2:
        raise ValueError("root height speed needs at least 2 frames after smoothing")
    t = np.arange(h.shape[1]) - (h.shape[1] - 1) / 2
    hc = h - h.mean(1, keepdims=True)
    resid = hc - (hc @ t / (t @ t))[:, None] * t
    return np.abs(np.diff(h, axis=1)).mean(1), np.sqrt((resid ** 2).mean(1))


def _speed(body: NDArray[np.float64]) -> NDArray[np.float64]:
    if body.shape[1] < 2:
        raise ValueError("body_speed needs at least 2 frames after smoothing")
    return _norm3(np.diff(body, axis=1)).mean(axis=(1, 2))


def _amplitude(body: NDArray[np.float64]) -> NDArray[np.float64]:
    dev = body - body.mean(axis=1, keepdims=True)
    return np.sqrt((dev ** 2).sum(-1).mean(axis=1)).mean(axis=1)


def body_error(pred_motions: ArrayLike, real_motions: ArrayLike) -> float:
    """Mean joint distance between the bodies about their roots (joint 0), (N, T, J, 3) each: where
    a motion is, and which way its path runs, do not count; its pose does."""
    pm, rm = _as_motions(pred_motions, "pred_motions"), _as_motions(real_motions, "real_motions")
    if pm.shape != rm.shape:
        raise ValueError(f"pred_motions {pm.shape} and real_motions {rm.shape} differ in shape")
    return float(_norm3((pm - pm[:, :, :1]) - (rm - rm[:, :, :1])).mean())


def mean_pose_error(motions: ArrayLike, labels: ArrayLike) -> float:
    """body_error of each motion's action-mean body (frame by frame, over these motions themselves):
    what a decoder that ignores everything but the action would reach. A model's body_error at or
    above it on clips it trained on means its pose decoder under-fits."""
    m = _as_motions(motions)
    y = _as_labels(labels, m.shape[0])
    body = m - m[:, :, :1]
    mean = np.empty_like(body)
    for c in np.unique(y):
        mean[y == c] = body[y == c].mean(axis=0)
    return float(_norm3(mean - body).mean())


def retrieval_errors(motions: ArrayLike, labels: ArrayLike, codes: ArrayLike, bank_motions: ArrayLike,
                     bank_labels: ArrayLike, bank_codes: ArrayLike) -> dict[str, float]:
    """What a decoder of new clips is up against when it draws them from a bank of known clips.

    For each motion (N, T, J, 3) of an action the bank (M, T, J, 3) holds, the body error about the root
    (per clip, as body_error) against the bank motion of its action whose code (D,) is nearest
    ("nearest_code": retrieval, what a lookup by the code gives) and against the bank motion of its
    action that fits it best ("best_clip": an oracle that looks at the answer). Means over the motions
    whose action has bank clips; NaN when none has."""
    m, b = _as_motions(motions), _as_motions(bank_motions, "bank_motions")
    y, by = _as_labels(labels, m.shape[0]), _as_labels(bank_labels, b.shape[0], "bank_labels")
    z, bz = np.asarray(codes, dtype=np.float64), np.asarray(bank_codes, dtype=np.float64)
    body, bank_body = m - m[:, :, :1], b - b[:, :, :1]
    nearest, best = [], []
    for i in range(len(m)):
        own = np.flatnonzero(by == y[i])
        if not len(own):
            continue
        errs = _norm3(bank_body[own] - body[i]).mean(axis=(1, 2))  # (K,): against each bank clip of the action
        nearest.append(errs[np.argmin(((bz[own] - z[i]) ** 2).sum(axis=1))])
        best.append(errs.min())
    if not nearest:
        return {"nearest_code": float("nan"), "best_clip": float("nan")}
    return {"nearest_code": float(np.mean(nearest)), "best_clip": float(np.mean(best))}


def damping_ratios(gen_motions: ArrayLike, gen_labels: ArrayLike, real_motions: ArrayLike,
                   real_labels: ArrayLike, smooth: int = 3) -> dict:
    """Generated over real body speed and amplitude, per category and their mean over categories.

    For each category present in gen_labels: mean body_speed (body_amplitude) of its generated
    motions over that of its real motions. A model that moves like the data scores 1; a damped
    one (limbs too slow, too little swing) below 1. Returns {"speed": float, "amplitude": float,
    "speed_by_class": {c: ratio}, "amplitude_by_class": {c: ratio}}; a category with no real motions,
    or real motions that do not move, has ratio NaN and is left out of the mean.
    """
    gm, rm = _as_motions(gen_motions, "gen_motions"), _as_motions(real_motions, "real_motions")
    gy = _as_labels(gen_labels, gm.shape[0], "gen_labels")
    ry = _as_labels(real_labels, rm.shape[0], "real_labels")
    (gen_speed, gen_amp), (real_speed, real_amp) = body_speed_and_amplitude(gm, smooth), body_speed_and_amplitude(rm, smooth)
    speed = class_ratios(gen_speed, gy, real_speed, ry)
    amp = class_ratios(gen_amp, gy, real_amp, ry)
    return {"speed": mean_finite(speed.values()), "amplitude": mean_finite(amp.values()),
            "speed_by_class": speed, "amplitude_by_class": amp}


def class_ratios(gen_values: ArrayLike, gen_labels: ArrayLike, real_values: ArrayLike,
                 real_labels: ArrayLike, still: float = 1e-6) -> dict[int, float]:
    """{c: mean of gen_values of class c / mean of real_values of class c} for every class in
    gen_labels; NaN for a class with no real values or real values of mean at most `still` (nothing to
    compare with: a rigid body's speed about its root is float rounding, 1e-8 of a metre a frame)."""
    gv, rv = np.asarray(gen_values, dtype=np.float64), np.asarray(real_values, dtype=np.float64)
    gy, ry = _as_labels(gen_labels, gv.shape[0], "gen_labels"), _as_labels(real_labels, rv.shape[0], "real_labels")
    out = {}
    for c in np.unique(gy).tolist():
        real = rv[ry == c]
        ok = real.size > 0 and real.mean() > still
        out[c] = float(gv[gy == c].mean() / real.mean()) if ok else float("nan")
    return out


def mean_finite(values) -> float:
    """Mean of the finite values (NaN when there are none)."""
    v = np.asarray(list(values), dtype=np.float64)
    return float(np.nanmean(v)) if np.isfinite(v).any() else float("nan")


def noise_ceiling(codes: ArrayLike, stds: ArrayLike, motions: ArrayLike, labels: ArrayLike,
                  rng: np.random.Generator, draws: int = 4, smooth: int = 3) -> dict:
    """The damping a squared-error decoder cannot avoid under its own posterior noise.

    In training the decoder sees z = mu_i + s_i * eps for clip i. The output with the least
    expected squared error for that z is the posterior mean of the motions that could have
    produced it: sum_j p(j | z) x_j over the clips j of the same class, p(j | z) proportional to
    N(z; mu_j, s_j^2 I). The noisier the codes against their spread, the more clips that average
    mixes and the slower it moves. Returns damping_ratios of those averages against the clips
    themselves: near 1 means the losses allow motion as lively as the data, well below 1 means
    no amount of training will reach it.

    codes, stds (N, D): each clip's posterior mean and standard deviation; motions (N, T, J, 3);
    labels (N,); `draws` noise draws per clip. Also "body": body_error of those averages against their
    clips, the least body error about the root a squared-error decoder can reach under that noise
    (0 when each code names its clip; mean_pose_error when every code of a class is the same).
    """
    mu = np.asarray(codes, dtype=np.float64)
    s = np.broadcast_to(np.asarray(stds, dtype=np.float64), mu.shape)
    m = _as_motions(motions)
    y = _as_labels(labels, m.shape[0])
    if mu.shape[0] != m.shape[0]:
        raise ValueError(f"codes ({mu.shape[0]}) and motions ({m.shape[0]}) differ in number")
    best, best_y, clip = [], [], []
    for c in np.unique(y).tolist():
        own = np.flatnonzero(y == c)
        mc, sc, xc = mu[own], s[own], m[own].reshape(len(own), -1)  # (n, D), (n, D), (n, T*J*3)
        for _ in range(draws):
            z = mc + sc * rng.standard_normal(mc.shape)  # (n, D)
            d2 = (((z[:, None, :] - mc[None]) / sc[None]) ** 2).sum(-1)  # (n, n)
            logp = -0.5 * d2 - np.log(sc).sum(-1)[None]
            w = np.exp(logp - logp.max(1, keepdims=True))
            w /= w.sum(1, keepdims=True)
            best.append((w @ xc).reshape(m[own].shape))
            best_y.append(np.full(len(own), c))
            clip.append(m[own])
    best = np.concatenate(best)
    return {**damping_ratios(best, np.concatenate(best_y), m, y, smooth), "body": body_error(best, np.concatenate(clip))}


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
