"""PNG figures: a forward run's model with the acquisition, shot gathers and snapshots; an inversion's misfit
curve and residual gather; a location's traces and map.

Uses matplotlib's object API with the Agg canvas (no pyplot, no global backend switch, no
display needed). Every figure is written atomically: to ``<name>.png.part`` first, renamed into
place when complete. Coordinates are in world metres (shown in km when the section is wider than
2 km), axis order (z, [y,] x); 3D volumes are shown as the x-z slice through a given y. Every image
has a colourbar with its quantity and units; gathers are drawn against receiver position in metres,
one panel per receiver line.
"""
from __future__ import annotations

import pathlib

import numpy as np

from adseismic.data.atomic import atomic_write
from adseismic.runs import format_position

__all__ = ["Background", "plot_model", "plot_gather", "plot_snapshots", "plot_misfit", "plot_station_traces", "plot_location", "save_figure", "xz_slice",
           "receiver_lines"]


def _figure(width: float, height: float):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def save_figure(fig, path) -> pathlib.Path:
    """Write ``fig`` as PNG to ``path`` atomically (temporary name, then os.replace)."""
    with atomic_write(path) as part:
        fig.savefig(part, format="png")
    return pathlib.Path(path)


class Background:
    """Figures drawn on one background thread while the caller goes on (an FWI's next band on the device):
    ``submit(fn, *args)`` queues a drawing, ``wait()`` returns once every queued one is written and raises the
    first failure. One thread, so matplotlib is never used by two threads at once: the caller draws nothing
    itself before ``wait()``, and hands over arrays it will not change."""

    def __init__(self):
        from concurrent.futures import ThreadPoolExecutor

        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="figures")
        self._jobs = [self._pool.submit(_warm_up)]

    def submit(self, fn, *args, **kwargs):
        self._jobs.append(self._pool.submit(fn, *args, **kwargs))

    def wait(self):
        jobs, self._jobs = self._jobs, []
        for job in jobs:
            job.result()


def _warm_up():
    """Draw a small figure (to memory): matplotlib's imports, fonts and colormaps load here (~1 s)."""
    import io

    fig = _figure(2.0, 2.0)
    fig.colorbar(fig.add_subplot().imshow(np.zeros((2, 2)), cmap="seismic"), label="a")
    fig.savefig(io.BytesIO(), format="png")


def _scale(extent_m: float) -> tuple[float, str]:
    """(divisor, unit) so that axes read in km for sections wider than 2 km."""
    return (1000.0, "km") if extent_m > 2000.0 else (1.0, "m")


def xz_slice(values: np.ndarray, origin, spacing: float, y: float | None = None):
    """(2D array (nz, nx), index of the slice or None) of a 2D array or a 3D (z, y, x) volume
    sliced at the node nearest to world ``y`` (m; default the middle)."""
    values = np.asarray(values)
    if values.ndim == 2:
        return values, None
    ny = values.shape[1]
    j = ny // 2 if y is None else int(np.clip(round((y - origin[1]) / spacing), 0, ny - 1))
    return values[:, j, :], j


