"""Polynomial model structure shared by ARX, ARMAX and OE, and the numpy filters behind
simulation and prediction.

Convention (MATLAB `idpoly`): for output i,
    A_i(q) y_i(t) = sum_l B_il(q) / F_il(q) u_l(t) + C_i(q) e_i(t) + offset_i,
with polynomials in the backward shift q^-1, A, C, F monic, and the input delay nk_l kept
as leading zeros of B_il. Note the sign: A = 1 + a_1 q^-1 + ..., so y(t) = -a_1 y(t-1) + ...
(GEKKO/Park et al. write +a_1 y(t-1); their a_1 is our -a_1).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class Polynomials:
    """Coefficient arrays of a polynomial model, powers q^0, q^-1, ... along the last axis.

    - `a`: (ny, na+1), monic.    - `b`: (ny, nu, nk+nb) with nk leading zeros.
    - `c`: (ny, nc+1), monic.    - `f`: (ny, nu, nf+1), monic.
    - `offset`: (ny,) constant equation offset, in the output's units.
    """

    a: np.ndarray
    b: np.ndarray
    c: np.ndarray
    f: np.ndarray
    offset: np.ndarray

    @property
    def ny(self) -> int:
        return self.a.shape[0]

    @property
    def nu(self) -> int:
        return self.b.shape[1]

    def io_rational(self, i: int):
        """Output i as one recursion: den(q) y = sum_l num_l(q) u_l + const.

        den = A_i prod_l F_il, num_l = B_il prod_{m != l} F_im, const = offset_i prod_l F_il(1).
        """
        fprod = np.ones(1)
        for f in self.f[i]:
            fprod = np.convolve(fprod, f)
        den = np.convolve(self.a[i], fprod)
        nums = []
        for l in range(self.nu):
            num = self.b[i, l]
            for m in range(self.nu):
                if m != l:
                    num = np.convolve(num, self.f[i, m])
            nums.append(num)
        width = max(len(n) for n in nums)
        num = np.stack([np.pad(n, (0, width - len(n))) for n in nums])
        return den, num, self.offset[i] * fprod.sum(), fprod


def lfilter(b, a, x) -> np.ndarray:
    """y = b(q)/a(q) x with zero initial conditions, a[0] = 1, along axis 0 of 1-D x
    (`scipy.signal.lfilter`)."""
    from scipy import signal

    return signal.lfilter(
        np.asarray(b, dtype=float), np.asarray(a, dtype=float), np.asarray(x, dtype=float)
    )


def _ar_recursion(a, w, y, start):
    """y(t) = w(t) - sum_{j>=1} a_j y(t-j) for t >= start; y[:start] given (initial values,
    zeros before index 0). `scipy.signal.lfilter` with the state set from those values."""
    from scipy import signal

    a = np.asarray(a, dtype=float)
    w = np.asarray(w, dtype=float)
    n = len(a) - 1
    out = np.empty(len(w))
    out[:start] = y[:start]
    if start >= len(w):
        return out
    if n == 0:
        out[start:] = w[start:]
        return out
    past = np.concatenate([np.zeros(max(0, n - start)), out[max(0, start - n) : start]])
    zi = signal.lfiltic([1.0], a, past[::-1])  # most recent output first
    out[start:] = signal.lfilter([1.0], a, w[start:], zi=zi)[0]
    return out


def lag_matrix(x: np.ndarray, lags: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Vectorised regressor block: entry [r, j] = x[rows[r] - lags[j]]."""
    return x[rows[:, None] - lags[None, :]]


def as_per_input(value, nu: int, name: str) -> tuple[int, ...]:
    """Scalar or per-input integer order -> tuple of length nu, validated."""
    vals = (value,) * nu if np.isscalar(value) else tuple(value)
    if len(vals) != nu:
        raise ValueError(
            f"{name}: got {len(vals)} values for {nu} inputs; pass a scalar or one value per input"
        )
    out = []
    for v in vals:
        if int(v) != v or v < 0:
            raise ValueError(
                f"{name}: orders and delays must be integers >= 0, got {v!r}"
                + ("; nk < 0 would make the model non-causal" if name == "nk" else "")
            )
        out.append(int(v))
    return tuple(out)


def as_order(value, name: str) -> int:
    if not np.isscalar(value) or int(value) != value or value < 0:
        raise ValueError(f"{name}: must be an integer >= 0, got {value!r}")
    return int(value)


def max_lag(na: int, nb: Sequence[int], nk: Sequence[int], extra: int = 0) -> int:
    """Number of initial samples a regressor needs: max(na, nk_l + nb_l - 1, extra)."""
    lags = [na, extra] + [k + n - 1 for n, k in zip(nb, nk) if n > 0]
    return max(lags)


def input_lags(nb: Sequence[int], nk: Sequence[int]) -> list[np.ndarray]:
    return [nk_l + np.arange(nb_l) for nb_l, nk_l in zip(nb, nk)]


def b_from_theta(theta_b: np.ndarray, nb, nk) -> np.ndarray:
    """Pack flat B coefficients (input by input) into (nu, max(nk+nb)) with leading zeros."""
    width = max(max(k + n for n, k in zip(nb, nk)), 1)
    b = np.zeros((len(nb), width))
    pos = 0
    for l, (n, k) in enumerate(zip(nb, nk)):
        b[l, k : k + n] = theta_b[pos : pos + n]
        pos += n
    return b


# --- Stability-preserving parameterisation (reflection coefficients, Levinson step-up) ---


def poly_from_reflection(k) -> np.ndarray:
    """Monic polynomial 1 + p_1 q^-1 + ... whose roots lie inside the unit circle iff
    every |k_m| < 1 (Schur-Cohn / Levinson step-up). Works on numpy and JAX arrays."""
    import jax.numpy as jnp

    xp = jnp if not isinstance(k, np.ndarray) else np
    p = xp.ones(1)
    for m in range(k.shape[0]):
        ext = xp.concatenate([p, xp.zeros(1)])
        p = ext + k[m] * ext[::-1]
    return p


def reflection_from_poly(p: np.ndarray) -> np.ndarray:
    """Inverse of `poly_from_reflection` (step-down); |k| >= 1 means a root on/outside |z|=1."""
    p = np.asarray(p, dtype=float)
    n = len(p) - 1
    k = np.zeros(n)
    for m in range(n, 0, -1):
        km = p[m]
        k[m - 1] = km
        if abs(km) >= 1:
            return np.full(n, np.inf)
        p = (p[:m] - km * p[m::-1][:m]) / (1 - km**2)
    return k


def reflect_inside(p: np.ndarray, margin: float = 0.98) -> np.ndarray:
    """Mirror roots outside the unit circle to 1/conj(root) and shrink to |z| <= margin."""
    p = np.asarray(p, dtype=float)
    if len(p) == 1:
        return p
    r = np.roots(p)
    mag = np.abs(r)
    r = np.where(mag > 1, 1 / np.conj(r), r)
    r = np.where(np.abs(r) > margin, r * margin / np.abs(r), r)
    return np.real(np.poly(r))


def is_stable_poly(p: np.ndarray) -> bool:
    p = np.asarray(p, dtype=float)
    return len(p) == 1 or bool(np.all(np.abs(np.roots(p)) < 1))
