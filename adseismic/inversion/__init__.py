"""Full-waveform inversion: the workflow (fwi), misfits, optimisers (L-BFGS, Gauss-Newton), model
parameterisations and gradient conditioning."""