def plot_model(path, velocity, spacing: float, origin, sources=None, receivers=None,
               title: str = "", label: str = "velocity (m/s)", cmap: str = "viridis",
               symmetric: bool = False) -> pathlib.Path:
    """Velocity (m/s) on a grid of ``spacing`` m with node 0 at world ``origin`` (z,[y,]x);
    sources (n, ndim) as red stars and receivers (m, ndim) as triangles, world metres.
    In 3D the x-z slice through the first source is shown (points within one cell of it).
    Other fields (a gradient): ``label``, ``cmap`` and ``symmetric`` (colour limits +-99th
    percentile of |value|)."""
    velocity = np.asarray(velocity)
    ndim = velocity.ndim
    src = None if sources is None else np.asarray(sources, float).reshape(-1, ndim)
    rec = None if receivers is None else np.asarray(receivers, float).reshape(-1, ndim)
    y0 = src[0, 1] if (ndim == 3 and src is not None and len(src)) else None
    v2, j = xz_slice(velocity, origin, spacing, y0)
    oz, ox = origin[0], origin[-1]
    nz, nx = v2.shape
    width_m, depth_m = (nx - 1) * spacing, (nz - 1) * spacing
    k, unit = _scale(max(width_m, depth_m))
    aspect = depth_m / max(width_m, 1e-9)
    fig = _figure(9.0, float(np.clip(9.0 * aspect, 2.5, 9.0)) + 1.0)
    ax = fig.add_subplot()
    half = 0.5 * spacing
    extent = ((ox - half) / k, (ox + width_m + half) / k, (oz + depth_m + half) / k, (oz - half) / k)
    lim = {"vmin": -_clip(v2), "vmax": _clip(v2)} if symmetric else {}
    im = ax.imshow(v2, extent=extent, cmap=cmap, aspect="equal", interpolation="nearest", **lim)
    fig.colorbar(im, ax=ax, label=label, shrink=float(np.clip(1.2 * aspect, 0.5, 0.9)))

    def sel(p):  # 3D: points near the slice
        if p is None or ndim == 2:
            return p
        return p[np.abs(p[:, 1] - (origin[1] + j * spacing)) <= spacing]

    r, s = sel(rec), sel(src)
    if r is not None and len(r):
        ax.scatter(r[:, -1] / k, r[:, 0] / k, marker="v", s=18 if len(r) <= 200 else 6, c="white", edgecolors="black",
                   linewidths=0.5, label=f"receivers ({len(rec)})", zorder=3)
    if s is not None and len(s):
        ax.scatter(s[:, -1] / k, s[:, 0] / k, marker="*", s=120, c="red", edgecolors="black",
                   linewidths=0.5, label=f"sources ({len(src)})", zorder=4)
    if (r is not None and len(r)) or (s is not None and len(s)):
        ax.legend(loc="lower right", fontsize=8, framealpha=0.8)
    ax.set_xlim(extent[0], extent[1])
    ax.set_ylim(extent[2], extent[3])
    ax.set_xlabel(f"x ({unit})")
    ax.set_ylabel(f"depth z ({unit})")
    where = f", x-z slice at y = {origin[1] + j * spacing:g} m" if j is not None else ""
    ax.set_title((title or "velocity model") + f" (dx = {spacing:g} m{where})")
    return save_figure(fig, path)


def plot_misfit(path, rows, title: str = "", labels=None, ylabel: str = "misfit / misfit at the band's start") -> pathlib.Path:
    """Misfit (normalised by each band's start value) against iteration; rows: (band, iteration, misfit);
    labels: {band: text} for the legend (e.g. format_band's "<= 4 Hz"); ylabel: what the misfit is."""
    fig = _figure(7.0, 4.5)
    ax = fig.add_subplot()
    labels = labels or {}
    for b in sorted({r[0] for r in rows}):
        it = [(i, j) for bb, i, j in rows if bb == b]
        name = f"band {b}" + (f" ({labels[b]})" if b in labels else "")
        ax.semilogy([i for i, _ in it], [j for _, j in it], "o-", ms=3, label=name)
    from matplotlib.ticker import MaxNLocator

    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("iteration")
    ax.set_ylabel(ylabel)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    ax.set_title(title or "misfit per band")
    return save_figure(fig, path)


def _norm(lo: float, hi: float):
    from matplotlib.colors import Normalize

    return Normalize(lo, hi)


def _clip(a: np.ndarray, pct: float = 99.0) -> float:
    c = float(np.percentile(np.abs(a), pct)) if a.size else 0.0
    if c <= 0:
        c = float(np.abs(a).max()) if a.size else 0.0
    return c if c > 0 else 1.0


def _axis_names(ncol: int) -> str:
    return {1: "x", 2: "zx", 3: "zyx"}[ncol]


