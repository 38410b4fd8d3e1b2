"""Polynomial curve and surface fits by linear least squares, as in thesis ch. 5 (pure numpy).

The thesis fitted z(amplitude, frequency) with a MATLAB "poly32" surface (R^2 = 99.30 %, RMSE
0.1327 um) and the sensor force with 8th- and 2nd-order polynomials in voltage. Here:

- `check_grid`: an amplitude-frequency table must be a full grid (no missing or repeated cells,
  amplitudes >= 0 V, frequencies >= 0 Hz);
- `polynomial_terms`: MATLAB-style exponents, x^i y^j with i <= dx, j <= dy, i + j <= max(dx, dy)
  (an int d means total degree d), in MATLAB's order p00, p10, p01, p20, p11, p02, ...;
- `fit_polynomial`: column-scaled least squares (well conditioned for 0-400 Hz ranges) with
  R^2, RMSE, AIC/AICc/BIC (Gaussian errors, variance profiled out);
- `grid`: the fitted surface on a fine grid (the thesis used 0.1 V x 1 Hz);
- `cross_validate`: leave-one-group-out prediction error (e.g. leave one voltage out), for any
  fit function, so polynomials and grey-box models are scored the same way.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np

from greybox.metrics import r_squared, rmse


def _finite(name: str, values) -> np.ndarray:
    v = np.asarray(values, dtype=float).reshape(-1)
    if v.size == 0:
        raise ValueError(f"{name}: empty; give at least one value")
    if not np.all(np.isfinite(v)):
        raise ValueError(
            f"{name}: contains NaN or inf at row {int(np.argmin(np.isfinite(v)))}; "
            "remove or fill those rows"
        )
    return v


def check_grid(amplitude_V, frequency_Hz, values):
    """(amplitudes (na,), frequencies (nf,), table (na, nf)) from a long-format table.

    Raises a ValueError for negative amplitudes or frequencies, mismatched lengths, repeated
    cells, and ragged tables (an amplitude that lacks some frequency), naming the missing cell.
    """
    a = _finite("amplitude_V", amplitude_V)
    f = _finite("frequency_Hz", frequency_Hz)
    z = _finite("values", values)
    if not a.size == f.size == z.size:
        raise ValueError(
            f"table: columns have different lengths (amplitude {a.size}, frequency "
            f"{f.size}, values {z.size})"
        )
    if np.any(a < 0):
        raise ValueError(
            f"amplitude_V: negative voltage range (min {a.min():g} V); the square "
            "wave runs from 0 V to the amplitude, give amplitudes >= 0 V"
        )
    if np.any(f < 0):
        raise ValueError(f"frequency_Hz: negative frequency ({f.min():g} Hz); give >= 0 Hz")
    amps, freqs = np.unique(a), np.unique(f)
    ia, jf = np.searchsorted(amps, a), np.searchsorted(freqs, f)
    table = np.full((amps.size, freqs.size), np.nan)
    seen = np.zeros(table.shape, dtype=int)
    np.add.at(seen, (ia, jf), 1)
    if np.any(seen > 1):
        i, j = np.argwhere(seen > 1)[0]
        raise ValueError(
            f"table: the cell amplitude {amps[i]:g} V, frequency {freqs[j]:g} Hz "
            "appears more than once; average repeats before fitting"
        )
    if np.any(seen == 0):
        i, j = np.argwhere(seen == 0)[0]
        raise ValueError(
            f"table: ragged amplitude-frequency table, {int((seen == 0).sum())} cells "
            f"missing (e.g. amplitude {amps[i]:g} V at {freqs[j]:g} Hz); every "
            "amplitude needs the same frequencies"
        )
    table[ia, jf] = z
    return amps, freqs, table


def polynomial_terms(degree) -> np.ndarray:
    """Exponents (p, k): int d -> 1-D powers 0..d (k = 1); (dx, dy) -> 2-D MATLAB polyXY terms."""
    if np.ndim(degree) == 0:
        d = int(degree)
        if d != degree or d < 0:
            raise ValueError(f"degree: {degree} must be a whole number >= 0")
        return np.arange(d + 1)[:, None]
    dx, dy = (int(d) for d in degree)
    if dx < 0 or dy < 0:
        raise ValueError(f"degree: {degree} must be >= 0 in each variable")
    top = max(dx, dy)
    terms = [
        (i, t - i) for t in range(top + 1) for i in range(t, -1, -1) if i <= dx and t - i <= dy
    ]
    return np.asarray(terms)


def design_matrix(x, exponents: np.ndarray) -> np.ndarray:
    """(N, p) monomials of the columns of `x` (N, k) raised to `exponents` (p, k)."""
    x = np.asarray(x, dtype=float).reshape(len(x), -1)
    return np.prod(x[:, None, :] ** exponents[None, :, :], axis=2)


def information_criteria(rss: float, n: int, p: int) -> dict:
    """Gaussian AIC, AICc and BIC with the noise variance profiled out (RSS / n)."""
    if n <= 0:
        raise ValueError("n: no data")
    ll_term = n * np.log(max(rss, 1e-300) / n)
    aicc = ll_term + 2 * p + (2 * p * (p + 1) / (n - p - 1) if n - p - 1 > 0 else np.inf)
    return {"aic": ll_term + 2 * p, "aicc": aicc, "bic": ll_term + p * np.log(n)}


@dataclasses.dataclass(frozen=True)
class PolynomialFit:
    """A least-squares polynomial in one or two variables, with its goodness of fit.

    `coefficients[k]` multiplies prod(x_j ** exponents[k, j]). R^2 and `rmse` = sqrt(RSS / n) are
    in-sample; `rmse_dof` = sqrt(RSS / (n - p)) is what MATLAB's Curve Fitting Toolbox calls RMSE.
    `criteria` holds AIC, AICc and BIC (`information_criteria`).
    """

    exponents: np.ndarray
    coefficients: np.ndarray
    r_squared: float
    rmse: float
    rmse_dof: float
    n_data: int
    criteria: dict

    @property
    def n_params(self) -> int:
        return len(self.coefficients)

    def __call__(self, *xs):
        shape = np.broadcast(*[np.asarray(x, float) for x in xs]).shape
        cols = np.column_stack(
            [np.broadcast_to(np.asarray(x, float), shape).reshape(-1) for x in xs]
        )
        return (design_matrix(cols, self.exponents) @ self.coefficients).reshape(shape)

    def describe(self, names=("x", "y"), digits: int = 4) -> str:
        parts = []
        for c, e in zip(self.coefficients, self.exponents):
            mono = "*".join(f"{n}^{p}" if p > 1 else n for n, p in zip(names, e) if p > 0)
            parts.append(f"{c:+.{digits}g}" + (f"*{mono}" if mono else ""))
        return " ".join(parts)


def fit_polynomial(x, z, degree, *, weights=None) -> PolynomialFit:
    """Least-squares polynomial z ~ P(x): `x` (N,) or (N, 2), `degree` int or (dx, dy).

    `weights` (N,) >= 0 multiply the residuals (e.g. 1 / standard error); R^2 and RMSE stay
    unweighted, as reported in the thesis.
    """
    x = np.asarray(x, dtype=float)
    x = x.reshape(len(x), -1)
    z = _finite("z", z)
    if not np.all(np.isfinite(x)):
        raise ValueError("x: contains NaN or inf; remove those rows")
    exps = polynomial_terms(degree)
    if exps.shape[1] != x.shape[1]:
        raise ValueError(
            f"degree: {degree} is for {exps.shape[1]} variable(s) but x has {x.shape[1]} column(s)"
        )
    n, p = z.size, len(exps)
    if n < p:
        raise ValueError(
            f"degree: {p} coefficients cannot be determined from {n} points; lower "
            "the degree or add data"
        )
    a = design_matrix(x, exps)
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=float).reshape(-1)
    if w.shape != (n,) or np.any(~np.isfinite(w)) or np.any(w < 0):
        raise ValueError("weights: need one finite value >= 0 per point")
    aw = a * w[:, None]
    scale = np.linalg.norm(aw, axis=0)
    scale[scale == 0] = 1.0
    coef, *_ = np.linalg.lstsq(aw / scale, z * w, rcond=None)
    coef = coef / scale
    z_hat = a @ coef
    rss = float(np.sum((z - z_hat) ** 2))
    return PolynomialFit(
        exponents=exps,
        coefficients=coef,
        r_squared=r_squared(z, z_hat),
        rmse=rmse(z, z_hat),
        rmse_dof=float(np.sqrt(rss / (n - p))) if n > p else float("nan"),
        n_data=n,
        criteria=information_criteria(rss, n, p),
    )


def grid(fit: PolynomialFit, x_range, y_range, *, dx: float = 0.1, dy: float = 1.0):
    """(x (nx,), y (ny,), z (nx, ny)) of a 2-D fit on a fine grid (thesis: 0.1 V x 1 Hz)."""
    if not (dx > 0 and dy > 0):
        raise ValueError("dx, dy: grid steps must be > 0")
    xs = np.arange(x_range[0], x_range[1] + dx / 2, dx)
    ys = np.arange(y_range[0], y_range[1] + dy / 2, dy)
    xx, yy = np.meshgrid(xs, ys, indexing="ij")
    return xs, ys, fit(xx, yy)


@dataclasses.dataclass(frozen=True)
class CrossValidation:
    """Held-out predictions: `predictions[i]` was made by a fit that never saw group of row i."""

    predictions: np.ndarray
    groups: np.ndarray
    rmse: float  # over all held-out points, units of z
    rmse_interior: float  # excluding groups at the ends (pure interpolation, no extrapolation)


def cross_validate(fit_and_predict: Callable, x, z, groups=None) -> CrossValidation:
    """Leave-one-group-out cross-validation for any model.

    `fit_and_predict(train_mask (N,) bool, x, z) -> z_hat (N,)` fits on the rows where the mask
    is True and predicts every row. `groups` (N,) labels rows left out together (default: each
    row alone; for repeated readings pass the voltage). Interior RMSE leaves out the smallest
    and largest group labels, so it measures interpolation only.
    """
    z = np.asarray(z, dtype=float).reshape(-1)
    groups = np.arange(z.size) if groups is None else np.asarray(groups).reshape(-1)
    if groups.shape != z.shape:
        raise ValueError("groups: need one label per row")
    labels = np.unique(groups)
    if labels.size < 3:
        raise ValueError("groups: cross-validation needs at least 3 groups")
    pred = np.full(z.shape, np.nan)
    for g in labels:
        held = groups == g
        pred[held] = np.asarray(fit_and_predict(~held, x, z)).reshape(-1)[held]
    interior = (groups != labels[0]) & (groups != labels[-1])
    return CrossValidation(pred, groups, rmse(z, pred), rmse(z[interior], pred[interior]))


def polynomial_predictor(degree, *, weights=None) -> Callable:
    """A `fit_and_predict` for `cross_validate` that fits `fit_polynomial(..., degree)`."""

    def fit_and_predict(train, x, z):
        x = np.asarray(x, dtype=float).reshape(len(z), -1)
        w = None if weights is None else np.asarray(weights)[train]
        return fit_polynomial(x[train], np.asarray(z)[train], degree, weights=w)(*x.T)

    return fit_and_predict
