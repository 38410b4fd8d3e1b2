"""What the data can and cannot identify, from the weighted Jacobian at the optimum.

Work in raw (transformed) coordinates, where log-parameters make "sd 0.5" mean "about +-50 %":

- one factorisation: the SVD of the column-scaled Jacobian J D^-1 (D = column norms), and one
  rank threshold: a direction whose singular value is below `RANK_TOL` times the largest is
  numerically undetermined. The posterior covariance (Gauss-Newton, data + prior rows) is
  D^-1 V S^-2 V^T D^-1 on the determined subspace and the data-only covariance is the same
  construction on the data rows. Because D absorbs any per-coordinate scale, the covariance,
  the standard errors in SI and the rank decision do not depend on how a parameter is scaled
  (`FreeParameter.scale`) or on the units of its raw coordinate;
- the weak directions are the principal axes of the data-only covariance in raw coordinates
  with sd > `WEAK_SD` (a combination the data pin down only to within +-50 % or worse), plus
  the undetermined directions (sd unbounded), each reported as a signed combination of raw
  coordinates (e.g. +0.71 log(A) + 0.71 log(R): only A/R is known);
- per parameter: "at bound" when the fit ended on one of its bounds (the optimum is on the
  boundary, so no interval is meaningful); "identifiable" when the data alone give sd <
  `WEAK_SD` in raw units (and the prior is not what constrains it); "prior-dominated" when a
  prior is present and the posterior sd is more than half the prior sd (the data shrank it
  less than 2x); else "not identifiable". For an unbounded parameter, raw units are
  value / scale: its `scale` states the magnitude that "+-0.5 raw" is measured against.
"""

from __future__ import annotations

import dataclasses

import numpy as np

WEAK_SD = 0.5  # raw-unit sd above which a direction or parameter counts as not identified
PRIOR_SHRINK = 0.25  # posterior var / prior var above this => prior-dominated
RANK_TOL = 1e-8  # singular value of the column-scaled Jacobian, relative, treated as zero
TINY = RANK_TOL**2  # the same threshold on eigenvalues of an information matrix J^T J
ZERO_COLUMN = 1e-10  # column norm (relative to the largest) below which a column is zero:
# raw coordinates are scaled to their values, so real columns differ by far less
ON_NULL = 1e-6  # squared weight on an undetermined direction that makes a coordinate undetermined
VERDICTS = ("identifiable", "prior-dominated", "not identifiable", "at bound", "not needed")


@dataclasses.dataclass(frozen=True)
class WeakDirection:
    sd_raw: float  # data-only standard deviation along this direction (inf if undetermined)
    combination: dict  # raw-coordinate label -> coefficient (unit vector, small terms dropped)

    def describe(self) -> str:
        terms = " ".join(f"{c:+.2f}*{name}" for name, c in self.combination.items())
        sd = "unbounded" if not np.isfinite(self.sd_raw) else f"sd {self.sd_raw:.2g}"
        return f"{terms} ({sd})"