def receiver_lines(receivers, max_lines: int = 6):
    """The receivers split into lines for a gather's panels, or None when they form no few straight lines.

    receivers: (n,) x or (n, ndim) world m (axis order (z,[y,]x)) in the order of the data. A line is a
    run of consecutive receivers along which one coordinate changes, always in the same direction (a
    surface line then a bottom line, a vertical borehole line); receivers that share every coordinate
    but one, in any order, are one line. Returns [{"index": (k,) rows of the data sorted along the line,
    "coordinate": (k,) m along it, "axis": "x", "y" or "z", "fixed": {axis: m} of the other axes}]."""
    p = np.asarray(receivers, float)
    p = p[:, None] if p.ndim == 1 else p
    n, ncol = p.shape
    names = _axis_names(ncol)
    if n < 2:
        return None
    tol = 1e-6 * max(float(np.ptp(p, axis=0).max()), 1.0)
    runs, start, axis, sign = [], 0, None, 0.0
    for i in range(1, n + 1):
        if i < n:
            step = p[i] - p[i - 1]
            moved = np.abs(step) > tol
            if moved.sum() == 1:
                a = int(np.argmax(moved))
                if axis is None:
                    axis, sign = a, np.sign(step[a])
                    continue
                if a == axis and np.sign(step[a]) == sign:
                    continue
        runs.append((start, i, axis))
        start, axis, sign = i, None, 0.0
    if len(runs) > max_lines or any(a is None for _, _, a in runs):  # one line in another order?
        moving = np.ptp(p, axis=0) > tol
        if moving.sum() != 1:
            return None
        runs = [(0, n, int(np.argmax(moving)))]
    out = []
    for s, e, a in runs:
        idx = np.arange(s, e)
        idx = idx[np.argsort(p[idx, a], kind="stable")]
        out.append({"index": idx, "coordinate": p[idx, a], "axis": names[a],
                    "fixed": {names[j]: float(p[s, j]) for j in range(ncol) if j != a}})  # fmt: skip
    return out


def _even(x) -> bool:
    d = np.diff(x)
    return len(x) > 1 and bool(np.all(d > 0)) and bool(np.allclose(d, d.mean(), rtol=1e-3))


def _gather_panel(ax, data, dt: float, line, norm):
    """Draw one line's traces (k, nt) on ax (colour limits: norm, shared by the panels and their colourbar);
    returns (image, x-range (lo, hi) in m, km divisor)."""
    nt = data.shape[1]
    t_end = (nt - 1) * dt
    kw = {"cmap": "seismic", "norm": norm}
    if line is None:
        im = ax.imshow(data.T, extent=(-0.5, len(data) - 0.5, t_end + 0.5 * dt, -0.5 * dt), aspect="auto",
                       interpolation="bilinear", **kw)  # fmt: skip
        ax.set_xlabel("receiver index")
        return im, None, 1.0
    x = line["coordinate"]
    k, unit = _scale(float(x[-1] - x[0]))
    lo, hi = x[0] - 0.5 * (x[1] - x[0]), x[-1] + 0.5 * (x[-1] - x[-2])
    if _even(x):
        im = ax.imshow(data.T, extent=(lo / k, hi / k, t_end + 0.5 * dt, -0.5 * dt), aspect="auto",
                       interpolation="bilinear", **kw)  # fmt: skip
    else:  # irregular spacing: each trace at its receiver's position
        from matplotlib.image import NonUniformImage

        im = NonUniformImage(ax, interpolation="nearest", extent=(lo / k, hi / k, t_end, 0.0), **kw)
        im.set_data(x / k, np.arange(nt) * dt, data.T)
        ax.add_image(im)
        ax.set_xlim(lo / k, hi / k)
        ax.set_ylim(t_end + 0.5 * dt, -0.5 * dt)
    ax.set_xlabel(f"receiver {'depth ' if line['axis'] == 'z' else ''}{line['axis']} ({unit})")
    return im, (lo, hi), k


