"""Time stepping, gradients and shot batching: forward runs (acoustic, elastic), checkpointed gradients
and their hand-written adjoint sweeps, Born modelling. A physics is handed over as its kernels'
launch helper and DESCRIPTION (adseismic.kernels.<name>)."""
