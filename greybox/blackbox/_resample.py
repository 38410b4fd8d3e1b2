"""Resampling onto a uniform grid with piecewise interpolants (thesis ch. 3: 191 -> 1910).

Interpolated samples are not measurements: their noise is correlated and high-frequency
content is invented by the interpolant, so every result computed on them is labelled
`resampled=True`.
"""

from __future__ import annotations

import numpy as np

from ._data import UniformData, _as_2d

_METHODS = ("linear", "pchip", "zoh")


def _pchip_slopes(t: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Fritsch-Carlson shape-preserving derivatives (as MATLAB `pchip`), per column of v."""
    h = np.diff(t)[:, None]
    m = np.diff(v, axis=0) / h
    n = len(t)
    d = np.zeros_like(v)
    if n == 2:
        d[:] = m[0]
        return d
    # Interior: weighted harmonic mean where neighbouring slopes agree in sign, else 0.
    w1 = 2 * h[1:] + h[:-1]
    w2 = h[1:] + 2 * h[:-1]
    same = (np.sign(m[1:]) * np.sign(m[:-1])) > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = (w1 / m[:-1] + w2 / m[1:]) / (w1 + w2)
        d[1:-1] = np.where(same, 1.0 / inv, 0.0)

    def edge(h0, h1, m0, m1):
        de = ((2 * h0 + h1) * m0 - h0 * m1) / (h0 + h1)
        de = np.where(np.sign(de) != np.sign(m0), 0.0, de)
        return np.where((np.sign(m0) != np.sign(m1)) & (np.abs(de) > 3 * np.abs(m0)), 3 * m0, de)

    d[0] = edge(h[0], h[1], m[0], m[1])
    d[-1] = edge(h[-1], h[-2], m[-1], m[-2])
    return d


def interpolate(t_s, values, t_new_s, method: str = "linear") -> np.ndarray:
    """Piecewise interpolation of `values` (N,) or (N, channels) from `t_s` to `t_new_s`.

    **Arguments:**
    - `t_s`: strictly increasing sample times [s].
    - `values`: samples at `t_s`; must be finite.
    - `t_new_s`: query times [s], inside [t_s[0], t_s[-1]] (no extrapolation).
    - `method`: "linear" (piecewise linear), "pchip" (shape-preserving piecewise cubic,
      no overshoot between samples) or "zoh" (hold the previous sample: for piecewise
      constant inputs such as laser on/off commands).

    **Returns:** array of shape (len(t_new_s),) + values.shape[1:].
    """
    if method not in _METHODS:
        raise ValueError(f"method: unknown {method!r}; use one of {_METHODS}")
    t = np.asarray(t_s, dtype=float)
    tq = np.asarray(t_new_s, dtype=float)
    v = np.asarray(values, dtype=float)
    one_d = v.ndim == 1
    v = _as_2d(v, "values")
    if t.ndim != 1 or len(t) != v.shape[0] or len(t) < 2:
        raise ValueError(f"t_s: need a 1-D array of >= 2 times matching values ({v.shape[0]})")
    if not (np.all(np.isfinite(t)) and np.all(np.diff(t) > 0)):
        raise ValueError(
            "t_s: times must be finite and strictly increasing; sort them and drop duplicate frames"
        )
    if not np.all(np.isfinite(v)):
        raise ValueError("values: contains NaN/inf; drop those samples (and their times) first")
    if tq.size and (tq.min() < t[0] - 1e-12 * abs(t[0]) or tq.max() > t[-1] + 1e-9):
        raise ValueError("t_new_s: query times outside the sampled span; no extrapolation")
    k = np.clip(np.searchsorted(t, tq, side="right") - 1, 0, len(t) - 2)
    if method == "zoh":
        k = np.clip(np.searchsorted(t, tq, side="right") - 1, 0, len(t) - 1)
        out = v[k]
    else:
        h = (t[k + 1] - t[k])[:, None]
        s = ((tq - t[k])[:, None]) / h
        if method == "linear":
            out = v[k] + s * (v[k + 1] - v[k])
        else:
            d = _pchip_slopes(t, v)
            h00 = 2 * s**3 - 3 * s**2 + 1
            h10 = s**3 - 2 * s**2 + s
            h01 = -2 * s**3 + 3 * s**2
            h11 = s**3 - s**2
            out = h00 * v[k] + h10 * h * d[k] + h01 * v[k + 1] + h11 * h * d[k + 1]
    return out[:, 0] if one_d else out


def resample(
    t_s, u, y, dt: float, *, method: str = "linear", input_method: str | None = None, name: str = ""
) -> UniformData:
    """Interpolate (possibly irregular) samples onto the grid t_s[0] + k dt, flagged resampled.

    **Arguments:**
    - `t_s`: measurement times [s], strictly increasing.
    - `u`, `y`: inputs (N,) or (N, nu) and outputs (N,) or (N, ny) at `t_s`.
    - `dt`: new sampling interval [s] (e.g. the old interval / 10, as the thesis did).
    - `method`: interpolant for y, "linear" or "pchip" (shape-preserving cubic).
    - `input_method`: interpolant for u; defaults to `method`. Use "zoh" for commands that
      are held between samples.

    **Returns:** a `UniformData` with `resampled=True`.
    """
    t = np.asarray(t_s, dtype=float)
    if not (np.isfinite(dt) and dt > 0):
        raise ValueError(f"dt: must be a positive interval in s, got {dt!r}")
    n_new = int(np.floor((t[-1] - t[0]) / dt + 1e-9)) + 1
    tq = t[0] + dt * np.arange(n_new)
    return UniformData(
        interpolate(t, u, tq, input_method or method),
        interpolate(t, y, tq, method),
        dt,
        resampled=True,
        name=name,
    )


def uniform_from_experiment(
    exp,
    dt: float,
    *,
    method: str = "pchip",
    remove_rest: bool = True,
    input_scale: float = 1.0,
    output_scale: float = 1.0,
):
    """A camera run prepared for black-box models, the way the thesis did it.

    Frames with a NaN reading are dropped, the rest level (the reading before the input first
    switches on, `Experiment.rest_level`) is removed, the outputs are interpolated onto a
    uniform grid (flagged `resampled`), and the known input waveform is evaluated exactly on
    the grid (no interpolation of the input).

    **Arguments:**
    - `exp`: a `greybox._model.data.Experiment` (SI units).
    - `dt`: grid interval [s]; `method`: "pchip" (shape-preserving cubic) or "linear".
    - `remove_rest`: subtract the rest level; needs >= 3 valid frames before the input onset.
    - `input_scale`, `output_scale`: factors applied to the SI values (e.g. 1e3 for mW and
      1e6 for um keep ARX coefficients well scaled).

    **Returns:** (`UniformData`, grid times [s] (n,), removed rest level in SI (n_y,)).
    """
    valid = np.all(np.isfinite(exp.y), axis=1)
    t, y = exp.t_s[valid], exp.y[valid]
    rest = exp.rest_level() if remove_rest else np.zeros(y.shape[1])
    if not np.all(np.isfinite(rest)):
        raise ValueError(
            f"{exp.name}: fewer than 3 valid frames before the input switches on, "
            "so the rest level is unknown; pass remove_rest=False"
        )
    d = resample(t, np.zeros_like(t), (y - rest) * output_scale, dt, method=method, name=exp.name)
    t_grid = t[0] + dt * np.arange(d.n_samples)
    u = np.asarray(exp.inputs(t_grid), dtype=float).reshape(t_grid.size, -1) * input_scale
    return UniformData(u, d.y, dt, resampled=True, name=exp.name), t_grid, rest