def plot_gather(path, data, dt: float, receiver_x=None, title: str = "", percentile: float = 99.0,
                source=None, units: str | None = None, quantity: str = "amplitude") -> pathlib.Path:  # fmt: skip
    """One shot gather (n_receivers, nt): time (s, down) against receiver position (world m), seismic
    colormap clipped symmetrically at the ``percentile`` of |data|, a colourbar in ``units``.

    receiver_x: (n,) receiver x or (n, ndim) receiver positions (world m, axis order (z,[y,]x)) in the
    order of the data. Receivers on several lines (a top and a bottom line, a borehole) get a panel
    each (receiver_lines), the horizontal axis in m along the line; without positions, or when the
    receivers form no few straight lines, the horizontal axis is the receiver index. source: the
    shot's position (the same columns as receiver_x), a star above the panels. units: of the data
    (default: a simulation's receiver data, in source-wavelet units, x m in 3D)."""
    data = np.asarray(data, dtype=float)
    clip = _clip(data, percentile)
    norm = _norm(-clip, clip)  # one for every panel and the colourbar
    pos = None if receiver_x is None else np.asarray(receiver_x, float)
    names = None if pos is None else _axis_names(1 if pos.ndim == 1 else pos.shape[1])
    lines = None if pos is None else receiver_lines(pos)
    if units is None:
        units = {"zx": "source-wavelet units", "zyx": "source-wavelet units x m"}.get(names, "source-wavelet units; x m in 3D")
    panels = lines or [None]
    fig = _figure(min(14.0, 4.0 + 4.0 * len(panels)), 6.0)
    axes = list(fig.subplots(1, len(panels), sharey=True, squeeze=False)[0])
    src = None if source is None else np.atleast_1d(np.asarray(source, float))
    for i, (ax, line) in enumerate(zip(axes, panels)):
        im, span, k = _gather_panel(ax, data if line is None else data[line["index"]], dt, line, norm)
        if line is not None:
            where = format_position(list(line["fixed"].values()), "".join(line["fixed"])) if line["fixed"] else f"line {i + 1}"
            ax.set_title(f"{len(line['index'])} receivers at {where}" if line["fixed"] else where, fontsize=9)
            if src is not None and len(src) == len(names):
                s = src[names.index(line["axis"])]
                if span[0] <= s <= span[1]:
                    ax.plot([s / k], [0.0], marker="*", ms=13, color="gold", mec="k", clip_on=False, zorder=5,
                            label="source" if i == 0 else None)  # fmt: skip
        ax.tick_params(labelsize=8)
    axes[0].set_ylabel("time (s)")
    fig.colorbar(im, ax=axes, label=f"{quantity} ({units})\nclipped at ±{clip:.3g}, the {percentile:g}th percentile of |{quantity}|",
                 fraction=0.05 if len(axes) > 1 else 0.15)  # fmt: skip
    fig.suptitle(title or "shot gather", fontsize=11)
    return save_figure(fig, path)


