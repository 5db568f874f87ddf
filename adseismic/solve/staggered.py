"""What the staggered physics (vti, viscoacoustic, acoustic_vd, elastic3d; 2D elastic for COMPONENTS) share: the
receivers' components, the verbs of the shared time loop (solve/loop.py) that do not depend on the physics, and the
taped checkpointed gradient with its misfit."""

import math

import numpy as np
import warp as wp

from adseismic.accel.reductions import l2_residual_kernel
from adseismic.runs import progress_bar
from adseismic.solve import common, sweep
from adseismic.solve.misfits import misfit as named_misfit

COMPONENTS = ("vx", "vz", "pressure")  # the order of the data arrays new_data gives and the launch helpers' record fills


class StaggeredSetup:
    """Mixin of the loop verbs common to the staggered physics' Setups. A Setup provides physics (its DESCRIPTION),
    prop (its launch helper: k (the kernels), axes (the CPML coefficients), new_state, materials, pad_model, step(st,
    mat, sources, n, out, clock), record(st, data, receiver_op, k, clock)), nt, models (physical wp.arrays),
    amplitudes, receivers (S, n, ndim), source_op and receiver_op, and the physics' own verbs: fields and
    loop_kernels; model, sources_of, key and inputs below serve an explosive-source physics whose materials come
    from its padded models, and are overridden where a physics differs."""

    data_components = COMPONENTS  # the receivers' components in new_data's order (elastic3d: vx, vy, vz, pressure)
    period = 2  # a captured loop steps into a second state and back
    lookahead = 1  # a step reads source sample n + 1

    def model(self, on_tape=False, out=None):
        """The padded model's materials (prop.materials of each padded model), into out (an earlier call's) if given;
        differentiable under a tape."""
        return self.prop.materials(*(self.prop.pad_model(m, on_tape) for m in self.models), requires_grad=on_tape, out=out)

    def sources_of(self, amplitudes, fixed=True):
        return (amplitudes, self.source_op)

    def key(self):
        """What a kept loop must match: the physics, its kernels, grid, time step, steps, shots, sources, receivers."""
        p = self.prop
        return (self.physics.name, p.k, p.shape, p.padded, p.dx, p.dt, p.n_shots, p.device, self.nt, self.amplitudes.shape,
                self.receivers.shape)  # fmt: skip

    def inputs(self, src):
        """The arrays a kept loop copies from a later setup: the CPML coefficients and the sources' (src: sources_of's,
        the operator last) and receivers' operators."""
        return [*(getattr(ax, f) for ax in self.prop.axes for f in ("a", "b", "ah", "bh")), *src[-1], *self.receiver_op]

    def fill_model(self, mat):
        self.model(out=mat)

    def advance(self, st, mat, src, data, k, n, out, clock, side=None):
        if side is None:
            self.prop.record(st, data, self.receiver_op, k, clock)
            return self.prop.step(st, mat, src, n, out, clock)
        with side():  # beside the step, which writes only `out`; joined before the next step may overwrite st
            self.prop.record(st, data, self.receiver_op, k, clock)
        out = self.prop.step(st, mat, src, n, out, clock)
        side.join()
        return out

    def record(self, st, data, k, clock):
        self.prop.record(st, data, self.receiver_op, k, clock)

    def new_data(self, n, requires_grad=False):
        shape = (self.prop.n_shots, self.receivers.shape[1], n)
        dtype, device = self.prop.dtype, self.prop.device
        return tuple(wp.zeros(shape, dtype=dtype, device=device, requires_grad=requires_grad) for _ in self.data_components)

    def new_level(self):
        return self.prop.new_state(requires_grad=True)

    def spare(self, st):
        return self.prop.new_state()

    def out_state(self, st, spare):
        return spare

    def freed(self, st):
        return st


