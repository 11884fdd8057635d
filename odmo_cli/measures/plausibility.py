"""What an animator sees that a classifier does not: network-free measures of a set of motions.

Pure functions, numpy in, numpy or floats out. Motions are (N, T, J, 3) in the dataset's frame and
units; the caller says which coordinate is up (`up`, with its sign), which joints are feet, the frame
rate and the body's leg length, which scales the thresholds so that one definition serves every
skeleton (docs/evaluation.md, "What an animator sees").

- Foot contact and skating, after GMD (Karunratanakul et al., ICCV 2023): a foot joint is in contact
  while it is within CONTACT_HEIGHT leg lengths of its own lowest point in the motion, and it skates
  when it moves on the ground plane faster than SLIDE_SPEED leg lengths a second between two contact
  frames. GMD's 5 cm and 2.5 cm a frame at 20 fps are these for a leg of 0.8 m.
- The root's bounce and glide: the root's vertical and horizontal speed, the square root of its mean
  squared frame-to-frame change (its kinetic energy per unit mass, up to constants).
- Kinetic features, after AIST++ (Li et al., ICCV 2021) and Bailando (Siyao et al., CVPR 2022): each
  joint's mean horizontal and vertical kinetic energy and its mean acceleration ("energy expenditure"),
  beside pose statistics (each joint's mean and spread about the root); their Fréchet distance and the
  coverage and density of Naeem et al. (ICML 2020) in that space, z-scored by a real set.
- Bone-length variation: how much the most-varying bone of a motion changes length.

Real crops of clips shorter than the crop are padded with copies of their last frame
(data.dataset.crop_pad_shift): a still body with planted feet that no capture recorded. The feet, root
and kinetic measures take `lengths` (N,), each motion's own frames, and leave the copies out; a
difference or average that reaches into them is left out too.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from odmo_cli.measures.diagnostics import class_ratios, mean_finite

CONTACT_HEIGHT = 0.0625  # leg lengths above the joint's lowest point (GMD: 5 cm for a 0.8 m leg)
SLIDE_SPEED = 0.625  # leg lengths per second on the ground plane (GMD: 2.5 cm a frame at 20 fps, 0.8 m leg)
SMOOTH = 3  # frames of centred moving average before speeds are taken (as diagnostics.body_speed)
COVERAGE_K = 5  # nearest neighbours of Naeem et al.'s coverage and density


@dataclass(frozen=True)
class Frame:
    """What the measures need to know of a skeleton and its dataset."""

    up: int  # index of the vertical coordinate
    up_sign: float  # +1 where larger is higher, -1 for a -y-up dataset
    feet: tuple[int, ...]  # foot joints (ankles and toes), each judged on its own
    fps: float
    leg: float  # leg length (hip to ankle) in the dataset's units: the thresholds' scale

    @property
    def ground(self) -> list[int]:
        return [i for i in range(3) if i != self.up]


def frame_for(skeleton, fps: float, real_motions: ArrayLike) -> Frame:
    """The Frame of a skeleton (geometry.skeletons.Skeleton: its up axis and legs) at `fps`, its leg
    length measured on real motions (N, T, J, 3) of the dataset."""
    hip, knee, ankle, _ = skeleton.legs[0]
    return Frame(skeleton.up_index, skeleton.up_sign, skeleton.feet, float(fps),
                 leg_length(real_motions, hip, knee, ankle))


def _motions(motions: ArrayLike) -> NDArray[np.float64]:
    m = np.asarray(motions, dtype=np.float64)
    if m.ndim != 4 or m.shape[-1] != 3 or m.shape[1] < 2:
        raise ValueError(f"motions must have shape (N, T, J, 3) with T >= 2, got {m.shape}")
    return m


def _smooth(x: NDArray[np.float64], k: int = SMOOTH) -> NDArray[np.float64]:
    """Centred k-frame moving average over axis 1 (the frames); shorter motions are left as they are."""
    if k <= 1 or x.shape[1] < k + 1:
        return x
    T = x.shape[1] - k + 1
    return sum(x[:, i:i + T] for i in range(k)) / k


def _own_frames(lengths: ArrayLike | None, n: int, T: int) -> NDArray[np.int64]:
    """(N,) each motion's own frames: all T without `lengths`, else lengths clipped to [0, T]."""
    if lengths is None:
        return np.full(n, T, dtype=np.int64)
    own = np.asarray(lengths, dtype=np.int64)
    if own.shape != (n,):
        raise ValueError(f"lengths must have shape ({n},), got {own.shape}")
    return np.clip(own, 0, T)


