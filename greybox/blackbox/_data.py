"""Uniformly sampled input/output data for black-box models."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


def _as_2d(x, name: str) -> np.ndarray:
    x = np.asarray(x, dtype=float)
    if x.ndim == 1:
        x = x[:, None]
    if x.ndim != 2:
        raise ValueError(f"{name}: expected shape (N,) or (N, channels), got {x.shape}")
    return x


@dataclass(frozen=True, eq=False)
class UniformData:
    """One experiment sampled on a uniform time grid.

    **Fields:**
    - `u`: inputs, shape (N, nu) (a 1-D array is taken as one channel), in the input's units.
    - `y`: outputs, shape (N, ny), in the output's units.
    - `dt`: sampling interval [s].
    - `resampled`: True when the samples were interpolated from a coarser or irregular
      grid (see `resample`); every model and result fitted on it carries this flag.
    - `name`: a label for reports.

    Arrays are stored 2-D, read-only, and must be finite: interpolate or drop gaps first.
    """

    u: np.ndarray
    y: np.ndarray
    dt: float
    resampled: bool = False
    name: str = ""

    def __post_init__(self):
        u = _as_2d(self.u, "u")
        y = _as_2d(self.y, "y")
        if u.shape[0] != y.shape[0]:
            raise ValueError(
                f"u and y: different numbers of samples ({u.shape[0]} vs {y.shape[0]}); "
                "pass signals on the same time grid"
            )
        for arr, label in ((u, "u"), (y, "y")):
            bad = ~np.isfinite(arr)
            if bad.any():
                first = int(np.argwhere(bad)[0, 0])
                raise ValueError(
                    f"{label}: {int(bad.sum())} non-finite value(s) (first at sample {first}); "
                    "a uniform grid must be complete: interpolate with `resample` or split "
                    "the record into experiments at the gap"
                )
        dt = float(self.dt)
        if not (np.isfinite(dt) and dt > 0):
            raise ValueError(f"dt: must be a positive sampling interval in s, got {self.dt!r}")
        u.setflags(write=False)
        y.setflags(write=False)
        object.__setattr__(self, "u", u)
        object.__setattr__(self, "y", y)
        object.__setattr__(self, "dt", dt)
        object.__setattr__(self, "resampled", bool(self.resampled))

    @property
    def n_samples(self) -> int:
        return self.y.shape[0]

    @property
    def nu(self) -> int:
        return self.u.shape[1]

    @property
    def ny(self) -> int:
        return self.y.shape[1]

    @property
    def time_s(self) -> np.ndarray:
        """Sample times [s], starting at 0."""
        return self.dt * np.arange(self.n_samples)

    def segment(self, start: int, stop: int) -> UniformData:
        """Samples `start <= k < stop` (0-based, like Python slicing) as a new experiment."""
        return UniformData(
            self.u[start:stop], self.y[start:stop], self.dt, self.resampled, self.name
        )


def detrend(data: UniformData) -> UniformData:
    """Remove the mean of every input and output channel (MATLAB `detrend(data, 0)`)."""
    return UniformData(
        data.u - data.u.mean(0), data.y - data.y.mean(0), data.dt, data.resampled, data.name
    )


def as_experiments(data: UniformData | Sequence[UniformData]) -> tuple[UniformData, ...]:
    """Normalise one experiment or a list of them; checks they agree on dt and channels."""
    exps = (data,) if isinstance(data, UniformData) else tuple(data)
    if not exps or not all(isinstance(d, UniformData) for d in exps):
        raise ValueError("data: pass a UniformData or a non-empty list of UniformData")
    d0 = exps[0]
    for d in exps[1:]:
        if d.nu != d0.nu or d.ny != d0.ny:
            raise ValueError("data: experiments have different numbers of inputs/outputs")
        if not np.isclose(d.dt, d0.dt, rtol=1e-9):
            raise ValueError(
                f"data: experiments have different dt ({d0.dt} s vs {d.dt} s); resample them "
                "to one grid first"
            )
    return exps
