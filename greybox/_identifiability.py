"""What the data can and cannot identify, from the weighted Jacobian at the optimum.

Work in raw (transformed) coordinates, where log-parameters make "sd 0.5" mean "about +-50 %":

- data Fisher information F_d = J_d^T J_d (rows = residuals / sigma), prior information
  F_p = J_p^T J_p, posterior covariance (F_d + F_p)^-1 (the Gauss-Newton Hessian);
- singular values of J_d: a direction with data-only standard deviation 1/s_i > 0.5 (or a
  numerically zero s_i) is a parameter combination the data do not pin down; it is reported as
  a signed combination of raw coordinates (e.g. +0.71 log(A) + 0.71 log(R): only A/R is known);
- per parameter: "identifiable" when the data alone give sd < 0.5 in raw units (and the prior
  is not what constrains it), "prior-dominated" when a prior is present and the posterior sd is
  more than half the prior sd (the data shrank it less than 2x), else "not identifiable".
"""

from __future__ import annotations

import dataclasses

import numpy as np

WEAK_SD = 0.5  # raw-unit sd above which a direction or parameter counts as not identified
PRIOR_SHRINK = 0.25  # posterior var / prior var above this => prior-dominated
TINY = 1e-10  # relative singular value treated as exactly zero


@dataclasses.dataclass(frozen=True)
class WeakDirection:
    sd_raw: float  # data-only standard deviation along this direction (inf if singular)
    combination: dict  # raw-coordinate label -> coefficient (unit vector, small terms dropped)

    def describe(self) -> str:
        terms = " ".join(f"{c:+.2f}*{name}" for name, c in self.combination.items())
        sd = "unbounded" if not np.isfinite(self.sd_raw) else f"sd {self.sd_raw:.2g}"
        return f"{terms} ({sd})"


@dataclasses.dataclass(frozen=True)
class IdentifiabilityReport:
    singular_values: np.ndarray  # of the weighted data Jacobian in raw coordinates
    condition_number: float
    weak_directions: tuple
    verdicts: tuple  # one per raw coordinate
    data_sd_raw: np.ndarray  # sd from the data alone (inf where unconstrained)
    covariance_raw: np.ndarray  # posterior (data + priors) on the determined subspace
    null_directions: np.ndarray  # (k, n) unit vectors nothing determines (k = 0 usually)
    raw_labels: tuple

    @property
    def undetermined(self) -> np.ndarray:
        """(n,) True for raw coordinates with no finite uncertainty."""
        return undetermined(self.null_directions, self.covariance_raw.shape[0])

    def summary(self) -> list[str]:
        lines = [
            f"singular values of the weighted Jacobian: "
            f"{', '.join(f'{s:.3g}' for s in self.singular_values)} "
            f"(condition number {self.condition_number:.3g})"
        ]
        if self.weak_directions:
            lines.append("parameter combinations the data do not determine:")
            lines += [f"  {w.describe()}" for w in self.weak_directions]
        else:
            lines.append("every freed parameter combination is determined by the data")
        return lines


def _pseudo_inverse(matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(inverse on the determined subspace, unit vectors spanning the undetermined one).

    An information matrix with (numerically) zero eigenvalues has directions about which the
    data and priors say nothing; they are excluded from the inverse and returned separately.
    """
    vals, vecs = np.linalg.eigh(matrix)
    keep = vals > max(vals.max(), 1e-300) * TINY
    inv = (vecs[:, keep] / vals[keep]) @ vecs[:, keep].T
    return inv, vecs[:, ~keep].T


def undetermined(null_directions: np.ndarray, n: int) -> np.ndarray:
    """Coordinates with real weight on an undetermined direction (rounding-level weights,
    < 1e-6, do not count: an identifiable parameter next to an unidentifiable pair stays)."""
    if null_directions.size == 0:
        return np.zeros(n, dtype=bool)
    return np.sum(null_directions**2, axis=0) > 1e-6


def analyse(
    jac_data: np.ndarray, jac_prior: np.ndarray, free_flat, raw: np.ndarray, labels
) -> IdentifiabilityReport:
    """Identifiability from the weighted data Jacobian `jac_data` (rows: residual / sigma) and
    the prior rows `jac_prior`, both in raw coordinates; `free_flat[k]` is the FreeParameter
    of raw coordinate k and `labels[k]` its display name."""
    n = raw.size
    raw_labels = tuple(
        p.raw_label().replace(p.path, label, 1) for p, label in zip(free_flat, labels)
    )
    if not np.all(np.isfinite(jac_data)):
        nan = np.full(n, np.nan)
        return IdentifiabilityReport(
            nan,
            float("nan"),
            (),
            ("not identifiable",) * n,
            nan,
            np.full((n, n), np.nan),
            np.eye(n),
            raw_labels,
        )
    # the singular values of a tall J equal those of its small R factor: QR first is far cheaper
    _, s, vt = np.linalg.svd(np.linalg.qr(jac_data, mode="r"))
    s_max = s.max() if s.size else 0.0
    safe_s = np.where(s > s_max * TINY, s, 0.0)
    with np.errstate(divide="ignore"):
        inv_s = np.where(safe_s > 0, 1.0 / np.where(safe_s > 0, safe_s, 1.0), np.inf)
    weak = []
    for i in range(s.size):
        if inv_s[i] > WEAK_SD:
            comb = {
                raw_labels[j]: float(vt[i, j])
                for j in np.argsort(-np.abs(vt[i]))
                if abs(vt[i, j]) > 0.1
            }
            weak.append(WeakDirection(float(inv_s[i]), comb))
    # Data-only variance per coordinate from the determined directions; a coordinate with real
    # weight on an exactly singular direction is unbounded. Rounding leaves ~1e-9 weights on
    # null directions for coordinates orthogonal to them, which must not count.
    null = ~np.isfinite(inv_s)
    null_weight = np.sum(vt[null].T ** 2, axis=1) if null.any() else np.zeros(n)
    data_var = np.sum(vt[~null].T ** 2 * inv_s[~null] ** 2, axis=1)
    data_var = np.where(null_weight > 1e-6, np.inf, data_var)
    fisher = jac_data.T @ jac_data + (jac_prior.T @ jac_prior if jac_prior.size else 0.0)
    cov, null_dirs = _pseudo_inverse(fisher)
    lost = undetermined(null_dirs, n)

    verdicts = []
    for k, p in enumerate(free_flat):
        post_var = np.inf if lost[k] else cov[k, k]
        if p.has_prior:
            value = float(p.to_value(raw[k]))
            dlog = p.value_derivative(raw[k]) / value
            prior_var_raw = (p.prior_log_sd / abs(dlog)) ** 2
            verdict = (
                "prior-dominated"
                if not post_var <= PRIOR_SHRINK * prior_var_raw
                else "identifiable"
            )
        else:
            verdict = "identifiable" if np.sqrt(data_var[k]) < WEAK_SD else "not identifiable"
        verdicts.append(verdict)
    cond = float(s_max / s.min()) if s.size and s.min() > 0 else float("inf")
    return IdentifiabilityReport(
        s, cond, tuple(weak), tuple(verdicts), np.sqrt(data_var), cov, null_dirs, raw_labels
    )
