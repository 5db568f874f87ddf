"""HDF5 output of a forward run, written atomically, and reading it back.

Layout of the file written by :func:`write_forward` (lengths in m, times in s, velocities in m/s;
array axis order (z, [y,] x) as everywhere in adseismic):

* ``receiver_data`` (n_shots, n_receivers, nt): the wavefield u sampled at the receivers at
  ``time``; attrs ``units``, ``axes`` = "shot,receiver,time".
* ``source_wavelet`` (nt,): the source time function s(t) injected at every shot.
* ``source_coordinates`` (n_shots, ndim), ``receiver_coordinates`` (n_receivers, ndim): world
  metres (the frame of the config's model), attrs ``units`` = "m", ``axes`` = "z,x" or "z,y,x".
* ``time`` (nt,): t = n dt, s.
* ``velocity`` (the simulation-grid model): m/s, attrs ``spacing`` (m), ``origin`` (world m of
  node 0), ``axes``.
* optional ``snapshots`` (n_snapshots, n_shots, *grid) with ``snapshot_times`` (n_snapshots,) s.
* physics elastic: one dataset per recorded quantity, named by it (``vx``, ``vz`` in m/s, ``pressure`` in Pa,
  ``das`` strain rate in 1/s), each (n_shots, n_receivers, nt) with attrs ``units`` and ``sample_times``; root attr
  ``components`` lists them, and ``receiver_data`` is an HDF5 soft link to the first.
* root attrs: whatever the caller passes (the CLI stores dx, dt, nt, order, precision, device,
  free_surface, pml_width, pml_reflection, adseismic_version, created_utc, config_yaml, plan).

Nothing is half-written: the file is written as ``<name>.h5.part`` in the same directory and
renamed into place with ``os.replace`` only when complete; on any error the part file is removed
(:func:`adseismic.data.atomic.write_h5_atomic`).
"""
from __future__ import annotations

import pathlib
from dataclasses import dataclass, field

import numpy as np

from adseismic.data.atomic import write_h5_atomic
from adseismic.data.traces import TraceError

__all__ = ["write_forward", "read_forward", "ForwardData", "AXES"]

AXES = {2: "z,x", 3: "z,y,x"}


@dataclass
class ForwardData:
    """The contents of a forward-run HDF5 file (see the module docstring for units and shapes)."""

    receiver_data: np.ndarray
    source_wavelet: np.ndarray
    source_coordinates: np.ndarray
    receiver_coordinates: np.ndarray
    time: np.ndarray
    velocity: np.ndarray
    spacing: tuple
    origin: tuple
    attrs: dict = field(default_factory=dict)
    snapshots: np.ndarray | None = None
    snapshot_times: np.ndarray | None = None
    components: dict = field(default_factory=dict)  # physics elastic: {name: (n_shots, n_receivers, nt)}

    @property
    def dt(self) -> float:
        return float(self.attrs.get("dt", self.time[1] - self.time[0] if len(self.time) > 1 else 0))

    @property
    def ndim(self) -> int:
        return self.velocity.ndim


def _attr(value):
    """HDF5-storable form of an attribute value (None -> "none", tuples -> arrays, bool kept)."""
    if value is None:
        return "none"
    if isinstance(value, (bool, np.bool_)):
        return np.bool_(value)
    if isinstance(value, (list, tuple)):
        return np.asarray(value)
    if isinstance(value, pathlib.Path):
        return str(value)
    return value


