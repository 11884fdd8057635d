"""Stick-figure drawings and animations of motions (matplotlib, no display needed).

Motions are drawn y-up whatever the dataset's frame: the skeleton's up axis is mapped to the
plot's vertical axis. Frames are redrawn by updating the existing artists' data, never by
assigning to matplotlib's artist lists.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import matplotlib

matplotlib.use("Agg")  # rendering to files only; never needs a display

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.animation import FuncAnimation, PillowWriter  # noqa: E402

from odmo_cli.errors import UserError  # noqa: E402
from odmo_cli.io import atomic_path  # noqa: E402
from odmo_cli.skeletons import Skeleton  # noqa: E402


def to_plot_frame(motions: np.ndarray, skeleton: Skeleton) -> np.ndarray:
    """(..., J, 3) in the dataset frame -> (..., J, 3) as (ground_a, ground_b, up) for 3-D plots."""
    a, b = skeleton.ground_axes
    up = motions[..., skeleton.up_index] * skeleton.up_sign
    return np.stack([motions[..., a], motions[..., b], up], axis=-1)


def _limits(points: np.ndarray) -> tuple[np.ndarray, float]:
    lo, hi = points.reshape(-1, 3).min(0), points.reshape(-1, 3).max(0)
    return (lo + hi) / 2, float((hi - lo).max() / 2 * 0.75 + 0.05)


def _figure(n: int, titles: Sequence[str] | None):
    cols = min(n, 5)
    rows = (n + cols - 1) // cols
    fig = plt.figure(figsize=(2.6 * cols, 2.8 * rows))
    fig.subplots_adjust(left=0, right=1, bottom=0, top=0.92, wspace=0, hspace=0.05)
    axes = [fig.add_subplot(rows, cols, i + 1, projection="3d") for i in range(n)]
    for i, ax in enumerate(axes):
        ax.set_axis_off()
        ax.view_init(elev=15, azim=-70)
        if titles:
            ax.set_title(titles[i], fontsize=8)
    return fig, axes


def animate(motions: np.ndarray, skeleton: Skeleton, out: str | Path, fps: float = 20,
            titles: Sequence[str] | None = None) -> Path:
    """Write motions (N, T, J, 3) as one animated GIF (a grid, one cell per motion)."""
    out = Path(out)
    if out.suffix.lower() not in (".gif", ".png"):
        raise UserError(f"cannot render to {out.name}: valid extensions are .gif and .png")
    motions = to_plot_frame(np.asarray(motions, dtype=np.float32), skeleton)
    if motions.ndim != 4:
        raise UserError(f"motions must be (N, T, J, 3), got {motions.shape}")
    fig, axes = _figure(len(motions), titles)
    lines = []
    for ax, motion in zip(axes, motions):
        centre, radius = _limits(motion)
        ax.set_xlim(centre[0] - radius, centre[0] + radius)
        ax.set_ylim(centre[1] - radius, centre[1] + radius)
        ax.set_zlim(centre[2] - radius, centre[2] + radius)
        ax.plot(motion[:, 0, 0], motion[:, 0, 1], motion[:, 0, 2], color="0.7", lw=0.8)  # root path
        lines.append([ax.plot([], [], [], lw=2, color=f"C{k}")[0] for k in range(len(skeleton.chains))])

    def draw(t: int):
        for motion, chain_lines in zip(motions, lines):
            pose = motion[min(t, len(motion) - 1)]
            for line, chain in zip(chain_lines, skeleton.chains):
                pts = pose[list(chain)]
                line.set_data_3d(pts[:, 0], pts[:, 1], pts[:, 2])
        return [ln for chain_lines in lines for ln in chain_lines]

    n_frames = max(len(m) for m in motions)
    with atomic_path(out, suffix=out.suffix) as tmp:
        if out.suffix.lower() == ".png":
            draw(n_frames // 2)
            fig.savefig(tmp, format="png", dpi=80)
        else:
            anim = FuncAnimation(fig, draw, frames=n_frames, blit=False)
            anim.save(str(tmp), writer=PillowWriter(fps=fps), dpi=60)
    plt.close(fig)
    return out


def latent_plot(codes: np.ndarray, colours: np.ndarray, names: Sequence[str], out: str | Path,
                method: str = "pca", gaussians: Sequence[tuple[np.ndarray, np.ndarray]] = (),
                seed: int = 0, title: str = "") -> Path:
    """Codes (N, D) projected to 2-D (pca or tsne), coloured by integer group; for PCA, the
    half-peak ellipse of each Gaussian (mean (D,), covariance (D, D)) is drawn too."""
    out = Path(out)
    if out.suffix.lower() not in (".png", ".pdf", ".svg"):
        raise UserError(f"cannot plot to {out.name}: valid extensions are .png, .pdf, .svg")
    if method == "pca":
        centre = codes.mean(0)
        _, _, vt = np.linalg.svd(codes - centre, full_matrices=False)
        basis = vt[:2].T  # (D, 2)
        xy = (codes - centre) @ basis
    elif method == "tsne":
        from sklearn.manifold import TSNE

        xy = TSNE(n_components=2, random_state=seed, init="pca",
                  perplexity=min(30, max(2, len(codes) // 4))).fit_transform(codes)
    else:
        raise UserError(f"unknown projection {method!r}; valid: pca, tsne")
    fig, ax = plt.subplots(figsize=(7, 6))
    for g in np.unique(colours):
        sel = colours == g
        ax.scatter(xy[sel, 0], xy[sel, 1], s=8, color=f"C{g % 10}", label=names[g] if g < len(names) else str(g))
    if method == "pca":
        from matplotlib.patches import Ellipse

        r = np.sqrt(2 * np.log(2))  # the half-peak contour of a Gaussian
        for mean, cov in gaussians:
            c2 = basis.T @ cov @ basis
            vals, vecs = np.linalg.eigh(c2)
            angle = np.degrees(np.arctan2(vecs[1, 1], vecs[0, 1]))
            ax.add_patch(Ellipse(((mean - centre) @ basis), 2 * r * np.sqrt(vals[1]), 2 * r * np.sqrt(vals[0]),
                                 angle=angle, fill=False, lw=1, color="0.2"))
    ax.legend(fontsize=7, markerscale=2, loc="best")
    ax.set_title(title or f"latent codes ({method.upper()})")
    with atomic_path(out, suffix=out.suffix) as tmp:
        fig.savefig(tmp, dpi=100, format=out.suffix[1:])
    plt.close(fig)
    return out
