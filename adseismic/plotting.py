"""PNG figures of a forward run: the model with the acquisition, shot gathers, snapshots.

Uses matplotlib's object API with the Agg canvas (no pyplot, no global backend switch, no
display needed). Every figure is written atomically: to ``<name>.png.part`` first, renamed into
place when complete. Coordinates are in world metres (shown in km when the section is wider than
2 km), axis order (z, [y,] x); 3D volumes are shown as the x-z slice through a given y.
"""
from __future__ import annotations

import pathlib

import numpy as np

from adseismic.data.atomic import atomic_write

__all__ = ["plot_model", "plot_gather", "plot_snapshots", "plot_misfit", "plot_station_traces", "plot_location", "save_figure", "xz_slice"]


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


def plot_misfit(path, rows, title: str = "") -> pathlib.Path:
    """Misfit (normalised by each band's start value) against iteration; rows: (band, iteration, misfit)."""
    fig = _figure(7.0, 4.5)
    ax = fig.add_subplot()
    for b in sorted({r[0] for r in rows}):
        it = [(i, j) for bb, i, j in rows if bb == b]
        ax.semilogy([i for i, _ in it], [j for _, j in it], "o-", ms=3, label=f"band {b}")
    ax.set_xlabel("iteration")
    ax.set_ylabel("misfit / misfit at the band's start")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    ax.set_title(title or "misfit")
    return save_figure(fig, path)


def _clip(a: np.ndarray, pct: float = 99.0) -> float:
    c = float(np.percentile(np.abs(a), pct)) if a.size else 0.0
    if c <= 0:
        c = float(np.abs(a).max()) if a.size else 0.0
    return c if c > 0 else 1.0


def plot_gather(path, data, dt: float, receiver_x=None, title: str = "",
                percentile: float = 99.0) -> pathlib.Path:
    """One shot gather (n_receivers, nt): time (s, down) against receiver x (world m), seismic
    colormap clipped symmetrically at the ``percentile`` of |data|. If receiver x is not evenly
    spaced and increasing (e.g. a vertical spread), the horizontal axis is the receiver index."""
    data = np.asarray(data, dtype=float)
    n_rec, nt = data.shape
    clip = _clip(data, percentile)
    fig = _figure(8.0, 6.0)
    ax = fig.add_subplot()
    x = None if receiver_x is None else np.asarray(receiver_x, float)
    even = (x is not None and n_rec > 1 and np.all(np.diff(x) > 0)
            and np.allclose(np.diff(x), np.diff(x).mean(), rtol=1e-3))
    t_end = (nt - 1) * dt
    if even:
        k, unit = _scale(x[-1] - x[0])
        h = 0.5 * (x[1] - x[0])
        extent = ((x[0] - h) / k, (x[-1] + h) / k, t_end + 0.5 * dt, -0.5 * dt)
        ax.set_xlabel(f"receiver x ({unit})")
    else:
        extent = (-0.5, n_rec - 0.5, t_end + 0.5 * dt, -0.5 * dt)
        ax.set_xlabel("receiver index")
    im = ax.imshow(data.T, extent=extent, aspect="auto", cmap="seismic", vmin=-clip, vmax=clip,
                   interpolation="bilinear")
    fig.colorbar(im, ax=ax, label=f"amplitude (clipped at the {percentile:g}th percentile)")
    ax.set_ylabel("time (s)")
    ax.set_title(title or "shot gather")
    return save_figure(fig, path)


def plot_snapshots(path, snapshots, times, spacing: float, origin, sources=None,
                   max_panels: int = 12, title: str = "") -> pathlib.Path:
    """A grid of wavefield snapshots of one shot: snapshots (n_snap, nz, [ny,] nx) at ``times``
    (s) on the grid of ``spacing`` m with node 0 at world ``origin``; at most ``max_panels``
    evenly chosen frames, each clipped at its own 99.5th percentile of |u| (seismic colormap).
    3D: the x-z slice through the first source. sources (n, ndim) world m are drawn as stars."""
    snaps = np.asarray(snapshots)
    times = np.asarray(times, float)
    n = len(snaps)
    ndim = snaps.ndim - 1
    src = None if sources is None else np.asarray(sources, float).reshape(-1, ndim)
    y0 = src[0, 1] if (ndim == 3 and src is not None and len(src)) else None
    pick = np.unique(np.linspace(0, n - 1, min(n, max_panels)).round().astype(int)) if n else []
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
        ax.imshow(frame, extent=extent, cmap="seismic", vmin=-c, vmax=c, aspect="equal",
                  interpolation="bilinear")
        if src is not None and len(src):
            ax.scatter(src[:1, -1] / k, src[:1, 0] / k, marker="*", s=40, c="gold",
                       edgecolors="black", linewidths=0.4)
            ax.set_xlim(extent[0], extent[1])
            ax.set_ylim(extent[2], extent[3])
        ax.set_title(f"t = {times[f]:.3g} s", fontsize=9)
        ax.tick_params(labelsize=7)
        if i % cols == 0:
            ax.set_ylabel(f"z ({unit})", fontsize=8)
        if i >= len(pick) - cols:
            ax.set_xlabel(f"x ({unit})", fontsize=8)
    fig.suptitle(title or "wavefield snapshots")
    return save_figure(fig, path)