def write_forward(path, *, receiver_data, source_wavelet, dt, source_coordinates,
                  receiver_coordinates, velocity, spacing, origin, attrs=None,
                  snapshots=None, snapshot_times=None, units="model units (u)", components=None) -> pathlib.Path:
    """Write a forward run to the HDF5 file ``path`` atomically and return ``path``.

    receiver_data (n_shots, n_receivers, nt); source_wavelet (nt,); dt (s);
    source_coordinates (n_shots, ndim) and receiver_coordinates (n_receivers, ndim) in world
    metres, axis order (z, [y,] x); velocity (nz, [ny,] nx) m/s on the simulation grid with
    ``spacing`` (m, scalar) and ``origin`` (world m of node 0); attrs: extra root attributes;
    snapshots (n_snapshots, n_shots, *grid) with snapshot_times (s), both or neither.
    components (physics elastic, instead of receiver_data = None): {name: (data (n_shots, n_receivers, nt), units,
    sample times)}, written as one dataset each; receiver_data becomes a link to the first.
    Shapes are checked before anything is written (ValueError).
    """
    if components:
        shapes = {np.shape(c[0]) for c in components.values()}
        if receiver_data is not None or len(shapes) != 1:
            raise ValueError(f"components: {len(shapes)} shapes {sorted(shapes)} (one expected) or receiver_data given too")
        receiver_data = next(iter(components.values()))[0]

    path = pathlib.Path(path)
    data = np.asarray(receiver_data)
    wavelet = np.asarray(source_wavelet, dtype=np.float64)
    src = np.asarray(source_coordinates, dtype=np.float64)
    rec = np.asarray(receiver_coordinates, dtype=np.float64)
    vel = np.asarray(velocity)
    ndim = vel.ndim
    if data.ndim != 3:
        raise ValueError(f"receiver_data: shape {data.shape} is not (n_shots, n_receivers, nt)")
    n_shots, n_rec, nt = data.shape
    if wavelet.shape != (nt,):
        raise ValueError(f"source_wavelet: shape {wavelet.shape} is not (nt,) = ({nt},)")
    if src.shape != (n_shots, ndim):
        raise ValueError(f"source_coordinates: shape {src.shape} is not (n_shots, ndim) = "
                         f"({n_shots}, {ndim})")
    if rec.shape != (n_rec, ndim):
        raise ValueError(f"receiver_coordinates: shape {rec.shape} is not (n_receivers, ndim) = "
                         f"({n_rec}, {ndim})")
    if (snapshots is None) != (snapshot_times is None):
        raise ValueError("snapshots and snapshot_times: give both or neither")
    if snapshots is not None:
        snapshots = np.asarray(snapshots)
        snapshot_times = np.asarray(snapshot_times, dtype=np.float64)
        if snapshots.shape[:2] != (len(snapshot_times), n_shots) or snapshots.shape[2:] != vel.shape:
            raise ValueError(f"snapshots: shape {snapshots.shape} is not (n_snapshots, n_shots, "
                             f"*grid) = ({len(snapshot_times)}, {n_shots}, "
                             f"{', '.join(map(str, vel.shape))})")

    path.parent.mkdir(parents=True, exist_ok=True)
    axes = AXES[ndim]

    def fill(f):
        import h5py

        if components:
            for name, (values, unit, times) in components.items():
                d = f.create_dataset(name, data=np.asarray(values))
                d.attrs.update(units=unit, axes="shot,receiver,time", sample_times=times)
            f["receiver_data"] = h5py.SoftLink(f"/{next(iter(components))}")
            f.attrs["components"] = list(components)
        else:
            d = f.create_dataset("receiver_data", data=data)
            d.attrs.update(units=units, axes="shot,receiver,time",
                           description="wavefield u at the receivers, sampled at `time`")
        d = f.create_dataset("source_wavelet", data=wavelet)
        d.attrs.update(axes="time", description="source time function s(t), every shot")
        for name, arr in (("source_coordinates", src), ("receiver_coordinates", rec)):
            d = f.create_dataset(name, data=arr)
            d.attrs.update(units="m", axes=axes, frame="world (the config's model frame)")
        d = f.create_dataset("time", data=np.arange(nt) * float(dt))
        d.attrs.update(units="s")
        d = f.create_dataset("velocity", data=vel)
        d.attrs.update(units="m/s", axes=axes, spacing=float(spacing),
                       origin=np.asarray(origin, dtype=np.float64))
        if snapshots is not None:
            chunks = (1, 1, *vel.shape) if snapshots.size else None
            d = f.create_dataset("snapshots", data=snapshots, chunks=chunks)
            d.attrs.update(units=units, axes="snapshot,shot," + axes)
            d = f.create_dataset("snapshot_times", data=snapshot_times)
            d.attrs.update(units="s")
        f.attrs["dt"] = float(dt)
        f.attrs["nt"] = int(nt)
        for k, v in (attrs or {}).items():
            f.attrs[k] = _attr(v)

    write_h5_atomic(path, fill)
    return path


def read_forward(path) -> ForwardData:
    """Read a file written by :func:`write_forward` back into a :class:`ForwardData`."""
    import h5py

    path = pathlib.Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file; run 'adseismic forward' first")
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise TraceError(f"{path} ({path.stat().st_size:,} bytes) is not a readable HDF5 file ({e}); it may be empty, "
                         f"truncated or another format: give a data.h5 written by 'adseismic forward'") from None
    try:
        return _read_forward(f, path)
    except (KeyError, OSError, RuntimeError, TypeError, ValueError) as e:
        if isinstance(e, TraceError):
            raise
        raise TraceError(f"{path}: not a complete 'adseismic forward' data file ({type(e).__name__}: {e}); it needs "
                         f"receiver_data, source_wavelet, source_coordinates, receiver_coordinates, time and velocity "
                         f"(with attrs spacing, origin): write it with 'adseismic forward' or "
                         f"adseismic.data.store.write_forward") from None
    finally:
        f.close()


def _read_forward(f, path) -> ForwardData:
    """The ForwardData of the open HDF5 file f (KeyError etc. when a dataset or attribute is missing)."""
    attrs = {}
    for k, v in f.attrs.items():
        if isinstance(v, bytes):
            v = v.decode()
        elif isinstance(v, np.generic):
            v = v.item()
        attrs[k] = v
    vel = f["velocity"]
    has_snap = "snapshots" in f
    return ForwardData(
        receiver_data=f["receiver_data"][()],
        source_wavelet=f["source_wavelet"][()],
        source_coordinates=f["source_coordinates"][()],
        receiver_coordinates=f["receiver_coordinates"][()],
        time=f["time"][()],
        velocity=vel[()],
        spacing=float(vel.attrs["spacing"]),
        origin=tuple(float(x) for x in vel.attrs["origin"]),
        attrs=attrs,
        snapshots=f["snapshots"][()] if has_snap else None,
        snapshot_times=f["snapshot_times"][()] if has_snap else None,
        components={n: f[n][()] for n in (c.decode() if isinstance(c, bytes) else str(c) for c in f.attrs.get("components", []))},
    )