def _valid(own: NDArray[np.int64], width: int, lost: int) -> NDArray[np.bool_]:
    """(N, width): index i of a series whose entry i spans frames i .. i + lost of its motion is the
    motion's own while i + lost < own frames."""
    return np.arange(width)[None] + lost < own[:, None]


def _mean(x: NDArray[np.float64], valid: NDArray[np.bool_]) -> NDArray[np.float64]:
    """Mean over axis 1 of x (N, T', ...) where valid (N, T'); NaN for a motion with no valid entry."""
    w = valid.reshape(valid.shape + (1,) * (x.ndim - 2)).astype(np.float64)
    count = w.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, (x * w).sum(axis=1) / np.maximum(count, 1), np.nan)


def leg_length(motions: ArrayLike, hip: int, knee: int, ankle: int) -> float:
    """Median over motions and frames of |hip - knee| + |knee - ankle|: the scale of the thresholds."""
    m = _motions(motions)
    upper = np.linalg.norm(m[:, :, hip] - m[:, :, knee], axis=-1)
    lower = np.linalg.norm(m[:, :, knee] - m[:, :, ankle], axis=-1)
    return float(np.median(upper + lower))


# -- feet ---------------------------------------------------------------------------------------------

def foot_contacts(motions: ArrayLike, frame: Frame, lengths: ArrayLike | None = None
                  ) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """Per motion (N,) each: foot-joint frames in contact, contact steps (a joint in contact at two
    consecutive frames) and the contact steps that skate (faster than SLIDE_SPEED on the ground
    plane), within each motion's own frames (`lengths`). Sums rather than shares, so that sets and
    actions pool them (`share`)."""
    m = _motions(motions)
    own = _valid(_own_frames(lengths, len(m), m.shape[1]), m.shape[1], 0)[..., None]  # (N, T, 1)
    feet = m[:, :, list(frame.feet)]  # (N, T, F, 3)
    height = frame.up_sign * feet[..., frame.up]  # (N, T, F)
    lowest = np.where(own, height, np.inf).min(axis=1, keepdims=True)
    contact = own & (height - lowest < CONTACT_HEIGHT * frame.leg)
    step = contact[:, 1:] & contact[:, :-1]  # (N, T-1, F)
    moved = np.linalg.norm(np.diff(feet[..., frame.ground], axis=1), axis=-1)  # (N, T-1, F), per frame
    skate = step & (moved > SLIDE_SPEED * frame.leg / frame.fps)
    return contact.sum(axis=(1, 2)), step.sum(axis=(1, 2)), skate.sum(axis=(1, 2))


def share(part: ArrayLike, whole: ArrayLike) -> float:
    """sum(part) / sum(whole): a pooled share; NaN when whole is empty or zero."""
    w = float(np.sum(whole))
    return float(np.sum(part)) / w if w > 0 else float("nan")


# -- the root -------------------------------------------------------------------------------------------

