"""Network-free measures of motions that training's end-of-training report and the evaluation share.

Pure functions: numpy in, python floats (or numpy arrays) out, no module state. Every random
choice goes through an explicit `rng: np.random.Generator`, so a seeded generator gives a
reproducible number.

Shape names: N motions, T frames, J joints, D code size.

- APD (ODMO §4.2.2) and mode homogeneity (ODMO §4.3.1): how homogeneous a set is, and how much
  splitting each action into the modes a model found makes it so (training reports it; the
  evaluation's n-APD, evaluation/metrics.py, is built on `apd`).
- Damping: how much the body moves about its root (speed and amplitude) and the root's height,
  generated over real, per action (`damping_ratios`, `class_ratios`): `odmo eval`'s speed and
  amplitude ratios, and training's decodes against their clips.
- What a decoder reaches and what bounds it: `body_error`, `mean_pose_error` (the action's mean
  pose), `retrieval_errors` (a lookup in a bank of clips) and `noise_ceiling` (the damping a
  squared-error decoder cannot avoid under its own posterior noise).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.distance import pdist


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
