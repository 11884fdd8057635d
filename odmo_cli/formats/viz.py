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
from matplotlib import animation  # noqa: E402
from matplotlib.animation import PillowWriter  # noqa: E402

from odmo_cli.errors import UserError  # noqa: E402
from odmo_cli.io import atomic_path  # noqa: E402
from odmo_cli.geometry.skeletons import Skeleton  # noqa: E402


def to_plot_frame(motions: np.ndarray, skeleton: Skeleton) -> np.ndarray:
    """(..., J, 3) in the dataset frame -> (..., J, 3) as (ground_a, ground_b, up) for 3-D plots."""
    a, b = skeleton.ground_axes
    up = motions[..., skeleton.up_index] * skeleton.up_sign
    return np.stack([motions[..., a], motions[..., b], up], axis=-1)


def _limits(points: np.ndarray) -> tuple[np.ndarray, float]:
    lo, hi = points.reshape(-1, 3).min(0), points.reshape(-1, 3).max(0)
    return (lo + hi) / 2, float((hi - lo).max() / 2 * 0.75 + 0.05)


CELL_INCHES = 2.6  # a cell's width in the figure (its height 2.8)
CELL_PIXELS = 480  # a cell's default width in pixels: a figure reads at this size
MAX_PIXELS = 1920  # the default figure's width at most (a wide grid gets smaller cells)


def _figure(n: int, titles: Sequence[str] | None, cols: int | None = None):
    cols = cols or min(n, 5)
    rows = (n + cols - 1) // cols
    fig = plt.figure(figsize=(CELL_INCHES * cols, 2.8 * rows))
    fig.subplots_adjust(left=0, right=1, bottom=0, top=0.92, wspace=0, hspace=0.05)
    axes = [fig.add_subplot(rows, cols, i + 1, projection="3d") for i in range(n)]
    for i, ax in enumerate(axes):
        ax.set_axis_off()
        ax.view_init(elev=15, azim=-70)
        if titles:
            ax.set_title(titles[i], fontsize=8)
    return fig, axes


def _trail_joints(skeleton: Skeleton) -> list[int]:
    """The root and the chains' end joints (hands, feet, head): what --trail follows."""
    return [0] + sorted({chain[-1] for chain in skeleton.chains})


def _writer_for(out: Path, fps: float):
    """(path actually written, matplotlib writer or None for a still, notice or "")."""
    suffix = out.suffix.lower()
    if suffix == ".png":
        return out, None, ""
    if suffix == ".mp4":
        if animation.writers.is_available("ffmpeg"):
            return out, animation.FFMpegWriter(fps=fps), ""
        gif = out.with_suffix(".gif")
        return gif, PillowWriter(fps=fps), f"note: ffmpeg not found, wrote {gif.name} (GIF) instead of {out.name}"
    if suffix == ".gif":
        return out, PillowWriter(fps=fps), ""
    raise UserError(f"cannot render to {out.name}: valid extensions are .gif, .mp4 and .png")