def plot_station_traces(path, observed, synthetic, dt: float, names, t0: float = 0.0, title: str = "") -> pathlib.Path:
    """Observed (black) against synthetic (red) traces (n_traces, nt), one row per trace, each
    normalised by its observed peak; time axis t0 + k dt (s)."""
    obs, syn = np.asarray(observed, float), np.asarray(synthetic, float)
    n, nt = obs.shape
    t = t0 + dt * np.arange(nt)
    fig = _figure(9.0, 1.0 + 0.45 * n)
    ax = fig.add_subplot()
    for i in range(n):
        norm = 0.45 / (np.abs(obs[i]).max() or 1.0)
        ax.plot(t, i + norm * obs[i], color="k", lw=0.8, label="observed" if i == 0 else None)
        ax.plot(t, i + norm * syn[i], color="tab:red", lw=0.8, label="synthetic" if i == 0 else None)
    ax.set_yticks(range(n), [str(s) for s in names], fontsize=7)
    ax.set_ylim(n - 0.4, -0.6)
    ax.set_xlabel("time after the record start (s)")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title(title or "observed and synthetic traces (each scaled by its observed peak)")
    return save_figure(fig, path)


def _ellipse_xy(cov_zx, center_zx, k: float, n: int = 100):
    """Points (x, z) of the ellipse d^T C^-1 d = k^2 of a (z, x) covariance about center."""
    w, v = np.linalg.eigh(np.asarray(cov_zx, float))
    a = np.linspace(0, 2 * np.pi, n)
    pts = (v @ (k * np.sqrt(np.maximum(w, 0))[:, None] * np.stack([np.cos(a), np.sin(a)]))).T + np.asarray(center_zx)
    return pts[:, 1], pts[:, 0]


def plot_location(path, model, stations, result_zx, cov_zx, k: float, misfit_map: dict, candidates=(), truth_zx=None,
                  stack=None, title: str = "") -> pathlib.Path:  # fmt: skip
    """Two panels: the model's (z, x) section (a slice through the event in 3D) with the stations,
    the back-projection stack (contours), the start candidates and the located event with its
    confidence ellipse (k: the ellipse scale for its confidence, adseismic.quakeml.confidence_scale);
    and the waveform misfit over positions near the event (misfit_map: z, x, misfit) with the same
    ellipse. Positions in world metres, (z, x)."""
    vals, _ = xz_slice(model.values, model.origin, model.spacing[0], y=None if model.ndim == 2 else result_zx[1])
    (z0, z1), (x0, x1) = model.extent[0], model.extent[-1]
    kd, unit = _scale(max(z1 - z0, x1 - x0))
    pos = np.asarray(result_zx, float)[[0, -1]]
    ex, ez = _ellipse_xy(cov_zx, pos, k)
    fig = _figure(13.0, 5.0)
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
    ax.set_xlabel(f"x ({unit})")
    ax.set_ylabel(f"z ({unit})")
    ax.legend(loc="lower left", fontsize=8)
    ax.set_title("model, stations, back-projection stack, location")
    m = misfit_map
    mis = np.asarray(m["misfit"], float)
    lev = np.nanmin(mis) + np.array([0.5, 1, 2, 4, 8, 16, 32, 64]) * max(k, 1.0) ** 2
    bx.contourf(m["x"], m["z"], np.log10(mis - np.nanmin(mis) + 1.0), levels=20, cmap="magma_r")
    cs = bx.contour(m["x"], m["z"], mis, levels=lev, colors="k", linewidths=0.5)
    bx.clabel(cs, fontsize=6, fmt=lambda v: f"+{v - np.nanmin(mis):.3g}")
    bx.plot(ex, ez, color="tab:cyan", lw=1.5, label="confidence ellipse")
    bx.plot(pos[1], pos[0], "*", color="tab:cyan", ms=12, mec="k")
    if truth_zx is not None:
        bx.plot(truth_zx[-1], truth_zx[0], "+", color="tab:green", ms=12, mew=2, label="truth")
    bx.invert_yaxis()
    bx.set_aspect("equal")
    bx.set_xlabel("x (m)")
    bx.set_ylabel("z (m)")
    bx.legend(loc="lower left", fontsize=8)
    bx.set_title("waveform misfit near the event\n(contours: increase above the minimum)")
    fig.suptitle(title)
    return save_figure(fig, path)
