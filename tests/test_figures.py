"""Figures and printed output that a person reads (issue 28): bands and positions written in words, gathers against
receiver position in metres with a panel per receiver line, a colourbar on every image, the location's ellipse
drawn to scale with a zoomed inset when small, and an inversion's log, summary and CLI output without Python
tuples."""

import json

import numpy as np
import pytest
import yaml

from adseismic import plotting


@pytest.fixture
def figures(monkeypatch):
    """The matplotlib figures the plotting functions save (they are still written)."""
    saved = []
    original = plotting.save_figure

    def keep(fig, path):
        saved.append(fig)
        return original(fig, path)

    monkeypatch.setattr(plotting, "save_figure", keep)
    return saved


def image_axes(fig):
    """The axes of fig that hold an image or filled contours (colourbars and insets excluded)."""
    return [ax for ax in fig.axes if not hasattr(ax, "_colorbar") and (ax.images or filled(ax))]


def filled(ax):
    from matplotlib.contour import ContourSet

    return [c for c in ax.collections if isinstance(c, ContourSet) and c.filled]


def assert_every_image_has_a_colourbar(fig):
    """Each image has a labelled colourbar: its own, or one drawn for panels that share its colour scale (norm)."""
    mappables = [m for ax in fig.axes for m in (*ax.images, *filled(ax))]
    assert mappables, "no image in the figure"
    bars = {id(m.norm): m.colorbar for m in mappables if m.colorbar is not None}
    for m in mappables:
        bar = m.colorbar or bars.get(id(m.norm))
        assert bar is not None, f"{type(m).__name__} in '{m.axes.get_title()}' has no colourbar"
        assert bar.ax.get_ylabel() or bar.ax.get_xlabel(), "a colourbar without a label"


# ------------------------------------------------------------------ words for bands and positions


@pytest.mark.parametrize("band, text", [((None, 4.0), "<= 4 Hz"), ((2.0, 4.0), "2-4 Hz"), ((2, None), ">= 2 Hz"),
                                        ((None, None), "full band"), ((0.5, 2.5), "0.5-2.5 Hz")])  # fmt: skip
def test_format_band(band, text):
    from adseismic.runs import format_band

    assert format_band(*band) == text


def test_format_position():
    from adseismic.runs import format_position

    assert format_position(np.array([698.68, 1612.01])) == "z = 698.7 m, x = 1612.0 m"
    assert format_position([1.0, 2.0, 3.0]) == "z = 1.0 m, y = 2.0 m, x = 3.0 m"
    assert format_position([698.684, 1612.01], digits=2, errors=[0.11, 0.094]) == "z = 698.68 +- 0.11 m, x = 1612.01 +- 0.09 m"
    assert format_position([10.0], "z") == "z = 10.0 m"
    with pytest.raises(ValueError):
        format_position([1.0, 2.0], "zyx")


# ------------------------------------------------------------------ gathers


def two_lines(n=21):
    x = np.linspace(0.0, 800.0, n)
    return np.concatenate([np.stack([np.full(n, 10.0), x], 1), np.stack([np.full(n, 590.0), x], 1)])


def test_gather_of_two_receiver_lines_has_a_panel_per_line_in_metres(tmp_path, figures):
    rec = two_lines()
    data = np.random.default_rng(0).standard_normal((len(rec), 50))
    plotting.plot_gather(tmp_path / "residual.png", data, 0.01, rec, title="residual")
    (fig,) = figures
    panels = image_axes(fig)
    assert len(panels) == 2
    for ax, z in zip(panels, (10.0, 590.0)):
        assert ax.get_xlabel() == "receiver x (m)"
        assert f"z = {z:.1f} m" in ax.get_title()
        x0, x1 = sorted(ax.get_xlim())
        assert x0 < 0.0 and 800.0 < x1 < 900.0  # the line's x in metres, not a receiver index 0..41
    assert_every_image_has_a_colourbar(fig)
    assert "source-wavelet units" in panels[-1].images[0].colorbar.ax.get_ylabel()
    plotting.plot_gather(tmp_path / "residual.png", data, 0.01, rec, source=[20.0, 100.0], quantity="residual")
    stars = [line for ax in image_axes(figures[-1]) for line in ax.get_lines() if line.get_marker() == "*"]
    assert len(stars) == 2 and stars[0].get_xdata()[0] == 100.0  # the source's x above each line
    assert figures[-1].axes[-1].get_ylabel().startswith("residual (source-wavelet units)")
    # receiver x alone (the forward command's gathers): the two lines are still two panels
    plotting.plot_gather(tmp_path / "g.png", data, 0.01, rec[:, -1])
    assert len(image_axes(figures[-1])) == 2