def taped_gradient(su, state_bytes: int, misfit, components, observed, wrt, arrays: dict, result, memory_budget=None,
                   segment_length=None, progress=False):
    """The misfit and its exact gradients through Warp's generated adjoints of every kernel under wp.Tape, in
    checkpointed segments (sweep.taped_sweep), for a Setup `su` without hand-written adjoints (vti, viscoacoustic).

    misfit: a name in misfits.MISFITS, summed over `components` against observed[name] (n_shots, n_receivers, nt), or a
    callable {name: data} -> (J, {name: dJ/d data}); state_bytes: one State's size, for the memory model (the
    checkpoints plus one segment's levels, each with its adjoint on the tape); memory_budget (bytes; None: the
    minimum, ~sqrt(nt) steps a segment) or segment_length (steps) sets the segments; arrays: name -> the Setup's
    differentiated wp.array for each name in wrt; result: the physics' result class, filled with loss, synthetic (a
    dict over su.data_components), the segments and a NumPy gradient per name in wrt."""
    loss = misfit_function(su, misfit, components, observed)

    def total(seg):
        return (math.ceil(su.nt / seg) - 1) * state_bytes + (seg + 2) * 2 * state_bytes

    seg, peak = sweep.choose_segment(su.nt, 1, total, memory_budget, segment_length)
    n_seg = math.ceil(su.nt / seg)
    bar = progress_bar(total=2 * n_seg, desc="gradient segments", unit="segments", enabled=progress)
    synthetic, J = sweep.taped_sweep(su, seg, n_seg, loss, bar)
    bar.close()
    res = result(loss=float(J), synthetic=dict(zip(su.data_components, synthetic)), segment_length=seg, n_segments=n_seg,
                 peak_bytes_estimate=peak)
    for name in wrt:
        setattr(res, name, np.array(arrays[name].grad.numpy()))
    return res


def misfit_function(su, misfit, components, observed):
    """loss(synthetic) -> (J, adjoints) of a gradient's misfit (taped_gradient's arguments; ValueError naming a bad
    one): synthetic, a tuple of NumPy arrays (S, n_rec, nt) in su.data_components' order; adjoints, dJ/dsynthetic in the
    same order (None for a component without)."""
    if not callable(misfit):
        shape = (su.prop.n_shots, su.receivers.shape[1], su.nt)
        for c in components:
            if c not in su.data_components:
                raise ValueError(f"components: {c!r} is not one of {su.data_components}")
            given = "missing" if observed is None or c not in observed else f"shape {_shape(observed[c])}"
            if given != f"shape {shape}":
                raise ValueError(f"observed[{c!r}]: {given}; give an array (n_shots, n_receivers, nt) = {shape} for each of `components`")

    def loss(synthetic):
        syn = dict(zip(su.data_components, synthetic))
        if callable(misfit):
            J, adj = misfit(syn)
        else:
            J, adj = 0.0, {}
            for c in components:
                j, adj[c] = named_misfit(misfit, syn[c], common.host_array(observed[c]), su.prop.dt)
                J += j
        return J, tuple(None if adj.get(c) is None else np.asarray(adj[c], dtype=float) for c in su.data_components)

    return loss


def _shape(a) -> tuple:
    """a's shape, a Warp array's without a copy to the host."""
    return tuple(a.shape) if isinstance(a, wp.array) else np.shape(a)


def observed_on_device(su, observed, name: str) -> wp.array:
    """observed[name] (n_shots, n_receivers, nt) as a float64 array on the run's device (common.float64_on_device: a
    Warp array there as it is); ValueError if missing or misshapen."""
    if observed is None or name not in observed:
        raise ValueError(f"observed: no {name!r} data; give observed[{name!r}] (n_shots, n_receivers, nt) for each of `components`")
    return common.float64_on_device(observed[name], su.prop.device, f"observed[{name!r}]", (su.prop.n_shots, su.receivers.shape[1], su.nt))


def l2_on_device(data, residual, observed_l2, nt: int, dt: float, components) -> wp.array:
    """The "l2" misfit of the synthetic data (arrays (S, n_rec, >= nt), named by `components`) against observed_l2
    ({component: observed float64 array (S, n_rec, nt)} on their device): its residuals (misfits._l2's, float64 rounded
    to the data's precision) into the components' arrays of residual (the others left alone); returns the sum of the
    squared differences, (1,) float64 on the device (the loss is 0.5 sum dt; reading it waits for the device)."""
    total = wp.zeros(1, dtype=wp.float64, device=data[0].device)
    for c, d, r in zip(components, data, residual):
        if c in observed_l2:
            wp.launch(l2_residual_kernel(d.dtype), dim=d.shape[:2], inputs=[d, observed_l2[c], nt, dt, r, total], device=d.device)
    return total
