"""The physics family in ``adseismic bench --physics`` (issue 26 item 8): variable-density acoustic, visco-acoustic
and VTI (2D) and isotropic elastic (3D), ours beside Deepwave 0.1.0's counterparts (deepwave.acoustic,
deepwave.viscoacoustic, deepwave.acoustic_vti, deepwave.elastic) on the same grid, steps, order, PML width,
shot, source and receivers.

Models (z depth, axis 0; two layers, the interface INTERFACE m deep (half the depth on grids too shallow for it), so
that its reflection reaches the receivers within the GPU scenes' 1 s):

    acoustic_vd    vp 1500 / 2000 m/s, rho 1800 / 2300 kg/m^3; explosive source, pressure recorded
    viscoacoustic  as acoustic_vd, Q 100 / 50 (3 mechanisms, flat over [f/3, 2.5 f], vp the phase velocity at f =
                   the Ricker's peak); explosive source, pressure recorded
    vti            as acoustic_vd, epsilon 0.2, delta 0.1 everywhere; explosive source, pressure recorded
    elastic3d      homogeneous vp 2000 m/s, vs vp / 1.8, rho 2200 kg/m^3; vertical point force, vz recorded

Geometry: one shot, the source 20 m deep at the centre node (x = (nx // 2) dx; y = (ny // 2) dx in 3D), receivers
20 m deep on every second node along x (x = 2 k dx); in 3D elastic both 25 m deep, on the row of vz nodes (vz lives
at (i + 1/2) dx in z in both tools, and Deepwave's integer z index i of a vz location names that node). Every location
is on a node of the recorded (or forced) field, so Deepwave's integer cell locations name the same points as our
metres and neither tool interpolates.

Deepwave's conventions, aligned here (a sample n of S is ours, of s Deepwave's; dx the cell, K = rho vp^2):
- explosive source: ours adds (S_{n+1} - S_n) / dx^2 to p (to -sH, -sV in VTI) in the step n -> n + 1; Deepwave's
  pressure rate s_n adds dt s_n there (viscoacoustic, acoustic_vti: s_n = (S_{n+1} - S_n) / (dt dx^2)) and its
  volume rate dt K s_n (acoustic: the same divided by K at the source node);
- force: ours adds dt b f_n / dx^3 to vz; Deepwave's force density dt b s_n (s_n = f_n / dx^3, N/m^3);
- visco-acoustic: Deepwave's v is the relaxed (zero-frequency) speed, ours the phase velocity at f: Deepwave gets
  the relaxed speed of our mechanisms (same Q, band and count of mechanisms; its GSLS fit of the weights differs);
- VTI: c11, c13, c33 from deepwave.anisotropy.thomsen_to_cij with vs = 0 (c13 = c33 sqrt(1 + 2 delta), as ours);
- receivers: pressure sample n at t = n dt, velocity at (n - 1/2) dt in both.
What still differs: the density at velocity nodes next to the interface (Deepwave: the arithmetic mean of rho; ours:
of 1/rho), the Q model's weights (Deepwave's GSLS fit), the CPML profiles (each tool's own). Measured on a CPU
(benchmarks/physics_vs_deepwave.py, 160^2 cells, 700 steps, float32): relative L2 difference 1.1e-3 (acoustic_vd),
1.3e-3 (vti), 4e-7 and 7e-7 with a uniform density (the interface's averaging is all of it), 2.5e-3 (viscoacoustic,
scale 0.9991: the Q fits); elastic3d 1.9e-7 (40^3, 150 steps).

Gradients: ours with respect to every model of the physics (acoustic_vd vp, rho; viscoacoustic vp, q, rho; vti vp,
epsilon, delta, rho; elastic3d vp, vs, rho), L2 misfit of the recorded component; Deepwave's with respect to the
same user-facing models (through thomsen_to_cij, vpvsrho_to_lambmubuoyancy) by backward() of the summed squared
recorded component. Deepwave's 3D elastic gradient runs with checkpoint_segments = ceil(sqrt(nt)) (its full
wavefield history of a 200^3 run, ~9 stored fields a step, would not fit a GPU), as ours checkpoints.
"""

from __future__ import annotations

import math
import traceback
from types import SimpleNamespace

import numpy as np

KINDS = ("acoustic_vd", "viscoacoustic", "vti", "elastic3d")
COMPONENT = {"acoustic_vd": "pressure", "viscoacoustic": "pressure", "vti": "pressure", "elastic3d": "vz"}
DEEPWAVE = {"acoustic_vd": "acoustic", "viscoacoustic": "viscoacoustic", "vti": "acoustic_vti", "elastic3d": "elastic"}
MECHANISMS = 3
EPSILON, DELTA = 0.2, 0.1
SOURCE_DEPTH = 20.0  # m
INTERFACE = 300.0  # m
STAGGER = {"elastic3d": 0.5}  # z offset (cells) of the recorded and forced component's nodes (vz); 0 for pressure


