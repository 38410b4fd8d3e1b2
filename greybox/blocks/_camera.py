"""Readout blocks: how a device's physical output becomes the readings in its files.

`Camera` (PHYSICS.md §10): exposure averaging, offset, drift, pixel scale; `SensorReadout`: an
instantaneous sensor (a thermometer, an encoder) with an offset (one, or one per output) and a
drift. Both give the readings at frame times from the outputs at their quadrature instants.

z_k = (1/T_e) int_{t_k - T_e}^{t_k} y(t) dt + offset + drift (t_k - t_0), in m; `to_px` divides
by the scale. The exposure integral uses Gauss-Legendre nodes inside the window, so both
simulation paths evaluate the state at the same instants.
"""

from __future__ import annotations

import abc
import functools

import equinox as eqx
import jax.numpy as jnp
import numpy as np


@functools.lru_cache(maxsize=16)
def _gauss_legendre(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Legendre nodes and weights on [-1, 1], computed once per order (a batch asks
    for them once per device); read-only, as the cache shares them."""
    x, w = np.polynomial.legendre.leggauss(n)
    x.setflags(write=False)
    w.setflags(write=False)
    return x, w


class AbstractReadout(eqx.Module):
    """Outputs y(t) at each frame's quadrature instants -> one reading per frame."""

    @abc.abstractmethod
    def quadrature(self) -> tuple[np.ndarray, np.ndarray]:
        """(offsets [s] <= 0 relative to the frame time, weights summing to 1)."""

    @abc.abstractmethod
    def observe(self, y_quad, t_s, t_ref_s=0.0):
        """Readings (N, n_y) [SI] from outputs (N, n_quadrature, n_y) at frame times (N,)."""


class SensorReadout(AbstractReadout):
    """An instantaneous sensor: reading = output + `offset` + `drift_per_s` (t - t0), in the
    output's SI unit (K for a thermometer, m for an encoder).

    `offset` is one value for every output (path ``readout.offset``) or a tuple with one per
    output (paths ``readout.offset[0]``, ``readout.offset[1]``, ...: separate sensors, each
    with its own zero error)."""

    offset: float | tuple = 0.0
    drift_per_s: float = 0.0

    def offsets(self, n_outputs: int):
        """The offset of each output (n_outputs,) [SI]."""
        off = jnp.asarray(self.offset, dtype=float)
        if off.ndim and off.shape != (n_outputs,):
            raise ValueError(
                f"offset: {off.shape[0]} values for {n_outputs} outputs; give one per output "
                "or a single value"
            )
        return jnp.broadcast_to(off, (n_outputs,))

    def quadrature(self) -> tuple[np.ndarray, np.ndarray]:
        return np.zeros(1), np.ones(1)

    def observe(self, y_quad, t_s, t_ref_s=0.0):
        off = self.offsets(y_quad.shape[-1])
        return y_quad[:, 0, :] + off + self.drift_per_s * (t_s - t_ref_s)[:, None]


class Camera(AbstractReadout):
    """- `m_per_px`: image scale [m/px] (calibrated, e.g. with a stage micrometer).
    - `exposure_s`: exposure time [s] (a known setting; 0 = instantaneous sampling).
    - `offset_m`: position of the reference (zero) in the image [m]; usually per experiment.
    - `drift_m_per_s`: linear drift (stage or focus) [m/s]; usually per experiment, often fixed 0.
    - `n_quadrature`: Gauss-Legendre nodes for the exposure average.
    """

    m_per_px: float = 0.645e-6
    exposure_s: float = eqx.field(static=True, default=0.0)
    offset_m: float = 0.0
    drift_m_per_s: float = 0.0
    n_quadrature: int = eqx.field(static=True, default=3)

    def __check_init__(self):
        if not self.exposure_s >= 0:
            raise ValueError(f"exposure_s: {self.exposure_s} must be >= 0 seconds")
        if isinstance(self.m_per_px, (int, float)) and not self.m_per_px > 0:
            raise ValueError(f"m_per_px: {self.m_per_px} must be > 0")

    def quadrature(self) -> tuple[np.ndarray, np.ndarray]:
        """(offsets [s] <= 0 relative to the frame time, weights summing to 1)."""
        if self.exposure_s == 0.0:
            return np.zeros(1), np.ones(1)
        x, w = _gauss_legendre(self.n_quadrature)
        return -self.exposure_s * (1.0 - x) / 2.0, w / 2.0

    def observe(self, y_quad_m, t_s, t_ref_s=0.0):
        """Frame readings [m] from outputs at the quadrature instants.

        `y_quad_m`: (N, n_quadrature, n_y) outputs; `t_s`: (N,) frame times [s]."""
        _, w = self.quadrature()
        mean = jnp.einsum("q,nqy->ny", jnp.asarray(w), y_quad_m)
        return mean + self.offset_m + self.drift_m_per_s * (t_s - t_ref_s)[:, None]

    def to_px(self, z_m):
        return z_m / self.m_per_px