def root_speeds(motions: ArrayLike, frame: Frame, lengths: ArrayLike | None = None
                ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per motion (N,), (N,): the root's vertical and horizontal speed in units per second, the root
    mean square of its frame-to-frame change after a SMOOTH-frame moving average, over each motion's own
    frames (`lengths`; NaN for a motion too short for one step). A bouncing run moves up and down every
    stride; a glide does not."""
    m = _motions(motions)
    root = _smooth(m[:, :, 0])  # (N, T', 3)
    lost = m.shape[1] - root.shape[1]  # frames a smoothed entry reaches past its index
    step = np.diff(root, axis=1) * frame.fps  # (N, T'-1, 3)
    valid = _valid(_own_frames(lengths, len(m), m.shape[1]), step.shape[1], lost + 1)
    vertical = np.sqrt(_mean(step[..., frame.up] ** 2, valid))
    horizontal = np.sqrt(_mean((step[..., frame.ground] ** 2).sum(-1), valid))
    return vertical, horizontal


# -- kinetic features --------------------------------------------------------------------------------------

def kinetic_features(motions: ArrayLike, frame: Frame, lengths: ArrayLike | None = None) -> NDArray[np.float64]:
    """(N, 9 J) per motion, after a SMOOTH-frame moving average: each joint's mean horizontal and
    vertical kinetic energy per unit mass (1/2 v^2, units^2/s^2) and mean acceleration norm
    (units/s^2), in the dataset's frame (the root's travel counts); then each joint's mean position
    about the root and its standard deviation over time (3 + 3 values). Over each motion's own frames
    (`lengths`); a row of NaN for a motion too short for an acceleration."""
    raw = _motions(motions)
    own = _own_frames(lengths, len(raw), raw.shape[1])
    m = _smooth(raw)  # (N, T', J, 3)
    lost = raw.shape[1] - m.shape[1]
    v = np.diff(m, axis=1) * frame.fps  # (N, T'-1, J, 3)
    a = np.diff(v, axis=1) * frame.fps if v.shape[1] > 1 else np.zeros_like(v)
    v_ok, a_ok = _valid(own, v.shape[1], lost + 1), _valid(own, a.shape[1], lost + 2)
    if v.shape[1] == 1:  # no acceleration to take: as before, zeros where the velocity is the motion's
        a_ok = v_ok
    ke_h = 0.5 * _mean((v[..., frame.ground] ** 2).sum(-1), v_ok)  # (N, J)
    ke_v = 0.5 * _mean(v[..., frame.up] ** 2, v_ok)
    spend = _mean(np.linalg.norm(a, axis=-1), a_ok)
    body = m - m[:, :, :1]
    m_ok = _valid(own, m.shape[1], lost)
    pose_mean = _mean(body, m_ok)  # (N, J, 3)
    pose_std = np.sqrt(_mean((body - pose_mean[:, None]) ** 2, m_ok))
    features = np.concatenate([ke_h, ke_v, spend, pose_mean.reshape(len(m), -1), pose_std.reshape(len(m), -1)], axis=1)
    features[~a_ok.any(axis=1)] = np.nan
    return features


def standardizer(reference: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Mean and standard deviation (floored) of the reference features (N, D): the z-scoring that
    `frechet` and `coverage_density` take their features in; rows with NaN (motions too short) left out."""
    r = np.asarray(reference, dtype=np.float64)
    r = r[np.isfinite(r).all(axis=1)]
    std = r.std(axis=0)
    moving = std[std > 0]
    # a feature that hardly varies in the real set (the root about itself: 0) would turn rounding into
    # large distances: floored at a hundredth of the typical spread
    floor = 0.01 * float(np.median(moving)) if moving.size else 1.0
    return r.mean(axis=0), np.maximum(std, floor)


def frechet(real: ArrayLike, generated: ArrayLike) -> float:
    """Fréchet distance between Gaussians fitted to two feature sets (N, D) and (M, D), N, M >= 2:
    |m1 - m2|^2 + tr(S1 + S2 - 2 (S1^1/2 S2 S1^1/2)^1/2), the root taken through symmetric
    eigendecompositions, so that sets with fewer motions than features (singular covariances) give a
    finite, non-negative number."""
    r, g = np.asarray(real, dtype=np.float64), np.asarray(generated, dtype=np.float64)
    s1, s2 = np.atleast_2d(np.cov(r, rowvar=False)), np.atleast_2d(np.cov(g, rowvar=False))
    w, v = np.linalg.eigh(s1)
    root1 = (v * np.sqrt(np.clip(w, 0, None))) @ v.T  # S1^1/2
    cross = np.linalg.eigvalsh(root1 @ s2 @ root1)
    d = ((r.mean(0) - g.mean(0)) ** 2).sum() + np.trace(s1) + np.trace(s2) - 2 * np.sqrt(np.clip(cross, 0, None)).sum()
    return float(max(d, 0.0))


def coverage_density(real: ArrayLike, generated: ArrayLike, k: int = COVERAGE_K) -> tuple[float, float]:
    """Naeem et al. (2020): each distinct real feature (N, D) gets the radius of its k-th nearest real
    neighbour. Coverage: the share of real features with a generated one (M, D) strictly inside their
    radius (0 when the generated set sits in one place, near 1 when it spans the real one). Density: the
    mean number of real balls each generated feature lies in, over k (near 1 for a set like the real one).
    Repeated real features count once: real crops of clips no longer than the crop are all the same
    crop, and copies would give each other a radius of 0, a ball nothing can enter (strict `<` as the
    authors' prdc)."""
    r, g = np.unique(np.asarray(real, dtype=np.float64), axis=0), np.asarray(generated, dtype=np.float64)
    if len(r) <= k or len(g) == 0:
        return float("nan"), float("nan")
    rr = _distances(r, r)
    radius = np.sort(rr, axis=1)[:, k]  # column 0 is the point itself
    inside = _distances(r, g) < radius[:, None]  # (N, M)
    return float(inside.any(axis=1).mean()), float(inside.sum() / (k * len(g)))