def test_receiver_lines():
    z = np.linspace(0.0, 500.0, 11)
    borehole = np.stack([z, np.full(11, 300.0)], 1)
    (line,) = plotting.receiver_lines(borehole)
    assert line["axis"] == "z" and line["fixed"] == {"x": 300.0}
    stations = np.stack([np.zeros(5), np.array([300.0, 100.0, 700.0, 200.0, 500.0])], 1)  # one line, any order
    (line,) = plotting.receiver_lines(stations)
    np.testing.assert_array_equal(line["coordinate"], [100.0, 200.0, 300.0, 500.0, 700.0])
    np.testing.assert_array_equal(line["index"], [1, 3, 0, 4, 2])
    areal = np.stack(np.meshgrid([0.0], np.arange(10.0) * 50, np.arange(10.0) * 50, indexing="ij"), -1).reshape(-1, 3)
    assert plotting.receiver_lines(areal) is None  # ten lines: the receiver index instead


def test_irregular_line_and_no_positions(tmp_path, figures):
    x = np.array([0.0, 30.0, 100.0, 110.0, 400.0])
    rec = np.stack([np.zeros(5), x], 1)
    plotting.plot_gather(tmp_path / "a.png", np.ones((5, 30)), 0.01, rec)
    plotting.plot_gather(tmp_path / "b.png", np.ones((5, 30)), 0.01)
    (a,), (b,) = image_axes(figures[0]), image_axes(figures[1])
    assert a.get_xlabel() == "receiver x (m)" and b.get_xlabel() == "receiver index"
    for fig in figures:
        assert_every_image_has_a_colourbar(fig)


# ------------------------------------------------------------------ colourbars on every image


def test_every_image_has_a_colourbar(tmp_path, figures):
    rng = np.random.default_rng(1)
    plotting.plot_model(tmp_path / "m.png", 2000 + rng.random((20, 30)), 10.0, (0.0, 0.0), [[0.0, 50.0]], two_lines(5) * 0.3)
    plotting.plot_model(tmp_path / "g.png", rng.standard_normal((20, 30)), 10.0, (0.0, 0.0), label="gradient", cmap="seismic",
                        symmetric=True)  # fmt: skip
    plotting.plot_snapshots(tmp_path / "s.png", rng.standard_normal((5, 20, 30)), np.arange(5) * 0.1, 10.0, (0.0, 0.0), [[0.0, 50.0]])
    plotting.plot_gather(tmp_path / "r.png", rng.standard_normal((10, 40)), 0.01, two_lines(5))
    assert len(figures) == 4
    for fig in figures:
        assert_every_image_has_a_colourbar(fig)


# ------------------------------------------------------------------ the location map


def location_figure(tmp_path, figures, sigma):
    from adseismic.data.model import Model

    model = Model(np.full((61, 111), 2000.0), 20.0)
    pos = np.array([700.0, 1600.0])
    cov = sigma**2 * np.array([[1.0, 0.6], [0.6, 0.8]])
    hw = max(4 * sigma, 60.0)
    z, x = pos[0] + np.linspace(-hw, hw, 11), pos[1] + np.linspace(-hw, hw, 11)
    d = np.stack(np.meshgrid(z - pos[0], x - pos[1], indexing="ij"), -1)
    mis = 1000.0 + 0.5 * np.einsum("...i,ij,...j", d, np.linalg.inv(cov), d)
    stations = np.stack([np.zeros(8), np.linspace(100.0, 2100.0, 8)], 1)
    plotting.plot_location(tmp_path / f"location_{sigma:g}.png", model, stations, pos, cov, 1.51, {"z": z, "x": x, "misfit": mis},
                           truth_zx=pos + 0.3 * sigma, title="located")  # fmt: skip
    fig = figures[-1]
    assert_every_image_has_a_colourbar(fig)
    (bx,) = [ax for ax in image_axes(fig) if filled(ax)]
    return fig, bx


