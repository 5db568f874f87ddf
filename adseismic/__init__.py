"""adseismic: differentiable seismic wave propagation with NVIDIA Warp."""
