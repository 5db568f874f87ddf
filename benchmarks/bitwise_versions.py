"""Bit-for-bit check across a restructure: run forward, gradient (checkpointed, every step kept, Warp's adjoint) and Born
of both physics in float32 and float64 on the CPU with one version of adseismic, and save every array.

    PYTHONPATH=<an install of the old version> python benchmarks/bitwise_versions.py old old.npz
    python benchmarks/bitwise_versions.py new new.npz
    python -c "import numpy as np; a, b = np.load(\"old.npz\"), np.load(\"new.npz\"); print([k for k in a.files if not np.array_equal(a[k], b[k])])"

"old" imports the layout before issue 21 (adseismic.propagate, .gradient, .elastic); "new" the public API.
"""
import sys

import numpy as np

which, out = sys.argv[1], sys.argv[2]
if which == "old":
    from adseismic.elastic import forward_elastic, gradient_elastic
    from adseismic.gradient import born, gradient
    from adseismic.propagate import forward
else:
    from adseismic import born, forward, forward_elastic, gradient, gradient_elastic

rng = np.random.default_rng(0)
res = {}
for prec in ("float32", "float64"):
    v = 2000.0 + 300.0 * rng.random((40, 52))
    s = np.zeros((2, 1, 300)); t = np.arange(300) * 1e-3
    s[:, 0] = (1 - 2 * (np.pi * 15 * (t - 0.08)) ** 2) * np.exp(-(np.pi * 15 * (t - 0.08)) ** 2)
    src = np.array([[[55.0, 101.7]], [[150.2, 400.9]]])
    rec = np.array([[[20.0, x] for x in np.linspace(10, 500, 9)]] * 2)
    obs = rng.standard_normal((2, 9, 300)) * 1e-6
    f = forward(v, 10.0, 1e-3, s, src, rec, precision=prec, pml_width=10)
    res[f"ac_fwd_{prec}"] = np.asarray(f.receiver_amplitudes)
    for seg in (None, 30):
        g = gradient(v, 10.0, 1e-3, s, src, rec, obs, precision=prec, pml_width=10, segment_length=seg,
                     wrt=("velocity", "source_amplitudes", "source_locations"), illumination=True)
        for k in ("velocity", "source_amplitudes", "source_locations", "illumination"):
            res[f"ac_grad_{prec}_{seg}_{k}"] = np.asarray(getattr(g, k))
        res[f"ac_grad_{prec}_{seg}_loss"] = np.array(g.loss)
    gw = gradient(v, 10.0, 1e-3, s, src, rec, obs, precision=prec, pml_width=10, segment_length=30, adjoint="warp")
    res[f"ac_gradwarp_{prec}"] = np.asarray(gw.velocity)
    res[f"ac_born_{prec}"] = born(v, rng.standard_normal(v.shape), 10.0, 1e-3, s, src, rec, precision=prec, pml_width=10)
    vp = 2500.0 + 200 * rng.random((40, 52)); vs = vp / 1.8; rho = 2000.0 + 0 * vp
    comp = np.broadcast_to([1.0, 0.5], (2, 1, 2)).copy()
    fe = forward_elastic(vp, vs, rho, 10.0, 1e-3, s, src, rec, source_components=comp, precision=prec, pml_width=10, free_surface=True)
    for k in ("vx", "vz", "pressure"):
        res[f"el_fwd_{prec}_{k}"] = np.asarray(getattr(fe, k))
    obs_e = {c: rng.standard_normal((2, 9, 300)) * 1e-9 for c in ("vx", "vz", "pressure")}
    for seg, adj in ((None, "hand"), (40, "hand"), (40, "warp")):
        ge = gradient_elastic(vp, vs, rho, 10.0, 1e-3, s, src, rec, obs_e, source_components=comp, precision=prec, pml_width=10,
                              segment_length=seg, adjoint=adj, wrt=("vp", "vs", "rho", "source_amplitudes", "source_locations"))
        for k in ("vp", "vs", "rho", "source_amplitudes", "source_locations"):
            res[f"el_grad_{prec}_{seg}_{adj}_{k}"] = np.asarray(getattr(ge, k))
        res[f"el_grad_{prec}_{seg}_{adj}_loss"] = np.array(ge.loss)
np.savez(out, **res)
print(len(res), "arrays")
