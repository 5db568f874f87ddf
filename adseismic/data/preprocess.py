"""Observed traces onto the simulation's time axis: :func:`preprocess` (detrend, taper,
band-pass, anti-aliased resampling, trim / pad), for shot gathers and station traces alike.

Units: seconds, Hz. Every step is logged on the ``adseismic.data.preprocess`` logger; every
problem with the input raises :class:`adseismic.data.traces.TraceError` naming the value and the
fix. Needs SciPy (imported inside the functions), not ObsPy.
"""
from __future__ import annotations

import logging
import math
from fractions import Fraction

import numpy as np

from adseismic.data.traces import TraceError

__all__ = ["preprocess"]

log = logging.getLogger(__name__)


def _butter(kind, freqs, fs, order):
    from scipy import signal

    return signal.butter(order, freqs, btype=kind, fs=fs, output="sos")


def _fir(up: int, down: int) -> np.ndarray:
    """Low-pass FIR for resample_poly: cutoff at the lower Nyquist, long Kaiser (beta 8) window."""
    from scipy import signal

    m = max(up, down)
    return signal.firwin(2 * 24 * m + 1, 1.0 / m, window=("kaiser", 8.0))


def preprocess(data, dt_in, *, dt, nt, t_shift=0.0, detrend=True, taper=0.05, band=None, order=4,
               fmax_required=None, antialias=0.8, name="data") -> np.ndarray:
    """Put traces onto the simulation's time axis: (..., nt_in) sampled at ``dt_in`` (s) ->
    float64 (..., nt) sampled at ``dt`` (s), output sample j at time t_shift + j*dt relative to
    the input's first sample (samples outside the input are zero).

    Steps, each logged (on the whole record, before trimming, so filters see no cut edges):

    1. ``detrend``: remove the least-squares straight line of each trace;
    2. ``taper``: cosine (Tukey) taper over this fraction of the record at EACH end (0: none);
    3. ``band`` = (fmin or None, fmax or None) Hz: zero-phase Butterworth (sosfiltfilt, so the
       amplitude response is squared: 2*``order`` poles in effect) band-pass, high-pass (fmax
       None) or low-pass (fmin None); fmax must be below the input Nyquist 1/(2 dt_in);
    4. anti-aliasing, when dt > dt_in: zero-phase Butterworth low-pass at ``antialias`` times the
       new Nyquist 1/(2 dt);
    5. resampling to ``dt``: ``scipy.signal.resample_poly`` (Kaiser-windowed FIR) when dt_in/dt is
       a ratio of integers <= 64 and t_shift a whole number of output samples; otherwise band-
       limited interpolation: resample_poly up by an integer factor to >= 32 samples per period
       of the highest frequency left, then a cubic spline at the exact output times;
    6. trim / zero-pad to ``nt`` samples starting at ``t_shift`` (s; may be negative).

    fmax_required (Hz): the simulation's highest frequency; TraceError if it is not below the
    input Nyquist 1/(2 dt_in) (the data cannot constrain it), a warning above 0.8 of it (typical
    digitizer anti-alias corner). ``name`` labels messages.
    """
    from scipy import signal

    x = np.array(data, dtype=np.float64)
    if x.ndim < 1 or x.shape[-1] < 2:
        raise TraceError(f"{name}: shape {x.shape} has fewer than 2 samples along its last "
                         f"(time) axis; pass (..., nt_in) traces")
    for key, val in (("dt_in", dt_in), ("dt", dt)):
        if not (isinstance(val, (int, float, np.floating)) and math.isfinite(val) and val > 0):
            raise TraceError(f"{key}: {val!r} is not a positive sample interval in seconds")
    if not (isinstance(nt, (int, np.integer)) and nt >= 1):
        raise TraceError(f"nt: {nt!r} is not a positive number of samples")
    if not math.isfinite(float(t_shift)):
        raise TraceError(f"t_shift: {t_shift!r} is not a finite time in seconds")
    if not 0 <= float(taper) <= 0.5:
        raise TraceError(f"taper: {taper!r} is not a fraction in [0, 0.5] of the record "
                         f"tapered at each end")
    dt_in, dt, t_shift = float(dt_in), float(dt), float(t_shift)
    nyq_in, nyq_out = 0.5 / dt_in, 0.5 / dt
    n_in = x.shape[-1]
    if not np.all(np.isfinite(x)):
        raise TraceError(f"{name}: contains NaN or inf samples; run check_samples to find the "
                         f"traces and remove or repair them")
    if fmax_required is not None:
        if not float(fmax_required) < nyq_in:
            raise TraceError(f"{name}: sampled at dt_in = {dt_in:g} s (Nyquist {nyq_in:g} Hz), too "
                             f"coarse for the simulation's maximum frequency fmax_required = "
                             f"{float(fmax_required):g} Hz; use data sampled at dt_in < "
                             f"{0.5 / float(fmax_required):g} s or lower the simulation's fmax "
                             f"(e.g. a lower-frequency wavelet)")
        if float(fmax_required) > 0.8 * nyq_in:
            log.warning("%s: fmax_required %g Hz is above 0.8 x the input Nyquist (%g Hz), where "
                        "recorders' anti-alias filters usually cut", name, fmax_required, nyq_in)
    if detrend:
        x = signal.detrend(x, axis=-1, type="linear")
        log.info("%s: removed linear trend", name)
    if taper > 0:
        x *= signal.windows.tukey(n_in, 2 * float(taper))
        log.info("%s: cosine taper over %.1f%% of the record at each end", name, 100 * taper)
    if band is not None:
        try:
            fmin, fmax = band
        except (TypeError, ValueError):
            raise TraceError(f"band: {band!r} is not a pair (fmin or None, fmax or None) in Hz") from None
        for key, f in (("fmin", fmin), ("fmax", fmax)):
            if f is not None and not (math.isfinite(float(f)) and 0 < float(f) < nyq_in):
                raise TraceError(f"band: {key} = {f!r} Hz is not between 0 and the input Nyquist "
                                 f"{nyq_in:g} Hz (dt_in = {dt_in:g} s)")
        if fmin is not None and fmax is not None and not float(fmin) < float(fmax):
            raise TraceError(f"band: fmin = {fmin} Hz is not below fmax = {fmax} Hz")
        if fmin is None and fmax is None:
            log.info("%s: full band: no band filter", name)
        else:
            if fmin is None:
                sos, what = _butter("lowpass", float(fmax), 1 / dt_in, order), f"low-pass {fmax} Hz"
            elif fmax is None:
                sos, what = _butter("highpass", float(fmin), 1 / dt_in, order), f"high-pass {fmin} Hz"
            else:
                sos = _butter("bandpass", [float(fmin), float(fmax)], 1 / dt_in, order)
                what = f"band-pass {fmin}-{fmax} Hz"
            x = signal.sosfiltfilt(sos, x, axis=-1)
            log.info("%s: zero-phase Butterworth %s, order %d (x2, forward-backward)",
                     name, what, order)
    if dt > dt_in * (1 + 1e-12):
        fc = float(antialias) * nyq_out
        x = signal.sosfiltfilt(_butter("lowpass", fc, 1 / dt_in, 8), x, axis=-1)
        log.info("%s: anti-alias zero-phase Butterworth low-pass %g Hz (%.2f x new Nyquist "
                 "%g Hz)", name, fc, antialias, nyq_out)
    return _resample_trim(x, dt_in, dt, nt, t_shift, name)