def plot_snapshots(path, snapshots, times, spacing: float, origin, sources=None,
                   max_panels: int = 12, title: str = "") -> pathlib.Path:
    """A grid of wavefield snapshots of one shot: snapshots (n_snap, nz, [ny,] nx) at ``times``
    (s) on the grid of ``spacing`` m with node 0 at world ``origin``; at most ``max_panels``
    evenly chosen frames, each divided by its own 99.5th percentile of |u| (given in its title) and
    clipped at +-1, one colourbar for all (seismic colormap). 3D: the x-z slice through the first
    source. sources (n, ndim) world m are drawn as stars."""
    snaps = np.asarray(snapshots)
    times = np.asarray(times, float)
    n = len(snaps)
    ndim = snaps.ndim - 1
    src = None if sources is None else np.asarray(sources, float).reshape(-1, ndim)
    y0 = src[0, 1] if (ndim == 3 and src is not None and len(src)) else None
    pick = np.unique(np.linspace(0, n - 1, min(n, max_panels)).round().astype(int)) if n else []
    norm = _norm(-1.0, 1.0)  # one for every frame and the colourbar
    cols = int(min(4, max(len(pick), 1)))
    rows = int(np.ceil(len(pick) / cols)) if len(pick) else 1
    frame0, _ = xz_slice(snaps[0], origin, spacing, y0) if n else (np.zeros((2, 2)), None)
    nz, nx = frame0.shape
    k, unit = _scale(max(nx, nz) * spacing)
    oz, ox = origin[0], origin[-1]
    extent = (ox / k, (ox + (nx - 1) * spacing) / k, (oz + (nz - 1) * spacing) / k, oz / k)
    panel_w = 3.2
    fig = _figure(panel_w * cols, rows * float(np.clip(panel_w * nz / nx, 1.2, 4.0)) + 0.8)
    for i, f in enumerate(pick):
        ax = fig.add_subplot(rows, cols, i + 1)
        frame, _ = xz_slice(snaps[f], origin, spacing, y0)
        c = _clip(frame, 99.5)
        im = ax.imshow(frame / c, extent=extent, cmap="seismic", norm=norm, aspect="equal",
                       interpolation="bilinear")
        if src is not None and len(src):
            ax.scatter(src[:1, -1] / k, src[:1, 0] / k, marker="*", s=40, c="gold",
                       edgecolors="black", linewidths=0.4)
            ax.set_xlim(extent[0], extent[1])
            ax.set_ylim(extent[2], extent[3])
        ax.set_title(f"t = {times[f]:.3g} s, clip {c:.2g}", fontsize=9)
        ax.tick_params(labelsize=7)
        if i % cols == 0:
            ax.set_ylabel(f"z ({unit})", fontsize=8)
        if i >= len(pick) - cols:
            ax.set_xlabel(f"x ({unit})", fontsize=8)
    if len(pick):
        fig.colorbar(im, ax=fig.axes, label="u / clip of its frame\n(clip: the 99.5th percentile of |u|, in each title)",
                     shrink=0.8, fraction=0.04)  # fmt: skip
    fig.suptitle(title or "wavefield snapshots")
    return save_figure(fig, path)


def plot_station_traces(path, observed, synthetic, dt: float, names, t0: float = 0.0, title: str = "",
                        components=None) -> pathlib.Path:
    """Observed (black) against synthetic (red) traces (n_traces, nt), one row per trace, each
    normalised by its observed peak; time axis t0 + k dt (s). components (n_traces,) e.g. "vz", "vx":
    one column per component (rows in trace order within each)."""
    obs, syn = np.asarray(observed, float), np.asarray(synthetic, float)
    groups = {None: list(range(len(obs)))} if components is None else {}
    for i, c in enumerate(components or ()):
        groups.setdefault(c, []).append(i)
    n = max(len(g) for g in groups.values())
    t = t0 + dt * np.arange(obs.shape[1])
    fig = _figure(9.0 if components is None else 5.0 * len(groups), 1.0 + 0.45 * n)
    for col, (comp, rows) in enumerate(groups.items()):
        ax = fig.add_subplot(1, len(groups), col + 1)
        for j, i in enumerate(rows):
            norm = 0.45 / (np.abs(obs[i]).max() or 1.0)
            ax.plot(t, j + norm * obs[i], color="k", lw=0.8, label="observed" if j == 0 else None)
            ax.plot(t, j + norm * syn[i], color="tab:red", lw=0.8, label="synthetic" if j == 0 else None)
        ax.set_yticks(range(len(rows)), [str(names[i]) for i in rows], fontsize=7)
        ax.set_ylim(len(rows) - 0.4, -0.6)
        ax.set_xlabel("time after the record start (s)")
        ax.legend(loc="upper right", fontsize=8)
        ax.set_title(f"{comp}: observed and synthetic (each scaled by its observed peak)" if comp else
                     (title or "observed and synthetic traces (each scaled by its observed peak)"), **({"fontsize": 9} if comp else {}))  # fmt: skip
    return save_figure(fig, path)