def animate(motions: np.ndarray, skeleton: Skeleton, out: str | Path, fps: float = 20,
            titles: Sequence[str] | None = None, end_points: np.ndarray | None = None,
            trail: bool = False, cols: int | None = None, size: tuple[int, int] | None = None,
            frame: int | None = None, frame_labels: Sequence[str] | None = None) -> tuple[Path, str]:
    """Write motions (N, T, J, 3) as one animation (a grid, one cell per motion).

    Each cell has a ground plane at the lowest foot height, the root trajectory on it, and the
    asked end point (end_points (N, 3), dataset frame; NaN rows are skipped) as a cross. With
    `trail` the paths of the root, hands, feet and head so far are drawn. `.mp4` needs ffmpeg,
    else a GIF is written beside it; `.png` is a still of `frame` (default: the middle one).
    size: (width, height) of the output in pixels (default: 480 x 517 per cell, the whole at most 1920 wide).
    frame_labels (T,): a label per frame (a composition's action), shown after each cell's title.
    Returns (the path written, a notice or "").
    """
    out = Path(out)
    written, writer, notice = _writer_for(out, fps)
    n_frames = max(len(m) for m in motions) if len(motions) else 0
    if frame is not None and writer is not None:
        raise UserError(f"--frame makes a still: write it to a .png, not {out.name}")
    if frame is not None and not 0 <= frame < n_frames:
        raise UserError(f"--frame {frame} is out of range: the motions have {n_frames} frames (0..{n_frames - 1})")
    if size is not None and (size[0] < 16 or size[1] < 16 or size[0] * size[1] > 4096 * 4096):
        raise UserError(f"--size must be between 16x16 and 4096x4096 pixels, got {size[0]}x{size[1]}")
    motions = np.asarray(motions, dtype=np.float32)
    if motions.ndim != 4 or motions.shape[-1] != 3 or motions.shape[2] != skeleton.n_joints or not len(motions):
        raise UserError(f"motions must be (N, T, {skeleton.n_joints}, 3), got {motions.shape}")
    motions = to_plot_frame(motions, skeleton)  # (N, T, J, 3) as (ground_a, ground_b, up)
    ends = None if end_points is None else to_plot_frame(np.asarray(end_points, dtype=np.float32), skeleton)
    fig, axes = _figure(len(motions), titles, cols)
    lines, trails = [], []
    follow = _trail_joints(skeleton)
    for i, (ax, motion) in enumerate(zip(axes, motions)):
        centre, radius = _limits(motion)
        floor = float(motion[..., 2].min())
        ax.set_xlim(centre[0] - radius, centre[0] + radius)
        ax.set_ylim(centre[1] - radius, centre[1] + radius)
        ax.set_zlim(centre[2] - radius, centre[2] + radius)
        gx, gy = np.meshgrid([centre[0] - radius, centre[0] + radius], [centre[1] - radius, centre[1] + radius])
        ax.plot_surface(gx, gy, np.full_like(gx, floor), color="0.85", alpha=0.4, linewidth=0)
        ax.plot(motion[:, 0, 0], motion[:, 0, 1], np.full(len(motion), floor), color="0.55", lw=0.8)
        if ends is not None and np.isfinite(ends[i, :2]).all():
            ax.plot([ends[i, 0]], [ends[i, 1]], [floor], marker="x", color="crimson", ms=6, ls="")
        lines.append([ax.plot([], [], [], lw=2, color=f"C{k}")[0] for k in range(len(skeleton.chains))])
        trails.append([ax.plot([], [], [], lw=0.7, color="0.3", alpha=0.6)[0] for _ in follow] if trail else [])

    def draw(t: int):
        for motion, chain_lines, trail_lines in zip(motions, lines, trails):
            now = min(t, len(motion) - 1)
            pose = motion[now]
            for line, chain in zip(chain_lines, skeleton.chains):
                pts = pose[list(chain)]
                line.set_data_3d(pts[:, 0], pts[:, 1], pts[:, 2])
            for line, j in zip(trail_lines, follow):
                path = motion[: now + 1, j]
                line.set_data_3d(path[:, 0], path[:, 1], path[:, 2])
        if frame_labels is not None and len(frame_labels):
            label = frame_labels[min(t, len(frame_labels) - 1)]
            for i, ax in enumerate(axes):
                ax.set_title(f"{titles[i]}: {label}" if titles else str(label), fontsize=8)
        return [ln for group in lines + trails for ln in group]

    cols_drawn = round(fig.get_size_inches()[0] / CELL_INCHES)
    dpi = min(CELL_PIXELS, MAX_PIXELS / cols_drawn) / CELL_INCHES
    if size is not None:
        fig.set_size_inches(size[0] / dpi, size[1] / dpi)
    try:
        with atomic_path(written, suffix=written.suffix) as tmp:
            if writer is None:
                draw(n_frames // 2 if frame is None else frame)
                fig.savefig(tmp, format="png", dpi=dpi)
            else:
                animation.FuncAnimation(fig, draw, frames=n_frames, blit=False).save(str(tmp), writer=writer, dpi=dpi)
    finally:
        plt.close(fig)
    return written, notice


def render_samples(samples: str | Path, out: str | Path, index: int | None = None, grid: str | None = None,
                   trail: bool = False, size: str | None = None, frame: int | None = None,
                   compare: str | None = None, data: str | Path | None = None, seed: int = 0) -> tuple[Path, str]:
    """`odmo render`: one motion (--index, default 0) or a ROWSxCOLS grid of the first motions.

    compare="real": under the generated motions, as many real clips of the same actions (random
    crops of the dataset's clip length, found with --data as everywhere else, drawn with `seed`).
    """
    from odmo_cli.formats.samples import read_samples
    from odmo_cli.geometry.skeletons import get_skeleton

    if index is not None and grid is not None:
        raise UserError("give either --index or --grid, not both")
    if compare not in (None, "real"):
        raise UserError(f"unknown --compare {compare!r}; valid: real")
    pixels = _size(size) if size is not None else None
    n = read_samples(samples, keys=())["n"]
    if grid is not None:
        rows, cols = _grid(grid)
        pick = list(range(min(n, rows * cols)))
    else:
        index = 0 if index is None else index
        if not 0 <= index < n:
            raise UserError(f"--index {index} is out of range: {Path(samples).name} has {n} motions (0..{n - 1})")
        pick, cols = [index], None
    f = read_samples(samples, keys=("motions",), rows=slice(pick[0], pick[-1] + 1),
                     optional=("actions", "end_points", "dataset", "frame_actions"))
    motions, ends = f["motions"], f["end_points"]
    actions = [str(a) for a in f["actions"]] if f["actions"] is not None else [""] * len(pick)
    skeleton, fps = get_skeleton(f["skeleton"]), f["fps"]
    titles = [f"{a} #{i}" for i, a in zip(pick, actions)]
    labels = f["frame_actions"]  # a composition (odmo compose): the action of every frame
    if labels is not None:
        titles = [f"#{i}" for i in pick]
    if compare == "real":
        if f["actions"] is None or labels is not None:
            raise UserError(f"--compare real needs each motion's one action; {Path(samples).name} has "
                            + ("a sequence of actions (odmo compose)" if labels is not None else "none"))
        dataset = str(f["dataset"]) if f["dataset"] is not None else None
        real = real_examples(dataset, skeleton, actions, motions.shape[1], data, seed)
        cols = cols or len(motions)
        motions = np.concatenate([motions, real])
        titles = titles + [f"real {a}" for a in actions]
        if ends is not None:
            ends = np.concatenate([ends, np.full((len(real), 3), np.nan, dtype=ends.dtype)])
    return animate(motions, skeleton, out, fps=fps, titles=titles, end_points=ends, trail=trail, cols=cols,
                   size=pixels, frame=frame, frame_labels=labels)


def real_examples(dataset: str | None, skeleton: Skeleton, actions: Sequence[str], length: int,
                  data: str | Path | None, seed: int) -> np.ndarray:
    """One random real crop (length frames, first root at the origin) per entry of `actions`:
    (len(actions), length, J, 3). The dataset is the samples file's, else the shipped dataset
    whose skeleton it is."""
    from odmo_cli.data.dataset import crop_pad_shift, random_start
    from odmo_cli.data.locate import resolve
    from odmo_cli.data.manifest import available_manifests, load_manifest
    from odmo_cli.data.readers import read_dataset

    if dataset is None:
        dataset = next((m for m in available_manifests() if load_manifest(m).skeleton_name == skeleton.name), None)
        if dataset is None:
            raise UserError(f"--compare real: no known dataset has skeleton {skeleton.name!r}")
    manifest, root = resolve(dataset, data)
    clips = read_dataset(root, manifest)
    rng = np.random.default_rng(seed)
    out = []
    for a in actions:
        if a not in manifest.action_names:
            raise UserError(f"--compare real: {manifest.name} has no action {a!r}")
        i = rng.choice(np.flatnonzero(clips.labels == list(manifest.action_names).index(a)))
        m = clips.motions[i]
        out.append(crop_pad_shift(m, length, random_start(len(m), length, rng)))
    return np.stack(out)


def _pair(text: str, expected: str) -> tuple[int, int]:
    """'AxB' -> (A, B), both positive integers; UserError `expected` (naming the option and its form)."""
    parts = text.lower().split("x")
    try:
        a, b = (int(p) for p in parts)
    except ValueError:
        a = b = 0
    if len(parts) != 2 or a <= 0 or b <= 0:
        raise UserError(f"{expected}; got {text!r}")
    return a, b


def _size(text: str) -> tuple[int, int]:
    return _pair(text, "--size must be WIDTHxHEIGHT in pixels, e.g. 640x480")


def _grid(text: str) -> tuple[int, int]:
    return _pair(text, "--grid must be ROWSxCOLS with positive numbers, e.g. 4x5")


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


# -- Notebook helpers: live figures, stick figures and animations that play without a kernel ------------
# Used by the teaching notebooks (notebooks/*.ipynb). Poses and motions are in the dataset's frame;
# `cube` and the axis limits are in plot coordinates (`to_plot_frame`: ground_a, ground_b, up).


def cube(points: np.ndarray, margin: float = 0.05) -> tuple[np.ndarray, float]:
    """Centre (3,) and half-size of the smallest axis-aligned cube holding points (..., 3), plus margin."""
    flat = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    lo, hi = flat.min(0), flat.max(0)
    return (lo + hi) / 2, float((hi - lo).max() / 2 + margin)


def draw_pose(ax, pose: np.ndarray, skeleton: Skeleton, centre: np.ndarray | None = None,
              radius: float | None = None, color: str | None = None, alpha: float = 1.0) -> list:
    """Draw one pose (J, 3) as a stick figure, up drawn up, in a 3-D axis: one line per chain of
    the skeleton (colour C<k> for chain k, or `color` for all), inside the cube of half-size
    `radius` around `centre` (plot coordinates; default: the pose's own `cube`). Returns the lines."""
    p = to_plot_frame(np.asarray(pose, dtype=np.float64), skeleton)  # (J, 3)
    if centre is None or radius is None:
        centre, radius = cube(p)
    lines = [ax.plot(*p[list(chain)].T, color=color or f"C{k}", lw=2, alpha=alpha)[0]
             for k, chain in enumerate(skeleton.chains)]
    for setter, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre):
        setter(c - radius, c + radius)
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=15, azim=-70)
    ax.set_xticklabels([]), ax.set_yticklabels([]), ax.set_zticklabels([])
    return lines


