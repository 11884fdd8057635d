"""ODMO's "M": the latent space of a trained model and the mode mixtures sampling draws from.

A latent bank holds, for every training clip, its mean code mu(P), action, end point and (where the
dataset has them) ground-truth mode; training writes it (training.odmo.latent_bank), and a file refitted
on random crops holds a crop bank beside it (generation.generate.crop_bank). They hold what mode
discovery and KNN end points need, so sampling never needs the dataset; nothing here reads one.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from odmo_cli.device import model_device


@torch.no_grad()
def codes_and_ends(model, batches) -> tuple[torch.Tensor, torch.Tensor]:
    """Encoder means and last-frame roots of motion batches, each (B, T, J, 3) -> (N, D), (N, 3)."""
    model.eval()
    dev = model_device(model)
    codes, ends = [], []
    for motion in batches:
        mu, _ = model.encode(motion.to(dev))
        codes.append(mu.cpu())
        ends.append(motion[:, -1, 0])
    return torch.cat(codes), torch.cat(ends)


def centroids(codes: np.ndarray, labels: np.ndarray, n_classes: int) -> np.ndarray:
    """Per-class mean code, (C, D); NaN rows for classes with no code."""
    out = np.full((n_classes, codes.shape[1]), np.nan)
    for c in range(n_classes):
        if (labels == c).any():
            out[c] = codes[labels == c].mean(0)
    return out


def separation(train_codes: np.ndarray, train_labels: np.ndarray, test_codes: np.ndarray,
               test_labels: np.ndarray, n_classes: int) -> dict[str, float]:
    """How well codes of different actions separate.

    centroid_distance: mean distance between class centroids (compare with the margin alpha);
    spread: RMS distance of codes to their own centroid; nearest_centroid_acc: share of test
    codes whose nearest training centroid is their own class.
    """
    cent = centroids(train_codes, train_labels, n_classes)
    present = ~np.isnan(cent[:, 0])
    c = cent[present]
    d = np.linalg.norm(c[:, None] - c[None], axis=-1)
    off = d[~np.eye(len(c), dtype=bool)]
    spread = np.sqrt(np.mean(np.sum((train_codes - cent[train_labels]) ** 2, axis=1)))
    dist_test = np.linalg.norm(test_codes[:, None] - c[None], axis=-1)  # (N, C_present)
    pred = np.flatnonzero(present)[dist_test.argmin(1)]
    return {"centroid_distance": float(off.mean()) if len(off) else 0.0,
            "min_centroid_distance": float(off.min()) if len(off) else 0.0,
            "spread": float(spread), "nearest_centroid_acc": float((pred == test_labels).mean())}


# -- mode discovery (main paper §3.3, supplement §2.2) -------------------------------------------

K_RANGE = (3, 11)
MIN_MEMBERS = 10  # components with fewer members are dropped as noise
# How k is chosen from the silhouette curve S_k (`odmo modes --refit --k-rule`): "paper", the supplement's
# text (§2.2: k 3..11, the first i with S_i > 0.95 S_{i+1}); "release", the authors' code
# (`sample_code_multimodal` in ensemble.py: k 3..9, raised while S_{k+1} >= 0.95 S_k, 5 EM starts per fit).
K_RULES = {"paper": {"k_range": K_RANGE, "n_init": 3}, "release": {"k_range": (3, 9), "n_init": 5}}


def k_rule_settings(rule: str) -> dict:
    """K_RULES[rule]: the rule's k range and EM starts per fit."""
    if rule not in K_RULES:
        raise ValueError(f"unknown k rule {rule!r}; valid: {', '.join(K_RULES)}")
    return K_RULES[rule]


@dataclass
class ActionModes:
    """A Gaussian mixture over one action's codes. weights follow the member counts."""

    means: np.ndarray  # (K, D)
    covariances: np.ndarray  # (K, D, D)
    counts: np.ndarray  # (K,) training codes assigned to each kept component
    silhouettes: dict[int, float] = field(default_factory=dict)  # k -> S_k
    note: str = ""  # why discovery fell back, when it did

    @property
    def weights(self) -> np.ndarray:
        return self.counts / self.counts.sum()

    def to_plain(self) -> dict:
        return {"means": torch.from_numpy(self.means), "covariances": torch.from_numpy(self.covariances),
                "counts": torch.from_numpy(self.counts), "ks": list(self.silhouettes),
                "silhouettes": list(self.silhouettes.values()), "note": self.note}

    @classmethod
    def from_plain(cls, d: dict) -> "ActionModes":
        return cls(d["means"].numpy(), d["covariances"].numpy(), d["counts"].numpy(),
                   dict(zip(d["ks"], d["silhouettes"])), d["note"])


