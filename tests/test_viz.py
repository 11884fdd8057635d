"""The notebook helpers of odmo_cli.formats.viz: cube, draw_pose, live and animation_html (headless)."""

from __future__ import annotations

import re

import matplotlib.pyplot as plt
import numpy as np
import pytest

from odmo_cli.formats import viz
from odmo_cli.errors import UserError
from odmo_cli.geometry.skeletons import get_skeleton

SK = get_skeleton("humanact12")


def a_pose(seed: int = 0) -> np.ndarray:
    """A (J, 3) pose with distinct joints, in the dataset's frame."""
    return np.random.default_rng(seed).normal(size=(SK.n_joints, 3))


def test_cube_holds_known_points():
    centre, half = viz.cube(np.array([[0.0, 0.0, 0.0], [2.0, 1.0, -1.0], [1.0, 0.5, 0.0]]))
    np.testing.assert_allclose(centre, [1.0, 0.5, -0.5])
    assert half == pytest.approx(1.0 + 0.05)  # the widest extent (x: 2) over 2, plus the margin
    centre, half = viz.cube(np.zeros((4, 7, 3)), margin=0.0)  # any leading shape; a point has size 0
    np.testing.assert_allclose(centre, 0.0)
    assert half == 0.0


def test_draw_pose_draws_one_line_per_chain_in_plot_coordinates():
    pose = a_pose()
    fig = plt.figure()
    ax = fig.add_subplot(projection="3d")
    lines = viz.draw_pose(ax, pose, SK, np.array([1.0, 2.0, 3.0]), 0.5, color="k")
    plotted = viz.to_plot_frame(pose, SK)
    assert len(lines) == len(ax.lines) == len(SK.chains)
    for line, chain in zip(lines, SK.chains):
        np.testing.assert_allclose(np.stack(line.get_data_3d(), -1), plotted[list(chain)])
        assert line.get_color() == "k"
    assert ax.get_xlim() == pytest.approx((0.5, 1.5)) and ax.get_zlim() == pytest.approx((2.5, 3.5))
    plt.close(fig)


def test_draw_pose_defaults_to_the_pose_cube_and_chain_colours():
    pose = a_pose(1)
    fig = plt.figure()
    ax = fig.add_subplot(projection="3d")
    lines = viz.draw_pose(ax, pose, SK)
    centre, half = viz.cube(viz.to_plot_frame(pose, SK))
    assert ax.get_ylim() == pytest.approx((centre[1] - half, centre[1] + half))
    assert [ln.get_color() for ln in lines[:2]] == ["C0", "C1"]
    plt.close(fig)


class FakeHandle:
    def __init__(self, shown):
        self.shown = shown

    def update(self, obj):
        self.shown.append(obj)


def test_live_draws_the_default_values_once_then_on_every_change(monkeypatch):
    widgets = pytest.importorskip("ipywidgets")
    pytest.importorskip("IPython")
    shown, calls = [], []

    def fake_display(obj, display_id=False):
        assert display_id is True
        shown.append(obj)
        return FakeHandle(shown)

    monkeypatch.setattr("IPython.display.display", fake_display)

    def draw(a, b):
        calls.append((a, b))
        fig, ax = plt.subplots()
        ax.plot([0, a], [0, b])
        return fig

    a, b = widgets.IntSlider(value=3, min=0, max=9), widgets.Dropdown(options=["x", "y"], value="x")
    viz.live(draw, {"a": a, "b": b})
    assert calls == [(3, "x")]  # once, with the defaults
    assert len(shown) == 1 and isinstance(shown[0], plt.Figure)
    assert shown[0].number not in plt.get_fignums()  # closed: shown by the handle only, not again
    a.value = 5
    b.value = "y"
    assert calls == [(3, "x"), (5, "x"), (5, "y")]
    assert len(shown) == 3 and all(isinstance(f, plt.Figure) for f in shown)


def test_animation_html_embeds_every_kept_frame_and_a_still():
    motions = np.stack([a_pose(0) + 0.01 * np.arange(10)[:, None, None],
                        a_pose(1) - 0.02 * np.arange(10)[:, None, None]])  # (2, 10, J, 3)
    html = viz.animation_html(motions, SK, titles=["one", "two"], every=3, dpi=20)
    assert len(re.findall(r'frames\[\d+\] = "data:image/png;base64,', html)) == 4  # frames 0, 3, 6, 9
    assert re.search(r'<img id="_anim_img\w+" src="data:image/png;base64,', html)
    with pytest.raises(UserError, match="motions must be"):
        viz.animation_html(motions[0], SK)