def _ellipse_xy(cov_zx, center_zx, k: float, n: int = 100):
    """Points (x, z) of the ellipse d^T C^-1 d = k^2 of a (z, x) covariance about center."""
    w, v = np.linalg.eigh(np.asarray(cov_zx, float))
    a = np.linspace(0, 2 * np.pi, n)
    pts = (v @ (k * np.sqrt(np.maximum(w, 0))[:, None] * np.stack([np.cos(a), np.sin(a)]))).T + np.asarray(center_zx)
    return pts[:, 1], pts[:, 0]


#: an ellipse narrower than this fraction of its panel gets a zoomed inset
INSET_BELOW = 0.15


def _ellipse_inset(ax, ex, ez, pos, truth=None, color="tab:cyan"):
    """A zoomed inset in the upper right of ax on the ellipse (ex, ez) (world m) about pos (z, x): axes in m from
    the event, equal scales, the zoomed square marked on ax and joined to the inset; returns the inset axes."""
    from matplotlib.patches import Rectangle
    from matplotlib.ticker import MaxNLocator

    half = 1.3 * max(float(np.ptp(ex)), float(np.ptp(ez)), 1e-9) / 2
    # a backdrop for the inset's labels, clear of the map's centre (the event)
    ax.add_patch(Rectangle((0.53, 0.53), 0.47, 0.47, transform=ax.transAxes, fc="white", ec="none", alpha=0.9, zorder=4))
    size = 0.36
    ins = ax.inset_axes([0.625, 0.625, size, size])
    ins.plot(ex - pos[1], ez - pos[0], color=color, lw=1.5)
    ins.plot(0.0, 0.0, "*", color=color, ms=10, mec="k")
    if truth is not None and max(abs(truth[-1] - pos[1]), abs(truth[0] - pos[0])) < half:
        ins.plot(truth[-1] - pos[1], truth[0] - pos[0], "+", color="tab:green", ms=10, mew=2)
    ins.set_xlim(-half, half)
    ins.set_ylim(half, -half)
    ins.set_aspect("equal")
    for axis in (ins.xaxis, ins.yaxis):
        axis.set_major_locator(MaxNLocator(4, symmetric=True))
    ins.tick_params(labelsize=6, pad=1, length=2)
    ins.set_xlabel("x - x_event (m)", fontsize=6, labelpad=1)
    ins.set_ylabel("z - z_event (m)", fontsize=6, labelpad=1)
    ins.grid(True, alpha=0.3)
    x0, x1 = ax.get_xlim()
    ins.set_title(f"zoom x{size * abs(x1 - x0) / (2 * half):.3g}, to scale", fontsize=7, pad=2)
    ax.indicate_inset((pos[1] - half, pos[0] - half, 2 * half, 2 * half), inset_ax=ins, edgecolor="k", alpha=0.6)
    return ins