def _resample_trim(x, dt_in, dt, nt, t_shift, name):
    from scipy import signal
    from scipy.interpolate import CubicSpline

    n_in = x.shape[-1]
    ratio = Fraction(dt_in / dt).limit_denominator(64)
    up, down = ratio.numerator, ratio.denominator
    exact = up <= 64 and abs(up * dt - down * dt_in) <= 1e-9 * down * dt_in
    shift = t_shift / dt
    out = np.zeros(x.shape[:-1] + (nt,))
    if exact and abs(shift - round(shift)) <= 1e-6:
        y = x if up == down == 1 else signal.resample_poly(x, up, down, axis=-1, window=_fir(up, down))
        if up != down:
            log.info("%s: resampled dt %g -> %g s with resample_poly (up %d, down %d)",
                     name, dt_in, dt, up, down)
        k0 = int(round(shift))
        lo, hi = max(k0, 0), min(k0 + nt, y.shape[-1])
        if hi > lo:
            out[..., lo - k0:hi - k0] = y[..., lo:hi]
        n_valid = max(hi - lo, 0)
    else:
        n_up = max(1, math.ceil(16 * dt_in / max(dt_in, dt)))
        dt_mid = dt_in / n_up
        times = t_shift + dt * np.arange(nt)
        valid = (times >= -1e-9 * dt_in) & (times <= (n_in - 1) * dt_in + 1e-9 * dt_in)
        rows = x.reshape(-1, n_in)
        flat = out.reshape(-1, nt)
        block = max(1, int(2e7 // (n_in * n_up)))
        for b in range(0, rows.shape[0], block):
            y = rows[b:b + block]
            if n_up > 1:
                y = signal.resample_poly(y, n_up, 1, axis=-1, window=_fir(n_up, 1))
            y = y[:, :(n_in - 1) * n_up + 1]
            spline = CubicSpline(dt_mid * np.arange(y.shape[-1]), y, axis=-1)
            flat[b:b + block, valid] = spline(np.clip(times[valid], 0, (n_in - 1) * dt_in))
        out = flat.reshape(out.shape)
        n_valid = int(valid.sum())
        log.info("%s: resampled dt %g -> %g s, t_shift %g s: resample_poly up %d then cubic spline "
                 "at the exact output times", name, dt_in, dt, t_shift, n_up)
    log.info("%s: output %d samples from t_shift = %g s (%d from the data, %d zero-padded)",
             name, nt, t_shift, n_valid, nt - n_valid)
    return out