def q_band(f_peak: float) -> tuple:
    """The band (Hz) over which Q is flat: our default for a Ricker of peak f_peak (solve.viscoacoustic)."""
    return (f_peak / 3.0, 2.5 * f_peak)


def scene(kind: str, shape: tuple, dx: float) -> tuple:
    """(model {name: array of shape}, sources (1, 1, ndim) m, receivers (1, nx // 2, ndim) m) of a physics scene
    (module docstring); shape (nz, [ny,] nx) cells of dx m."""
    if kind not in KINDS:
        raise ValueError(f"physics kind {kind!r} is not one of {KINDS}")
    two = np.ones(shape)
    two[min(round(INTERFACE / dx), shape[0] // 2):] = 2.0  # 1 above, 2 below
    layered = {"vp": np.where(two == 1, 1500.0, 2000.0), "rho": np.where(two == 1, 1800.0, 2300.0)}
    model = {
        "acoustic_vd": lambda: layered,
        "viscoacoustic": lambda: {"vp": layered["vp"], "q": np.where(two == 1, 100.0, 50.0), "rho": layered["rho"]},
        "vti": lambda: {"vp": layered["vp"], "epsilon": np.full(shape, EPSILON), "delta": np.full(shape, DELTA),
                        "rho": layered["rho"]},  # fmt: skip
        "elastic3d": lambda: {"vp": np.full(shape, 2000.0), "vs": np.full(shape, 2000.0 / 1.8), "rho": np.full(shape, 2200.0)},
    }[kind]()
    nx, depth = shape[-1], SOURCE_DEPTH + STAGGER.get(kind, 0.0) * dx
    mid = [(shape[1] // 2) * dx] if len(shape) == 3 else []
    src = np.array([[[depth, *mid, (nx // 2) * dx]]])
    rec = np.array([[[depth, *mid, 2 * k * dx] for k in range(nx // 2)]])
    return model, src, rec


def run_ours(kind, mode, model, dx, dt, amplitudes, sources, receivers, *, device, order, pml_width, f_peak,
             memory_budget=None, observed=None, segment_length=None):  # fmt: skip
    """Our solver of `kind` on the scene: forward -> an object with receiver_amplitudes (the recorded COMPONENT,
    (1, n_rec, nt)); gradient -> the physics' gradient result (L2 misfit of COMPONENT against `observed`)."""
    comp = COMPONENT[kind]
    args = (dx, dt, amplitudes, sources, receivers)
    kw = dict(order=order, pml_width=pml_width, device=device)
    grad = {} if mode == "forward" else dict(observed={comp: observed}, components=(comp,), memory_budget=memory_budget,
                                             segment_length=segment_length)  # fmt: skip
    m = model
    if kind == "acoustic_vd":
        from adseismic.solve import acoustic_vd as api

        run = api.forward_acoustic_vd if mode == "forward" else api.gradient_acoustic_vd
        out = run(m["vp"], m["rho"], *args, **kw, **grad)
    elif kind == "viscoacoustic":
        from adseismic.solve import viscoacoustic as api

        run = api.forward_viscoacoustic if mode == "forward" else api.gradient_viscoacoustic
        out = run(m["vp"], m["q"], m["rho"], *args, q_band=q_band(f_peak), f_ref=f_peak, mechanisms=MECHANISMS, **kw, **grad)
    elif kind == "vti":
        from adseismic.solve import vti as api

        run = api.forward_vti if mode == "forward" else api.gradient_vti
        out = run(m["vp"], m["epsilon"], m["delta"], m["rho"], *args, **kw, **grad)
    else:
        from adseismic.solve import elastic3d as api

        run = api.forward_elastic3d if mode == "forward" else api.gradient_elastic3d
        out = run(m["vp"], m["vs"], m["rho"], *args, source_type="force", **kw, **grad)
    return SimpleNamespace(receiver_amplitudes=getattr(out, comp)) if mode == "forward" else out


def relaxed_velocity(vp, q, f_peak: float) -> np.ndarray:
    """The zero-frequency speed (m/s) of our visco-acoustic medium of phase velocity vp (m/s) at f_peak and quality
    factor q, with our mechanisms: Deepwave's `v` for the same medium."""
    from adseismic.kernels.viscoacoustic import fit_mechanisms
    from adseismic.solve.viscoacoustic import unrelaxed_velocity

    mech = fit_mechanisms(*q_band(f_peak), MECHANISMS)
    return unrelaxed_velocity(vp, q, mech, f_peak) / np.sqrt(1.0 + mech.y(q).sum(axis=-1))


def source_rate(amplitudes, dt: float, dx: float) -> np.ndarray:
    """(S_{n+1} - S_n) / (dt dx^2) (last sample 0): Deepwave's 2D pressure rate (Pa/s) of our explosive moment S."""
    amp = np.asarray(amplitudes, dtype=float)
    return np.diff(amp, axis=-1, append=amp[..., -1:]) / (dt * dx**2)


def deepwave_call(kind, grad: bool, model, dx, dt, amplitudes, sources, receivers, *, device, order, pml_width, f_peak):
    """A callable running Deepwave's counterpart of `kind` once and returning (receiver tensor,) of COMPONENT (1,
    n_rec, nt), with the user-facing models requiring grad when `grad`. A Deepwave error is raised again as a
    RuntimeError naming the Deepwave function and the line of Deepwave's source where it happened."""
    import deepwave
    import torch

    dev = torch.device(device)

    def tensor(x, requires_grad=False):
        return torch.tensor(np.asarray(x, dtype=float), dtype=torch.float32, device=dev, requires_grad=requires_grad)

    def cells(loc):  # every location is on a node of its field (scene): metres -> Deepwave's integer index of that node
        c = np.asarray(loc) / dx
        c[..., 0] -= STAGGER.get(kind, 0.0)
        return torch.tensor(np.rint(c).astype(np.int64), device=dev)

    src, rec = cells(sources), cells(receivers)
    common = dict(accuracy=order, pml_width=pml_width, pml_freq=f_peak)
    m = {k: tensor(v, grad) for k, v in model.items()}
    if kind == "acoustic_vd":
        i = tuple(int(j) for j in np.rint(np.asarray(sources)[0, 0] / dx).astype(int))
        k_src = float(model["rho"][i] * model["vp"][i] ** 2)
        amp = tensor(source_rate(amplitudes, dt, dx) / k_src)

        def call():
            return deepwave.acoustic(m["vp"], m["rho"], dx, dt, source_amplitudes_volume_rate=amp, source_locations_volume_rate=src,
                                     receiver_locations_p=rec, **common).receiver_amplitudes_p  # fmt: skip
    elif kind == "viscoacoustic":
        m["vp"] = tensor(relaxed_velocity(model["vp"], model["q"], f_peak), grad)
        amp = tensor(source_rate(amplitudes, dt, dx))

        def call():
            return deepwave.viscoacoustic(m["vp"], m["rho"], m["q"], dx, dt, source_amplitudes_pressure_rate=amp,
                                          source_locations_pressure_rate=src, receiver_locations_p=rec,
                                          q_n_mechanisms=MECHANISMS, q_band=q_band(f_peak), **common).receiver_amplitudes_p  # fmt: skip
    elif kind == "vti":
        amp, vs = tensor(source_rate(amplitudes, dt, dx)), torch.zeros_like(m["vp"]).detach()

        def call():
            c11, c13, c33, _, _, b = deepwave.anisotropy.thomsen_to_cij(m["vp"], vs, m["rho"], m["epsilon"], m["delta"])
            out = deepwave.acoustic_vti(c11, c13, c33, b, dx, dt, source_amplitudes_pressure_rate=amp,
                                        source_locations_pressure_rate=src, receiver_locations_p=rec, **common)  # fmt: skip
            return out.receiver_amplitudes_p
    else:
        amp = tensor(np.asarray(amplitudes, dtype=float) / dx**3)  # force density (N/m^3) of our point force (N)
        segments = math.ceil(math.sqrt(np.shape(amplitudes)[-1])) if grad else None

        def call():
            lamb, mu, b = deepwave.vpvsrho_to_lambmubuoyancy(m["vp"], m["vs"], m["rho"])
            return deepwave.elastic(lamb, mu, b, dx, dt, source_amplitudes_z=amp, source_locations_z=src, receiver_locations_z=rec,
                                    checkpoint_segments=segments, **common).receiver_amplitudes_z  # fmt: skip

    def named():
        try:
            return (call(),)
        except Exception as exc:
            where = next((f"{f.filename.rpartition('/')[2]}:{f.lineno}" for f in reversed(traceback.extract_tb(exc.__traceback__))
                          if "deepwave" in f.filename), "?")  # fmt: skip
            text = (str(exc).strip().splitlines() or [""])[0]
            raise RuntimeError(f"deepwave.{DEEPWAVE[kind]} ({'gradient' if grad else 'forward'}) at {where}: "
                               f"{type(exc).__name__}: {text}") from exc  # fmt: skip

    return named


def difference(ours, reference) -> tuple:
    """(relative L2 difference ||ours - reference|| / ||ours||, least-squares scale a of ours ~ a reference) of two
    receiver arrays of one shape; (None, None) if ours is all zero. A scale far from 1 flags a convention not aligned
    (units, sign); the difference then measures the conventions, not the schemes. ours: NumPy or a Warp array on any device."""
    import warp as wp

    o, r = np.asarray(ours.numpy() if isinstance(ours, wp.array) else ours, dtype=float), np.asarray(reference, dtype=float)
    if o.shape != r.shape:
        raise ValueError(f"receiver data of shapes {o.shape} (ours) and {r.shape} (Deepwave) differ")
    norm = float(np.linalg.norm(o))
    if norm == 0.0:
        return None, None
    rr = float(np.vdot(r, r))
    return float(np.linalg.norm(o - r)) / norm, (float(np.vdot(o, r)) / rr if rr > 0 else None)