def plot_location(path, model, stations, result_zx, cov_zx, k: float, misfit_map: dict, candidates=(), truth_zx=None,
                  stack=None, title: str = "", confidence: float = 0.68) -> pathlib.Path:  # fmt: skip
    """Two panels: the model's (z, x) section (a slice through the event in 3D) with the stations,
    the back-projection stack (contours), the start candidates, the located event with its
    confidence ellipse (k: the ellipse scale for its confidence, adseismic.quakeml.confidence_scale)
    and the outline of the misfit map; and the waveform misfit over positions near the event
    (misfit_map: z, x, misfit = 1/2 sum((synthetic - observed) / noise std)^2) with a colourbar and
    the same ellipse, drawn to scale, with a zoomed inset when it is smaller than INSET_BELOW of the
    map. Positions in world metres, (z, x)."""
    from matplotlib.patches import Rectangle

    vals, _ = xz_slice(model.values, model.origin, model.spacing[0], y=None if model.ndim == 2 else result_zx[1])
    (z0, z1), (x0, x1) = model.extent[0], model.extent[-1]
    kd, unit = _scale(max(z1 - z0, x1 - x0))
    pos = np.asarray(result_zx, float)[[0, -1]]
    ex, ez = _ellipse_xy(cov_zx, pos, k)
    fig = _figure(13.0, 5.5)
    ax, bx = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    im = ax.imshow(vals, extent=(x0 / kd, x1 / kd, z1 / kd, z0 / kd), cmap="viridis", aspect="equal")
    fig.colorbar(im, ax=ax, label="velocity (m/s)", shrink=0.8)
    if stack is not None:
        axes, s = stack["axes"], np.asarray(stack["stack"])
        if s.ndim == 3:
            s = s.max(axis=1)
        ax.contour(np.asarray(axes[-1]) / kd, np.asarray(axes[0]) / kd, s, levels=6, colors="w", linewidths=0.6, alpha=0.8)
    st = np.asarray(stations, float)
    ax.plot(st[:, -1] / kd, st[:, 0] / kd, "v", color="tab:orange", ms=7, mec="k", label="stations")
    for i, c in enumerate(candidates):
        ax.plot(c["position"][-1] / kd, c["position"][0] / kd, "s", mfc="none", mec="w", ms=7, label="start(s)" if i == 0 else None)
    ax.plot(pos[1] / kd, pos[0] / kd, "*", color="tab:red", ms=14, mec="k", label="located")
    ax.plot(ex / kd, ez / kd, color="tab:red", lw=1.2)
    if truth_zx is not None:
        ax.plot(truth_zx[-1] / kd, truth_zx[0] / kd, "+", color="w", ms=12, mew=2, label="truth")
    m = misfit_map
    mx, mz, mis = np.asarray(m["x"], float), np.asarray(m["z"], float), np.asarray(m["misfit"], float)
    ax.add_patch(Rectangle((mx.min() / kd, mz.min() / kd), np.ptp(mx) / kd, np.ptp(mz) / kd, fill=False, ec="w", lw=1.0,
                           ls="--", label="misfit map (right)"))  # fmt: skip
    ax.set_xlabel(f"x ({unit})")
    ax.set_ylabel(f"z ({unit})")
    ax.legend(loc="lower left", fontsize=8)
    ax.set_title("model, stations, back-projection stack, location", fontsize=10)
    lo = np.nanmin(mis)
    lev = lo + np.array([0.5, 1, 2, 4, 8, 16, 32, 64]) * max(k, 1.0) ** 2
    cf = bx.contourf(mx, mz, np.log10(mis - lo + 1.0), levels=20, cmap="magma_r")
    fig.colorbar(cf, ax=bx, label="log10(1 + misfit - its minimum)\nmisfit = 1/2 sum((synthetic - observed) / noise std)^2", shrink=0.8)
    cs = bx.contour(mx, mz, mis, levels=lev, colors="k", linewidths=0.5)
    bx.clabel(cs, fontsize=6, fmt=lambda v: f"+{v - lo:.3g}")
    bx.plot(ex, ez, color="tab:cyan", lw=1.5, label=f"{100 * confidence:.0f}% confidence ellipse")
    bx.plot(pos[1], pos[0], "*", color="tab:cyan", ms=12, mec="k")
    if truth_zx is not None:
        bx.plot(truth_zx[-1], truth_zx[0], "+", color="tab:green", ms=12, mew=2, label="truth")
    bx.set_xlim(mx.min(), mx.max())
    bx.set_ylim(mz.max(), mz.min())
    bx.set_aspect("equal")
    bx.set_xlabel("x (m)")
    bx.set_ylabel("z (m)")
    bx.legend(loc="lower left", fontsize=8)
    small = max(np.ptp(ex), np.ptp(ez)) < INSET_BELOW * max(np.ptp(mx), np.ptp(mz))
    if small:
        _ellipse_inset(bx, ex, ez, pos, truth_zx)
    bx.set_title("waveform misfit near the event" + (" (inset: the ellipse to scale, zoomed)" if small else "")
                 + "\n(contours: increase above the minimum)", fontsize=10)  # fmt: skip
    fig.suptitle(title)
    return save_figure(fig, path)
