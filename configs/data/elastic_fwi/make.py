"""Writes true_vp.npy and true_vs.npy, the true model of configs/elastic_fwi.yaml (python make.py, here): two layers
(vp 1800 / 2300 m/s, vs = vp / 1.8, interface at 250 m) on a 31 x 41 grid of 20 m (z, x), with a Gaussian anomaly
(standard deviation 70 m) at z = 400 m, x = 400 m: +230 m/s in vp (+10%) and -100 m/s in vs (-8%)."""
import numpy as np

nz, nx, dx = 31, 41, 20.0
z = np.arange(nz)[:, None] * dx * np.ones((1, nx))
x = np.arange(nx)[None, :] * dx * np.ones((nz, 1))
vp = np.where(z < 250.0, 1800.0, 2300.0)
vs = vp / 1.8
bump = np.exp(-((z - 400.0) ** 2 + (x - 400.0) ** 2) / (2 * 70.0**2))
np.save("true_vp.npy", (vp + 230.0 * bump).astype(np.float32))
np.save("true_vs.npy", (vs - 100.0 * bump).astype(np.float32))
