"""Data-based starts of a process-noise fit's noise parameters (`ProcessNoise.start_noise`).

- Measurement sd of each output: the robust spread of its frame-to-frame differences / sqrt 2.
- Intensities (process noise on a state group, input and output random walks): the
  intensity at which the noise adds, per frame, a tenth of the measurement variance
  (`SHARE`), on the output and over the horizon where it shows most:
  q = SHARE / max_{j, h} [(C Qd(h) C^T)_jj dt / (h sd_j^2)], Qd(h) the Van Loan integral of
  unit intensity on the group over h = dt, 2 dt, 4 dt, ... (up to the longest run), A and C
  the device linearised at its initial state and first input.

  Unit-correct: a state in other units than the output (a chevron's temperature read as a
  displacement) starts at its own scale. The rule this replaces, 0.1 sd^2 / dt in the
  output's units, started the chevron's thermal noise at 3.8e-14 K^2/s, where the
  likelihood is flat and the fit never moved it. Horizon-matched: a state that reaches the
  output through a lag (the TCLab heater seen through its sensor's ~18 s lag) shows its
  noise over that lag, not within one frame; one frame alone would start it ~600x too high
  (1.47 K^2/s where the fit ends at 0.0026), the horizons start it at 0.0024. A state read
  directly (or an output walk) shows it most over the first frame: 0.1 sd^2 / dt there, as
  before.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from greybox._compile import jit
from greybox._model.parameters import set_values
from greybox.stochastic._kalman import discretise
from greybox.stochastic._sde_device import _NOISE_FIELDS, StochasticDevice, _t0

SHARE = 0.1  # noise added per frame, as a fraction of the measurement variance
_INTENSITIES = ("process", "output_walk", "input_walk")


def measurement_sd(experiments) -> np.ndarray:
    """Per output: the robust spread (1.4826 MAD) of frame-to-frame differences / sqrt 2; the
    RMS difference where that is 0 (quantised, slowly moving readings), else 1e-3 of the
    readings' spread."""
    d = np.concatenate([np.diff(e.y, axis=0) for e in experiments])
    q = d.shape[1]
    sd = np.array(
        [1.4826 * np.nanmedian(np.abs(d[:, j] - np.nanmedian(d[:, j]))) for j in range(q)]
    ) / np.sqrt(2)
    spread = np.array(
        [np.nanstd(np.concatenate([e.y[:, j] for e in experiments])) for j in range(q)]
    )
    rms = np.array([np.sqrt(np.nanmean(d[:, j] ** 2)) for j in range(q)]) / np.sqrt(2)
    sd = np.where(np.isfinite(sd) & (sd > 0), sd, rms)
    return np.where(np.isfinite(sd) & (sd > 0), sd, np.maximum(1e-3 * spread, 1e-12))


def frame_interval(experiments) -> float:
    """The median frame interval of every run [s] (1 s for single-frame runs)."""
    dts = np.concatenate([np.diff(e.t_s) for e in experiments])
    return float(np.median(dts)) if dts.size else 1.0


@jit
def _rates(sd: StochasticDevice, t0, u0, horizons, paths: tuple):
    """(paths, horizons, outputs): the output variance a unit intensity at each of `paths`
    (no noise elsewhere) adds over each horizon from a known state, per second of horizon;
    the device linearised at its initial mean and input `u0`."""
    z0 = sd.initial_mean()
    A = jax.jacfwd(lambda z: sd.augmented_field(t0, z, u0))(z0)
    C = jax.jacfwd(sd.augmented_output)(z0)
    no_input = jnp.zeros((A.shape[0], 1), A.dtype)
    every = [f"{f}.{n}" for f in _INTENSITIES for n in getattr(sd, f).names]

    def one(path):  # Qc as the device lays it out (`diffusion`), unit intensity at `path`
        Qc = set_values(sd, every, [float(p == path) for p in every]).diffusion(A.dtype)
        _, _, Qd = discretise(A, no_input, Qc, horizons)
        return jnp.diagonal(C @ Qd @ C.T, axis1=-2, axis2=-1) / horizons[:, None]

    return jnp.stack([one(p) for p in paths])


def horizons(experiments, dt: float) -> np.ndarray:
    """dt, 2 dt, 4 dt, ... up to the longest run's duration."""
    span = max(float(e.t_s[-1] - e.t_s[0]) for e in experiments)
    return dt * 2.0 ** np.arange(int(np.log2(max(span / dt, 1.0))) + 1)


def start_noise(model: StochasticDevice, experiments, free) -> StochasticDevice:
    """`model` with the free noise parameters that have no `initial` at their data-based
    starts (the module docstring)."""
    sd_y = measurement_sd(experiments)
    dt = frame_interval(experiments)
    paths, vals = [], []
    todo = [p.path for p in free if p.initial is None and _field(p.path) in _NOISE_FIELDS]
    intensities = [p for p in todo if _field(p) in _INTENSITIES]
    if intensities:
        e = experiments[0]
        pw = e.inputs.to_piecewise()
        u0 = np.asarray(pw.values, dtype=float).reshape(len(pw.times_s), -1)[0]
        h = horizons(experiments, dt)
        rate = _rates(e.apply_settings(model), _t0(e), u0, h, tuple(intensities))
        # per frame, on the output and over the horizon where the noise shows most
        shown = np.max(np.asarray(rate) * dt / sd_y**2, axis=(1, 2))
    # no effect on any output (an unobservable state): the output-unit rule, for want of one
    fallback = SHARE * float(np.mean(sd_y)) ** 2 / dt
    for p in todo:
        paths.append(p)
        if _field(p) == "measurement":
            vals.append(float(sd_y[model.measurement.names.index(p.partition(".")[2])]))
            continue
        s = shown[intensities.index(p)]
        vals.append(float(SHARE / s) if np.isfinite(s) and s > 0 else fallback)
    return set_values(model, paths, vals)


def _field(path: str) -> str:
    return path.partition(".")[0]