def live(draw, controls: dict) -> None:
    """Show the figure draw(**values) for the controls' current values now, and redraw it in place
    whenever a control (an ipywidgets ValueWidget, keyed by draw's argument name) changes.

    A static viewer or a headless run keeps the first figure (a PNG output); a live front end
    updates it. Returns nothing, so that a cell ending with it shows no extra output.
    """
    from IPython.display import display  # notebooks only: IPython is no dependency of the library

    def figure():
        fig = draw(**{name: w.value for name, w in controls.items()})
        plt.close(fig)  # shown through the display handle only, not again at the end of the cell
        return fig

    handle = display(figure(), display_id=True)
    for w in controls.values():
        w.observe(lambda _: handle.update(figure()), names="value")


def animation_html(motions: np.ndarray, skeleton: Skeleton, titles: Sequence[str] | None = None,
                   fps: float = 20.0, every: int = 2, dpi: int = 60, cell: float = 2.4,
                   cols: int | None = None) -> str:
    """Motions (N, T, J, 3) side by side as HTML/JS that plays in a notebook without a kernel
    (matplotlib's `to_jshtml`: every frame is a PNG inside the page, so keep it small).

    Every `every`-th frame is kept and played at fps / every; each cell is `cell` inches at `dpi`,
    with the root's path on the floor in grey and one fixed cube per motion. The first frame is
    also the image's initial source, so a viewer that runs no JavaScript still shows a still.
    """
    motions = np.asarray(motions, dtype=np.float64)
    if motions.ndim != 4 or motions.shape[2] != skeleton.n_joints or motions.shape[-1] != 3:
        raise UserError(f"motions must be (N, T, {skeleton.n_joints}, 3), got {motions.shape}")
    plot = to_plot_frame(motions, skeleton)  # (N, T, J, 3)
    frames = list(range(0, motions.shape[1], max(1, int(every))))
    n = len(motions)
    cols = cols or min(n, 5)
    rows = (n + cols - 1) // cols
    fig = plt.figure(figsize=(cell * cols, cell * rows * 1.05))
    fig.subplots_adjust(left=0, right=1, bottom=0, top=0.92, wspace=0, hspace=0.08)
    lines = []
    for i in range(n):
        ax = fig.add_subplot(rows, cols, i + 1, projection="3d")
        centre, radius = cube(plot[i])
        floor = plot[i, ..., 2].min()
        ax.plot(plot[i, :, 0, 0], plot[i, :, 0, 1], np.full(len(plot[i]), floor), color="0.6", lw=1)
        lines.append(draw_pose(ax, motions[i, 0], skeleton, centre, radius))
        ax.set_box_aspect((1, 1, 1), zoom=1.35)  # 3-D axes leave a wide margin by default
        ax.set_axis_off()
        if titles is not None:
            ax.set_title(titles[i], fontsize=8)

    def show(t: int):
        for i, chain_lines in enumerate(lines):
            for line, chain in zip(chain_lines, skeleton.chains):
                pts = plot[i, t, list(chain)]
                line.set_data_3d(pts[:, 0], pts[:, 1], pts[:, 2])
        return [ln for group in lines for ln in group]

    fig.set_dpi(dpi)
    try:
        anim = animation.FuncAnimation(fig, show, frames=frames, interval=1000 * max(1, int(every)) / fps,
                                       blit=False)
        html = anim.to_jshtml(fps=fps / max(1, int(every)), default_mode="loop")
    finally:
        plt.close(fig)
    return _with_still(html)


def _with_still(html: str) -> str:
    """Give matplotlib's jshtml image its first frame as initial source (unchanged if not found)."""
    import re

    first = re.search(r'frames\[0\] = "(data:image/[a-z]+;base64,[^"]*)"', html)
    img = re.search(r'<img id="(_anim_img[0-9a-f]+)">', html)
    if not (first and img):
        return html
    return html.replace(img.group(0), f'<img id="{img.group(1)}" src="{first.group(1)}">', 1)