def choose_k(silhouettes: dict[int, float], rule: str = "paper") -> int:
    """k from the silhouette curve S_k. "paper": the first i (from the smallest k) with
    S_i > 0.95 S_{i+1}, the largest k if none. "release": k raised from the smallest while
    S_{k+1} >= 0.95 S_k, which goes on along a flat or slowly falling curve where "paper" stops."""
    k_rule_settings(rule)
    ks = sorted(silhouettes)
    for i, j in zip(ks[:-1], ks[1:]):
        if rule == "paper" and silhouettes[i] > 0.95 * silhouettes[j]:
            return i
        if rule == "release" and silhouettes[j] < 0.95 * silhouettes[i]:
            return i
    return ks[-1]


def _gmm(codes: np.ndarray, k: int, seed: int, n_init: int = 3):
    from sklearn.mixture import GaussianMixture  # imported here: sampling needs no sklearn

    return GaussianMixture(n_components=k, covariance_type="full", n_init=n_init, reg_covar=1e-4,
                           random_state=seed).fit(codes)


def single_gaussian(codes: np.ndarray, note: str = "") -> ActionModes:
    d = codes.shape[1]
    cov = np.cov(codes, rowvar=False) if len(codes) > 1 else np.zeros((d, d))
    cov = np.atleast_2d(cov) + 1e-4 * np.eye(d)
    return ActionModes(codes.mean(0, keepdims=True), cov[None], np.array([len(codes)], dtype=np.int64), {}, note)


def discover_modes(codes: np.ndarray, seed: int = 0, k_range: tuple[int, int] | None = None,
                   min_members: int = MIN_MEMBERS, rule: str = "paper") -> ActionModes:
    """Fit GMMs with k in k_range (default: the rule's) to one action's codes (N, D), pick k by the
    silhouette rule (K_RULES), refit, and drop components with fewer than min_members codes."""
    import sklearn.metrics  # noqa: F401  loaded before the limit below, which binds loaded libraries only
    import sklearn.mixture  # noqa: F401
    from threadpoolctl import threadpool_limits

    settings = k_rule_settings(rule)
    # small matrices: threaded BLAS only adds overhead (x10 slower with another job running)
    with threadpool_limits(1):
        return _discover(np.unique(codes.astype(np.float64), axis=0), seed, k_range or settings["k_range"],
                         min_members, rule)


def _discover(codes: np.ndarray, seed: int, k_range: tuple[int, int], min_members: int, rule: str) -> ActionModes:
    lo, hi = k_range
    n_init = K_RULES[rule]["n_init"]
    if len(codes) < lo * min_members:
        return single_gaussian(codes, f"{len(codes)} clips are too few for {lo} modes of {min_members}: one Gaussian")
    silhouettes = {}
    for k in range(lo, min(hi, len(codes) - 1) + 1):
        labels = _gmm(codes, k, seed, n_init).predict(codes)
        if len(np.unique(labels)) < 2:
            silhouettes[k] = -1.0
            continue
        silhouettes[k] = float(_silhouette(codes, labels))
    gmm = _gmm(codes, choose_k(silhouettes, rule), seed, n_init)
    counts = np.bincount(gmm.predict(codes), minlength=gmm.n_components)
    keep = counts >= min_members
    if not keep.any():
        return single_gaussian(codes, "no component kept 10 members: one Gaussian")
    return ActionModes(gmm.means_[keep], gmm.covariances_[keep], counts[keep].astype(np.int64), silhouettes)


def _silhouette(codes: np.ndarray, labels: np.ndarray) -> float:
    from sklearn.metrics import silhouette_score

    return silhouette_score(codes, labels)