def _distances(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    d2 = (a * a).sum(1)[:, None] + (b * b).sum(1)[None] - 2 * a @ b.T
    return np.sqrt(np.maximum(d2, 0))


# -- bones ---------------------------------------------------------------------------------------------------

def bone_variation(motions: ArrayLike, parents: Sequence[int]) -> NDArray[np.float64]:
    """Per motion (N,): how much its most-varying bone changes length (max minus min over the frames),
    in the dataset's units. 0 for a rigid body."""
    m = _motions(motions)
    child = [j for j, p in enumerate(parents) if p >= 0]
    length = np.linalg.norm(m[:, :, child] - m[:, :, [parents[j] for j in child]], axis=-1)  # (N, T, B)
    return (length.max(axis=1) - length.min(axis=1)).max(axis=1)


# -- a set against a real one -------------------------------------------------------------------------------

PER_ACTION = ("foot_skate", "foot_contact", "root_up", "root_ground", "coverage", "density")


def measure(motions: ArrayLike, frame: Frame, parents: Sequence[int], lengths: ArrayLike | None = None
            ) -> dict[str, NDArray]:
    """Everything `compare` needs of a set of motions (N, T, J, 3), per motion, so that the motions
    need not be kept: foot-contact counts, root speeds, kinetic features and bone variation, over
    each motion's own frames (`lengths`, (N,): real crops padded past their clip's end; default all)."""
    m = _motions(motions)
    own = _own_frames(lengths, len(m), m.shape[1])
    contact, steps, skate = foot_contacts(m, frame, own) if frame.feet else (np.zeros(len(m), np.int64),) * 3
    up, ground = root_speeds(m, frame, own)
    return {"contact": contact, "steps": steps, "skate": skate, "root_up": up, "root_ground": ground,
            "kinetic": kinetic_features(m, frame, own), "bones": bone_variation(m, parents),
            "slots": own * len(frame.feet)}


def compare(gen: dict, gen_labels: ArrayLike, real: dict, real_labels: ArrayLike,
            scale: tuple[NDArray, NDArray]) -> dict[str, float]:
    """The measures of one set (`measure`'s output, with its labels) against a real set: overall and per
    action ("<measure>/<action index>"). `scale`: the z-scoring of the kinetic features (`standardizer`
    of a real set). Root speeds are ratios to the real set's, per action, and their mean over actions;
    coverage and density are taken within each action, then averaged; foot shares are pooled."""
    gy, ry = np.asarray(gen_labels), np.asarray(real_labels)
    mean, std = scale
    gz, rz = (gen["kinetic"] - mean) / std, (real["kinetic"] - mean) / std
    g_ok, r_ok = np.isfinite(gz).all(axis=1), np.isfinite(rz).all(axis=1)  # motions too short for them: out
    gz, rz, gky, rky = gz[g_ok], rz[r_ok], gy[g_ok], ry[r_ok]
    out: dict[str, float] = {
        "foot_skate": share(gen["skate"], gen["steps"]),
        "foot_contact": share(gen["contact"], gen["slots"]),
        "kinetic_fd": frechet(rz, gz) if len(gz) >= 2 and len(rz) >= 2 else float("nan"),
        "bone_var": float(np.percentile(gen["bones"], 95)),
        "bone_var_median": float(np.median(gen["bones"])),
    }
    for key in ("root_up", "root_ground"):
        g, r = np.isfinite(gen[key]), np.isfinite(real[key])
        ratios = {c: v for c, v in class_ratios(gen[key][g], gy[g], real[key][r], ry[r]).items() if np.isfinite(v)}
        if ratios:  # none where the real roots keep still (as damping's speed and amplitude)
            out[key] = mean_finite(ratios.values())
        out.update({f"{key}/{c}": v for c, v in ratios.items()})
    cover = {}
    for c in np.unique(gy).tolist():
        g = gy == c
        out[f"foot_skate/{c}"] = share(gen["skate"][g], gen["steps"][g])
        out[f"foot_contact/{c}"] = share(gen["contact"][g], gen["slots"][g])
        cov, den = coverage_density(rz[rky == c], gz[gky == c])
        if np.isfinite(cov):
            cover[c] = (cov, den)
            out[f"coverage/{c}"], out[f"density/{c}"] = cov, den
    out["coverage"] = mean_finite(v[0] for v in cover.values())
    out["density"] = mean_finite(v[1] for v in cover.values())
    return {k: v for k, v in out.items() if not (k.count("/") and not np.isfinite(v))}