@dataclasses.dataclass(frozen=True)
class IdentifiabilityReport:
    """- `singular_values`, `condition_number`: of the column-scaled weighted data Jacobian
      (independent of parameter scaling; a zero means an undetermined combination).
    - `weak_directions`, `verdicts` (one per raw coordinate), `data_sd_raw` (data alone,
      inf where undetermined), `covariance_raw` (posterior, determined subspace),
      `null_directions` ((k, n) raw unit vectors nothing determines), `raw_labels`,
      `undetermined` ((n,) coordinates with real weight on a null direction), `bounds`
      (per coordinate: None, "lower" or "upper" when the fit ended on that bound).
    """

    singular_values: np.ndarray
    condition_number: float
    weak_directions: tuple
    verdicts: tuple
    data_sd_raw: np.ndarray
    covariance_raw: np.ndarray
    null_directions: np.ndarray
    raw_labels: tuple
    undetermined: np.ndarray
    bounds: tuple = ()

    def explain(self, k: int) -> str:
        """Why raw coordinate `k` is not identified, in words: the weak or undetermined
        combination that carries it most (every "not identifiable" verdict names one)."""
        label = self.raw_labels[k] if k < len(self.raw_labels) else None
        best, weight = None, 0.0
        for w in self.weak_directions:
            c = abs(w.combination.get(label, 0.0))
            if c > weight:
                best, weight = w, c
        if best is None:
            sd = self.data_sd_raw[k] if k < len(self.data_sd_raw) else float("nan")
            return f"data-only sd {sd:.2g} in raw units, no single weak combination"
        return f"weak combination {best.describe()}"

    def summary(self) -> list[str]:
        lines = [
            f"singular values of the column-scaled weighted Jacobian: "
            f"{', '.join(f'{s:.3g}' for s in self.singular_values)} "
            f"(condition number {self.condition_number:.3g})"
        ]
        if self.weak_directions:
            lines.append("parameter combinations the data do not determine:")
            lines += [f"  {w.describe()}" for w in self.weak_directions]
        else:
            lines.append("every freed parameter combination is determined by the data")
        return lines


@dataclasses.dataclass(frozen=True)
class ScaledFactor:
    """SVD of a column-scaled Jacobian: J D^-1 = U diag(s) Vt, D = `col_norm`; `keep` marks
    the singular values above RANK_TOL times the largest (the determined directions)."""

    col_norm: np.ndarray
    s: np.ndarray
    vt: np.ndarray
    keep: np.ndarray

    @staticmethod
    def of(jac: np.ndarray) -> ScaledFactor:
        jac = np.asarray(jac, dtype=float)
        n = jac.shape[1]
        d = np.linalg.norm(jac, axis=0)
        # a column at rounding level of the largest is zero: scaled up to unit norm, its
        # rounding noise would mix with every other column (a likelihood fit's Jacobian from
        # its finite-difference Hessian, where a vanished noise intensity's column is ~1e-14
        # of the others, made every parameter "not identifiable")
        zero = ~(d > ZERO_COLUMN * (d.max() if d.size else 0.0))
        jac = np.where(zero[None, :], 0.0, jac)
        d = np.where(zero, 1.0, d)  # an all-zero column stays zero: exactly undetermined
        scaled = jac / d
        # the singular values of a tall J equal those of its small R factor: QR first is cheaper
        r = np.linalg.qr(scaled, mode="r") if scaled.shape[0] > n else scaled
        _, s, vt = np.linalg.svd(r)
        s = np.concatenate([s, np.zeros(n - s.size)])
        if vt.shape[0] < n:  # fewer rows than coordinates: complete the basis
            q, _ = np.linalg.qr(vt.T, mode="complete")
            vt = np.vstack([vt, q[:, vt.shape[0] :].T])
        keep = s > (s[0] if s.size else 0.0) * RANK_TOL
        return ScaledFactor(d, s, vt, keep)

    def covariance(self) -> np.ndarray:
        """(J^T J)^+ in raw coordinates on the determined subspace."""
        v = self.vt[self.keep].T / self.col_norm[:, None]
        return (v / self.s[self.keep] ** 2) @ v.T

    def undetermined(self) -> np.ndarray:
        """(n,) coordinates with real weight on an undetermined direction (rounding-level
        weights do not count: an identifiable parameter next to an unidentifiable pair stays)."""
        null = self.vt[~self.keep]
        if null.size == 0:
            return np.zeros(self.vt.shape[1], dtype=bool)
        return np.sum(null**2, axis=0) > ON_NULL

    def null_directions(self) -> np.ndarray:
        """(k, n) orthonormal raw-coordinate directions nothing determines."""
        null = self.vt[~self.keep] / self.col_norm[None, :]
        if null.size == 0:
            return np.zeros((0, self.vt.shape[1]))
        q, _ = np.linalg.qr(null.T)
        return q.T


