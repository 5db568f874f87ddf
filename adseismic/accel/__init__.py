"""GPU machinery shared by every physics: CUDA-graph time loops and the kept store (graphs), device
reductions (reductions). The solver imports it; physics (adseismic.kernels) never does."""