def test_location_map_has_a_colourbar_and_an_inset_on_a_small_ellipse(tmp_path, figures):
    _, bx = location_figure(tmp_path, figures, sigma=0.1)  # a ~0.3 m ellipse on a 120 m misfit map, a 2 km model
    assert "misfit" in filled(bx)[0].colorbar.ax.get_ylabel()
    (inset,) = bx.child_axes
    (ellipse,) = [line for line in inset.get_lines() if len(line.get_xdata()) > 10]
    ex, ez = ellipse.get_xdata(), ellipse.get_ydata()
    half = 0.5 * np.ptp(inset.get_xlim())
    assert 0.3 < np.ptp(ex) / (2 * half) < 1.0 and 0.3 < np.ptp(ez) / (2 * half) < 1.0  # fills the inset
    assert inset.get_aspect() == 1.0  # to scale
    # a large ellipse is readable on the map itself: no inset
    _, bx = location_figure(tmp_path, figures, sigma=15.0)
    assert not bx.child_axes


# ------------------------------------------------------------------ an inversion's log, summary and output


def test_fwi_log_summary_and_output_print_bands_in_words(tmp_path, capsys, figures):
    from adseismic.cli import main

    from .test_fwi import TINY

    cfg = {**TINY, "inversion": {**TINY["inversion"], "bands": [4.0, {"fmin": 2.0, "fmax": 6.0}, None], "iterations": 1}}
    path = tmp_path / "fwi.yaml"
    path.write_text(yaml.safe_dump(cfg))
    out = tmp_path / "run"
    assert main(["fwi", str(path), "-o", str(out)]) == 0
    printed = capsys.readouterr()
    log = (out / "fwi.log").read_text()
    text = (out / "summary.json").read_text()
    for where in (printed.out, printed.err, log, text):
        assert "(None" not in where and "None," not in where and "[None" not in where
    summary = json.loads(text)
    assert [b["band"] for b in summary["bands"]] == ["<= 4 Hz", "2-6 Hz", "full band"]
    assert [(b["f_low_hz"], b["f_high_hz"]) for b in summary["bands"]] == [(None, 4.0), (2.0, 6.0), (None, None)]
    assert "band 0 (<= 4 Hz) iteration 1" in log and "band 2 (full band) iteration 1" in log
    assert "band 1 (2-6 Hz):" in printed.out
    # the residual figure of each band: the top and the bottom receiver lines in their own panels, x in metres
    residuals = [f for f in figures if "residual" in f.get_suptitle()]
    assert len(residuals) == 3 and "band 2 (full band)" in residuals[-1].get_suptitle()
    panels = image_axes(residuals[-1])
    assert len(panels) == 2 and all(ax.get_xlabel() == "receiver x (m)" for ax in panels)
    for fig in figures:
        if image_axes(fig):
            assert_every_image_has_a_colourbar(fig)


def test_background_figures_are_written_in_order_and_a_failure_is_raised(tmp_path):
    """An FWI's band figures are drawn on one thread beside the next band; wait() returns once they are on disk and
    raises a drawing's failure instead of losing it."""
    bg = plotting.Background()
    rows = [(0, i, 0.5**i) for i in range(5)]
    bg.submit(plotting.plot_misfit, tmp_path / "a.png", rows)
    bg.submit(plotting.plot_misfit, tmp_path / "b.png", rows)
    bg.wait()
    assert (tmp_path / "a.png").stat().st_size > 1000 and (tmp_path / "b.png").stat().st_size > 1000
    bg.submit(plotting.plot_misfit, tmp_path / "no" / "such" / "dir.png", rows)
    with pytest.raises(FileNotFoundError):
        bg.wait()
    assert not list(tmp_path.glob("*.part"))