def _pseudo_inverse(matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(inverse on the determined subspace, unit vectors spanning the undetermined one) of an
    information matrix, with the same column scaling and rank threshold as `ScaledFactor`."""
    d = np.sqrt(np.clip(np.diag(matrix), 0, None))
    d = np.where(d > 0, d, 1.0)
    vals, vecs = np.linalg.eigh(matrix / np.outer(d, d))
    keep = vals > max(vals.max(), 1e-300) * RANK_TOL**2
    v = vecs[:, keep] / d[:, None]
    inv = (v / vals[keep]) @ v.T
    null = vecs[:, ~keep] / d[:, None]
    if null.size:
        null, _ = np.linalg.qr(null)
    return inv, null.T


def undetermined(null_directions: np.ndarray, n: int) -> np.ndarray:
    """Coordinates with real weight on an undetermined direction (rounding-level weights,
    < 1e-6, do not count: an identifiable parameter next to an unidentifiable pair stays)."""
    if null_directions.size == 0:
        return np.zeros(n, dtype=bool)
    return np.sum(null_directions**2, axis=0) > 1e-6


def analyse(
    jac_data: np.ndarray, jac_prior: np.ndarray, free_flat, raw: np.ndarray, labels, bounds=None
) -> IdentifiabilityReport:
    """Identifiability from the weighted data Jacobian `jac_data` (rows: residual / sigma) and
    the prior rows `jac_prior`, both in raw coordinates; `free_flat[k]` is the FreeParameter
    of raw coordinate k, `labels[k]` its display name and `bounds[k]` None, "lower" or
    "upper" (the bound the fit ended on, see `FreeParameter.bound_hit`)."""
    n = raw.size
    bounds = tuple(bounds) if bounds is not None else (None,) * n
    raw_labels = tuple(
        p.raw_label().replace(p.path, label, 1) for p, label in zip(free_flat, labels)
    )
    jac_prior = np.asarray(jac_prior, dtype=float).reshape(-1, n)
    if not np.all(np.isfinite(jac_data)) or not np.all(np.isfinite(jac_prior)):
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
            np.ones(n, dtype=bool),
            bounds,
        )
    data = ScaledFactor.of(jac_data)
    post = ScaledFactor.of(np.vstack([jac_data, jac_prior])) if jac_prior.size else data
    data_cov = data.covariance()
    data_lost = data.undetermined()
    data_var = np.where(data_lost, np.inf, np.diag(data_cov))
    cov = post.covariance()
    lost = post.undetermined()

    weak = []
    for v in data.null_directions():
        weak.append(_weak(v, np.inf, raw_labels))
    vals, vecs = np.linalg.eigh(data_cov)
    for i in np.argsort(-vals):
        if np.sqrt(max(vals[i], 0.0)) > WEAK_SD:
            weak.append(_weak(vecs[:, i], float(np.sqrt(vals[i])), raw_labels))

    verdicts = []
    for k, p in enumerate(free_flat):
        if bounds[k] == "not needed":  # a noise level at zero: an answer, not a failure
            verdicts.append("not needed")
            continue
        if bounds[k] is not None:
            verdicts.append("at bound")
            continue
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
    s = data.s
    cond = float(s[0] / s[-1]) if s.size and s[-1] > 0 else float("inf")
    return IdentifiabilityReport(
        s,
        cond,
        tuple(weak),
        tuple(verdicts),
        np.sqrt(data_var),
        cov,
        post.null_directions(),
        raw_labels,
        lost,
        bounds,
    )


def _weak(v: np.ndarray, sd: float, raw_labels) -> WeakDirection:
    v = v / np.linalg.norm(v)
    if v[np.argmax(np.abs(v))] < 0:
        v = -v
    comb = {raw_labels[j]: float(v[j]) for j in np.argsort(-np.abs(v)) if abs(v[j]) > 0.1}
    return WeakDirection(sd, comb)
