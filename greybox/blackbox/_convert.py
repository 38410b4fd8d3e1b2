"""Transfer functions, discrete <-> continuous conversion (ZOH, Tustin), poles/zeros/DC
gain, and export to python-control (optional dependency, imported lazily).

Conversions work channel by channel (output i, input l). Covariance is not carried over
(as in MATLAB `d2c`). Whole-sample input delays are kept as a dead time `delay_s`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._poly import Polynomials


@dataclass(frozen=True, eq=False)
class DiscreteTF:
    """Discrete-time transfer-function matrix G_il(q) = num[i][l](q^-1) / den[i][l](q^-1).

    `num`/`den`: nested tuples (ny x nu) of coefficient arrays in powers q^0, q^-1, ...
    (den monic; input delay = leading zeros of num); `dt` [s]; `resampled`.
    Works with `simulate`, `step_response`, `poles`, `zeros`, `dc_gain`.
    """

    num: tuple
    den: tuple
    dt: float
    resampled: bool = False

    def polynomials(self) -> Polynomials:
        ny, nu = len(self.num), len(self.num[0])
        wb = max(len(n) for row in self.num for n in row)
        wf = max(len(d) for row in self.den for d in row)
        b = np.zeros((ny, nu, wb))
        f = np.zeros((ny, nu, wf))
        for i in range(ny):
            for l in range(nu):
                b[i, l, : len(self.num[i][l])] = self.num[i][l]
                f[i, l, : len(self.den[i][l])] = self.den[i][l]
        return Polynomials(np.ones((ny, 1)), b, np.ones((ny, 1)), f, np.zeros(ny))


@dataclass(frozen=True, eq=False)
class ContinuousTF:
    """Continuous-time G_il(s) = exp(-s delay_s[i, l]) num[i][l](s) / den[i][l](s).

    `num`/`den`: nested tuples (ny x nu) of coefficients in descending powers of s (den
    monic); `delay_s`: (ny, nu) dead times [s]; `method`: "zoh" or "tustin" (how it was
    obtained); `dt`: the sampling interval of the discrete model [s]; `resampled`.
    """

    num: tuple
    den: tuple
    delay_s: np.ndarray
    method: str
    dt: float
    resampled: bool = False


def transfer_function(model) -> DiscreteTF:
    """The input-output (noise-free) part of an ARX/ARMAX/OE model as a `DiscreteTF`."""
    pol = model.polynomials()
    num, den = [], []
    for i in range(pol.ny):
        nrow, drow = [], []
        for l in range(pol.nu):
            fl = np.trim_zeros(pol.f[i, l], "b")
            d = np.convolve(pol.a[i], fl)
            nrow.append(np.trim_zeros(pol.b[i, l], "b") if pol.b[i, l].any() else np.zeros(1))
            drow.append(d)
        num.append(tuple(nrow))
        den.append(tuple(drow))
    return DiscreteTF(tuple(num), tuple(den), model.dt, bool(model.resampled))


def _as_tf(model):
    return model if isinstance(model, DiscreteTF | ContinuousTF) else transfer_function(model)


def poles(model) -> list[list[np.ndarray]]:
    """Poles per channel [i][l]: roots of den in z (discrete; delay poles at z = 0
    excluded) or in s [1/s] (continuous)."""
    tf = _as_tf(model)
    return [[np.roots(d) for d in row] for row in tf.den]


def zeros(model) -> list[list[np.ndarray]]:
    """Finite zeros per channel [i][l] (leading delay zeros of B stripped)."""
    tf = _as_tf(model)
    return [
        [np.roots(np.trim_zeros(n, "f")) if np.any(n) else np.zeros(0) for n in row]
        for row in tf.num
    ]


def dc_gain(model) -> np.ndarray:
    """Steady-state gain (ny, nu): G(z=1) for discrete, G(s=0) for continuous models."""
    tf = _as_tf(model)
    out = np.zeros((len(tf.num), len(tf.num[0])))
    for i, (nrow, drow) in enumerate(zip(tf.num, tf.den)):
        for l, (n, d) in enumerate(zip(nrow, drow)):
            dv = np.sum(d) if isinstance(tf, DiscreteTF) else d[-1]
            nv = np.sum(n) if isinstance(tf, DiscreteTF) else n[-1]
            out[i, l] = np.inf if dv == 0 else nv / dv
    return out


# --- state space helpers (SISO, controllable canonical form) ---


def _ss(num_desc, den_desc):
    """Controllable canonical (A, B, C, D) of num/den in descending powers, len equal."""
    den = np.asarray(den_desc, float)
    num = np.asarray(num_desc, float)
    num, den = num / den[0], den / den[0]
    n = len(den) - 1
    D = num[0]
    c = num[1:] - D * den[1:]
    A = np.zeros((n, n))
    if n:
        A[0] = -den[1:]
        A[1:, :-1] = np.eye(n - 1)
    B = np.zeros((n, 1))
    if n:
        B[0, 0] = 1.0
    return A, B, c[None, :], D


def _tf_from_ss(A, B, C, D):
    """SISO num/den (descending powers, same length) of C (xI - A)^-1 B + D."""
    pa = np.real(np.poly(A)) if A.size else np.ones(1)
    pabc = np.real(np.poly(A - B @ C)) if A.size else np.ones(1)
    return pabc - pa + D * pa, pa


def _expm(M):
    import scipy.linalg

    return scipy.linalg.expm(M)


def _logm_real(M):
    """The real matrix logarithm of the ZOH block matrix (scipy's Schur-Pade `logm`, which
    handles repeated poles such as 1/(s+1)^2), or an error when none exists."""
    import scipy.linalg

    w = np.linalg.eigvals(M)
    if np.any(np.abs(w) < 1e-12) or np.any((np.abs(w.imag) < 1e-12) & (w.real < 0)):
        raise ValueError(
            "model: a pole at z = 0 or on the negative real axis has no real ZOH continuous "
            "equivalent; use method='tustin' or a lower order"
        )
    L = np.asarray(scipy.linalg.logm(M))
    if np.max(np.abs(L.imag), initial=0.0) > 1e-8 * max(1.0, np.max(np.abs(L))) or not (
        np.allclose(scipy.linalg.expm(L.real), M, atol=1e-9)
    ):
        raise ValueError(
            "model: the ZOH inversion has no accurate real logarithm; use method='tustin'"
        )
    return L.real


def _q_to_z(num, den):
    """Coefficients in q^-1 -> same-length descending powers of z."""
    L = max(len(num), len(den))
    return np.pad(num, (0, L - len(num))), np.pad(den, (0, L - len(den)))


def d2c(model, method: str = "tustin") -> ContinuousTF:
    """Discrete model -> continuous transfer functions with dead time.

    `method="zoh"`: exact inverse of zero-order-hold sampling (matrix logarithm), dead time
    (nk - 1) dt; `method="tustin"`: bilinear s = (2/dt)(z - 1)/(z + 1), dead time nk dt (as
    the thesis did). Covariance is not converted.
    """
    if method not in ("zoh", "tustin"):
        raise ValueError(f"method: unknown {method!r}; use 'zoh' or 'tustin'")
    tf = _as_tf(model)
    if isinstance(tf, ContinuousTF):
        raise ValueError("model: already continuous")
    dt = tf.dt
    nums, dens, delay = [], [], np.zeros((len(tf.num), len(tf.num[0])))
    for i, (nrow, drow) in enumerate(zip(tf.num, tf.den)):
        nr, dr = [], []
        for l, (n, d) in enumerate(zip(nrow, drow)):
            nk = int(np.argmax(n != 0)) if np.any(n) else 0
            rest = n[nk:]
            if method == "zoh":
                lead = min(nk, 1)  # keep one sample of delay in the strictly proper part
                rest = np.concatenate([np.zeros(lead), rest])
                delay[i, l] = (nk - lead) * dt
                nz, dz = _q_to_z(rest, d)
                A, B, C, D = _ss(nz, dz)
                n_x = len(A)
                M = np.eye(n_x + 1)
                M[:n_x, :n_x] = A
                M[:n_x, n_x:] = B
                Lg = _logm_real(M) / dt
                ns, ds = _tf_from_ss(Lg[:n_x, :n_x], Lg[:n_x, n_x:], C, D)
            else:
                delay[i, l] = nk * dt
                nz, dz = _q_to_z(rest, d)
                deg = len(dz) - 1
                ns, ds = np.zeros(1), np.zeros(1)
                for k in range(deg + 1):
                    basis = (np.poly1d([dt, 2.0]) ** (deg - k) * np.poly1d([-dt, 2.0]) ** k).coeffs
                    ns = np.polyadd(ns, nz[k] * basis)
                    ds = np.polyadd(ds, dz[k] * basis)
            ns, ds = np.atleast_1d(np.real(ns)), np.atleast_1d(np.real(ds))
            ds = np.trim_zeros(ds, "f")
            nr.append(np.trim_zeros(ns, "f") / ds[0] if np.any(ns) else np.zeros(1))
            dr.append(ds / ds[0])
        nums.append(tuple(nr))
        dens.append(tuple(dr))
    return ContinuousTF(tuple(nums), tuple(dens), delay, method, dt, tf.resampled)


def c2d(model: ContinuousTF, dt: float, method: str = "zoh") -> DiscreteTF:
    """Continuous transfer functions -> `DiscreteTF` by ZOH (exact for held inputs) or
    Tustin. Dead times must be whole multiples of `dt` [s]."""
    if method not in ("zoh", "tustin"):
        raise ValueError(f"method: unknown {method!r}; use 'zoh' or 'tustin'")
    if not isinstance(model, ContinuousTF):
        raise ValueError("model: pass a ContinuousTF (from d2c or built by hand)")
    if not dt > 0:
        raise ValueError(f"dt: must be > 0 s, got {dt!r}")
    nums, dens = [], []
    for i, (nrow, drow) in enumerate(zip(model.num, model.den)):
        nr, dr = [], []
        for l, (n, d) in enumerate(zip(nrow, drow)):
            samples = model.delay_s[i, l] / dt
            if abs(samples - round(samples)) > 1e-6:
                raise ValueError(
                    f"dt: delay {model.delay_s[i, l]} s is not a whole number "
                    "of samples; choose dt dividing the delay"
                )
            deg = len(d) - 1
            if len(n) > len(d):
                raise ValueError("model: improper transfer function (num degree > den)")
            nd = np.pad(np.asarray(n, float), (len(d) - len(n), 0))
            if method == "zoh":
                A, B, C, D = _ss(nd, d)
                n_x = len(A)
                M = np.zeros((n_x + 1, n_x + 1))
                M[:n_x, :n_x] = A * dt
                M[:n_x, n_x:] = B * dt
                E = _expm(M)
                nz, dz = _tf_from_ss(E[:n_x, :n_x], E[:n_x, n_x:], C, D)
            else:  # s = (2/dt)(z - 1)/(z + 1), multiply through by (z + 1)^deg
                nz, dz = np.zeros(1), np.zeros(1)
                for k in range(deg + 1):
                    basis = (
                        np.poly1d([2.0 / dt, -2.0 / dt]) ** (deg - k) * np.poly1d([1.0, 1.0]) ** k
                    )
                    nz = np.polyadd(nz, nd[k] * basis.coeffs)
                    dz = np.polyadd(dz, d[k] * basis.coeffs)
            nz, dz = np.asarray(nz, float), np.asarray(dz, float)
            nz, dz = nz / dz[0], dz / dz[0]
            nz[np.abs(nz) < 1e-12 * np.abs(nz).max(initial=0.0)] = 0.0  # round-off tails
            nz = np.trim_zeros(nz, "b") if np.any(nz) else np.zeros(1)
            nr.append(np.concatenate([np.zeros(int(round(samples))), nz]))
            dr.append(dz)
        nums.append(tuple(nr))
        dens.append(tuple(dr))
    return DiscreteTF(tuple(nums), tuple(dens), float(dt), model.resampled)


def to_control(model, form: str = "tf", pade_order: int | None = None):
    """Export to python-control (`pip install greybox[control]`) as `TransferFunction`
    (`form="tf"`) or `StateSpace` (`form="ss"`).

    Discrete models keep their delays exactly (powers of z^-1) and `dt`. Continuous models
    with dead time need `pade_order` (a Pade approximation of exp(-s delay)).
    """
    try:
        import control
    except ImportError as err:  # optional extra
        raise ImportError(
            "to_control needs python-control: pip install 'greybox[control]'"
        ) from err
    if form not in ("tf", "ss"):
        raise ValueError(f"form: unknown {form!r}; use 'tf' or 'ss'")
    tf = _as_tf(model)
    if isinstance(tf, DiscreteTF):
        num, den = [], []
        for nrow, drow in zip(tf.num, tf.den):
            pairs = [_q_to_z(n, d) for n, d in zip(nrow, drow)]
            num.append([list(p[0]) for p in pairs])
            den.append([list(p[1]) for p in pairs])
        sys = control.tf(num, den, tf.dt)
    else:
        if np.any(tf.delay_s > 0) and pade_order is None:
            raise ValueError(
                "pade_order: the model has dead time; pass pade_order (e.g. 3) "
                "to approximate exp(-s delay), or use the DiscreteTF"
            )
        rows = []
        for i, (nrow, drow) in enumerate(zip(tf.num, tf.den)):
            row = []
            for l, (n, d) in enumerate(zip(nrow, drow)):
                g = control.tf(list(n), list(d))
                if tf.delay_s[i, l] > 0:
                    g = g * control.tf(*control.pade(tf.delay_s[i, l], pade_order))
                row.append(g)
            rows.append(row)
        if len(rows) == 1 and len(rows[0]) == 1:
            sys = rows[0][0]
        else:
            sys = control.tf(
                [[list(np.atleast_1d(g.num[0][0])) for g in r] for r in rows],
                [[list(np.atleast_1d(g.den[0][0])) for g in r] for r in rows],
            )
    return control.ss(sys) if form == "ss" else sys
