"""Physics: one folder each (acoustic/, elastic/) with its Warp kernels, launch helper and DESCRIPTION
(fields, parameters and units, stencils, CFL and dispersion numbers); common.py and numerics.py hold
what they share. Nothing here schedules work: graphs, streams and reductions are adseismic.accel's,
time loops and gradients adseismic.solve's. Installed as adseismic.kernels."""