def fit_modes(bank: dict, n_classes: int, seed: int = 0, rule: str = "paper") -> dict:
    """Mode mixtures per action (k chosen by `rule`, K_RULES) plus one Gaussian per action (the
    paper's ODMO_conv), as plain values."""
    codes, labels = bank["codes"].numpy(), bank["labels"].numpy()
    per_action = [discover_modes(codes[labels == c], seed, rule=rule) for c in range(n_classes)]
    conventional = [single_gaussian(codes[labels == c].astype(np.float64)) for c in range(n_classes)]
    return {"seed": seed, "rule": rule, "actions": [m.to_plain() for m in per_action],
            "conventional": [m.to_plain() for m in conventional]}


def sample_codes(modes: ActionModes, n: int, rng: np.random.Generator, mode: int | None = None,
                 weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """n codes (n, D) and their component ids (n,): from one component, from given weights, or
    mode-preserving (components drawn in proportion to their member counts)."""
    ids = mode_ids(modes, n, rng, mode, weights)
    return codes_of(modes, ids, rng), ids


def mode_ids(modes: ActionModes, n: int, rng: np.random.Generator, mode: int | None = None,
             weights: np.ndarray | None = None) -> np.ndarray:
    """n component ids (n,): all `mode`, else drawn with `weights` (default: the mixture's own)."""
    if mode is not None:
        return np.full(n, mode, dtype=np.int64)
    p = modes.weights if weights is None else np.asarray(weights, dtype=np.float64) / np.sum(weights)
    return rng.choice(len(modes.means), size=n, p=p)


def codes_of(modes: ActionModes, ids: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One code (n, D) float32 drawn from each given component (ids (n,))."""
    eps = rng.standard_normal((len(ids), modes.means.shape[1]))
    chol = np.linalg.cholesky(modes.covariances)  # (K, D, D)
    return (modes.means[ids] + np.einsum("nij,nj->ni", chol[ids], eps)).astype(np.float32)


def knn_end_points(bank_codes: np.ndarray, bank_ends: np.ndarray, codes: np.ndarray, k: int = 1) -> np.ndarray:
    """End point of each code (n, D) as the mean end point of its k nearest bank codes (n, 3)."""
    from scipy.spatial.distance import cdist

    d = cdist(codes, bank_codes)  # (n, N), without an (n, N, D) temporary: memory stays flat in n
    nearest = np.argsort(d, axis=1)[:, :k]
    return bank_ends[nearest].mean(1).astype(np.float32)


def assign(modes: ActionModes, codes: np.ndarray) -> np.ndarray:
    """Most likely component of each code (N, D) -> (N,)."""
    from scipy.stats import multivariate_normal

    logp = np.stack([np.log(w) + multivariate_normal(m, c, allow_singular=True).logpdf(codes)
                     for m, c, w in zip(modes.means, modes.covariances, modes.weights)], axis=-1)
    return np.atleast_2d(logp).argmax(-1)


def adjusted_rand(labels_true: np.ndarray, labels_pred: np.ndarray) -> float:
    """Adjusted Rand index between two clusterings (N,) (sklearn.metrics.adjusted_rand_score)."""
    from sklearn.metrics import adjusted_rand_score

    return float(adjusted_rand_score(np.asarray(labels_true), np.asarray(labels_pred)))


def mode_report(bank: dict, modes: dict, actions: list[str]) -> list[dict]:
    """Per action: modes found, member counts, silhouettes and, where the bank has ground-truth
    modes, the adjusted Rand index between discovered and true modes."""
    codes, labels, truth = bank["codes"].numpy(), bank["labels"].numpy(), bank["modes"].numpy()
    rows = []
    for a, name in enumerate(actions):
        m = ActionModes.from_plain(modes["actions"][a])
        own = labels == a
        row = {"action": name, "clips": int(own.sum()), "modes": len(m.means), "members": m.counts.tolist(),
               "silhouettes": {int(k): round(v, 4) for k, v in m.silhouettes.items()}, "note": m.note,
               "true_modes": None, "ari": None}
        t = truth[own]
        if own.any() and (t >= 0).all():
            row["true_modes"] = int(len(np.unique(t)))
            row["ari"] = adjusted_rand(t, assign(m, codes[own].astype(np.float64)))
        rows.append(row)
    return rows
