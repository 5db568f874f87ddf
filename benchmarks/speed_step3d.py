"""Per-launch GPU times of the 3D acoustic step's parts on a bench scene (S3D400 by default): psi along each axis,
the frame (CPML and halo cells, in tiles of flat-offset cells), the core tiles at several layouts (rows x columns a
thread, threads a block) alone and with the frame, and the per-cell reference step; each replayed from a captured graph. The
layouts' results are checked against the reference step's.

    python benchmarks/speed_step3d.py [SCENE]      (a CUDA device)
"""

import sys
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from speed_kernels import per_launch  # noqa: E402

import adseismic.solve.acoustic as A  # noqa: E402
from adseismic.bench import DT, DX, PML, SCENES, build_arrays  # noqa: E402

LAYOUTS = [(4, 2, 128), (2, 2, 128), (8, 2, 128), (4, 4, 128), (4, 2, 64), (4, 2, 256)]  # (rows, columns, threads a block)


def main(name="S3D400", device="cuda:0"):
    wp.init()
    a = build_arrays(SCENES[name], 20)
    su = A.setup(a.model["velocity"], DX, DT, a.amplitudes, a.sources, a.receivers, order=4, pml_width=PML, device=device)
    prop = su.prop
    st, out, vpad = prop.new_state(), prop.new_state(), su.model()
    rng = np.random.default_rng(0)
    for f in (st.u, st.u_prev):
        f.assign(rng.standard_normal(f.shape).astype(np.float32))
    args = [st.u, st.u_prev, out.u, vpad, *out.psi, *st.zeta, *out.zeta, *prop.axes, prop.dt2, prop.inv_dx, prop.top]
    interior = int(np.prod(prop.interior))
    core = (prop.core[1] - prop.core[0]) * (prop.ycore[1] - prop.ycore[0]) * (prop.core[3] - prop.core[2])
    print(f"{name}: padded {prop.padded}, interior {interior} cells, core {core}, frame {prop.frame_cells}")

    def show(label, t, cells):
        print(f"{label:34s} {t * 1e6:9.1f} us  {cells / t / 1e9:7.1f} Gcell/s")

    for ax in range(3):
        def psi(ax=ax):
            inputs = [st.u, st.psi[ax], out.psi[ax], prop.axes[ax], prop.inv_dx]
            wp.launch(prop.k.psi_flat[ax], dim=int(np.prod(prop.strip_shape(ax))), inputs=inputs, device=device)

        show(f"psi along axis {ax}", per_launch(psi, device, 20), int(np.prod(prop.strip_shape(ax))))
    reference = per_launch(lambda: wp.launch(prop.k.step, dim=prop.interior, inputs=args, device=device), device, 20)
    show("reference step", reference, interior)
    ref = out.u.numpy()
    show("frame", per_launch(lambda: prop.step_core(args, st.u, st.u_prev, out.u, vpad, part="frame"), device, 20), prop.frame_cells)
    for rows, cols, block in LAYOUTS:
        prop.core_rows, prop.core_cols, prop.core_threads = rows, cols, block
        out.u.zero_()
        alone = per_launch(lambda: prop.step_core(args, st.u, st.u_prev, out.u, vpad, part="core"), device, 20)
        show(f"core r{rows} c{cols} b{block}", alone, core)
        t = per_launch(lambda: prop.step_core(args, st.u, st.u_prev, out.u, vpad), device, 20)
        show(f"  with frame (max diff {np.abs(out.u.numpy() - ref).max() / np.abs(ref).max():.0e})", t, interior)


if __name__ == "__main__":
    main(*sys.argv[1:2])
