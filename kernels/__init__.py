"""Warp kernels and their launch helpers, one module per physics."""
