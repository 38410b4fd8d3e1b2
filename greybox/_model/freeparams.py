"""Free parameters of a fit: which model field, how it is transformed, its prior.

The optimiser works on unconstrained raw values; each `FreeParameter` maps raw <-> physical:

- both bounds: ``value = lower + (upper - lower) * sigmoid(raw)`` (bounded, "logit"),
- a lower bound only: ``value = lower + exp(raw)`` (positive, "log"; log-space steps suit
  parameters that span decades),
- no bounds: ``value = scale * raw`` ("linear"; `scale` keeps raw O(1), e.g. 1e-6 for m).
  Left at None, `fit` derives it from the starting value (|start|, or 1 for a start of 0) and
  records the number in `FitResult.free`. Values, standard errors, intervals and the rank
  decision of a fit do not depend on `scale` (the covariance is computed from a column-scaled
  Jacobian); it only sets the optimiser's raw step and, for the verdict, what "a typical
  magnitude" of the parameter is.

A value that ends within `AT_BOUND_FRACTION` of its range from a bound (|logit| > 6.9), or a
lower-bounded value that shrank to within that fraction of its starting distance from the
bound, is "at bound": the optimum lies on the boundary, not inside it. For bounds that span
decades (lower > 0 and upper / lower >= 100) the range is measured in log space: with bounds
1..1e4, 5.3 is not at bound (18 % of the log range) and 1.0001 is; with 1e-4..1 s, 1.06e-3 s
is not.

Fields not listed stay fixed at the model's value. A parameter may be shared by all
experiments or estimated once per experiment (offsets, drift, initial temperature). An
optional Gaussian prior on log(value) (median, log-sd) encodes what the data cannot identify.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

AT_BOUND_FRACTION = 1e-3  # distance to a bound, as a fraction of the range, that counts as "at"
LOG_SCALED_RATIO = 100.0  # bounds spanning this ratio or more: "at bound" judged in log space


@dataclasses.dataclass(frozen=True)
class FreeParameter:
    """- `path`: dotted field path in the model, e.g. ``"thermal.tau_s"``.
    - `unit`: display unit of the SI value (``"s"``, ``"K/W"``, ``"m"``, ``"1"``).
    - `lower`, `upper`: physical bounds (None = unbounded on that side).
    - `per_experiment`: one value per experiment instead of one shared value.
    - `prior_median`, `prior_log_sd`: Gaussian prior on log(value) (needs a positive value).
    - `initial`: starting value (default: the model's current value). Not part of the
      parameter's identity (equality, hash): two parameters that differ only in where they
      start share one compiled solver.
    - `scale`: typical magnitude [unit], used only by unbounded ("linear") parameters; None
      derives it from the starting value when fitting (see the module docstring).
    """

    path: str
    unit: str = ""
    lower: float | None = None
    upper: float | None = None
    per_experiment: bool = False
    prior_median: float | None = None
    prior_log_sd: float | None = None
    # the starting value is read on the host only (the raw start vector is a dynamic input):
    # left out of equality and hash, a new device's starts never make a new compiled solver
    initial: float | None = dataclasses.field(default=None, compare=False)
    scale: float | None = None

    def __post_init__(self):
        if self.lower is not None and self.upper is not None and not self.upper > self.lower:
            raise ValueError(
                f"{self.path}: upper bound {self.upper} must exceed lower {self.lower}"
            )
        if (self.prior_median is None) != (self.prior_log_sd is None):
            raise ValueError(f"{self.path}: give both prior_median and prior_log_sd, or neither")
        if self.prior_median is not None:
            if not self.prior_median > 0 or not self.prior_log_sd > 0:
                raise ValueError(
                    f"{self.path}: a log-normal prior needs prior_median > 0 and prior_log_sd > 0"
                )
        if self.upper is not None and self.lower is None:
            raise ValueError(f"{self.path}: an upper bound needs a lower bound too")
        if self.scale is not None and not self.scale > 0:
            raise ValueError(f"{self.path}: scale must be > 0 (or None to derive it)")

    @property
    def transform(self) -> str:
        if self.lower is not None and self.upper is not None:
            return "logit"
        if self.lower is not None:
            return "log"
        return "linear"

    @property
    def log_scaled(self) -> bool:
        """Bounds that span decades (lower > 0, upper / lower >= `LOG_SCALED_RATIO`): the
        parameter's scale is logarithmic, and "at bound" is judged in log space."""
        return (
            self.transform == "logit"
            and self.lower > 0
            and self.upper / self.lower >= LOG_SCALED_RATIO
        )

    @property
    def has_prior(self) -> bool:
        return self.prior_median is not None

    @property
    def step(self) -> float:
        """The linear transform's scale (1 while `scale` is None and not yet derived)."""
        return 1.0 if self.scale is None else float(self.scale)

    def with_scale_from(self, start: float) -> FreeParameter:
        """This parameter with `scale` derived from the starting value `start` when it is None
        (|start|, or 1 for a start of 0); bounded parameters and explicit scales are kept."""
        if self.transform != "linear" or self.scale is not None:
            return self
        v = abs(float(start))
        return dataclasses.replace(self, scale=v if np.isfinite(v) and v > 0 else 1.0)

    def bound_hit(self, raw: float, raw_start: float) -> str | None:
        """ "lower" or "upper" when the value at `raw` sits on that bound (see the module
        docstring), else None. `raw_start` is where the fit started (for a lower bound only)."""
        raw = float(raw)
        if self.log_scaled:
            # judged where the parameter lives: the fraction of the log range from a bound
            value = float(self.to_value(raw))
            lo, hi = np.log(self.lower), np.log(self.upper)
            frac = (np.log(max(value, self.lower)) - lo) / (hi - lo)
            return "lower" if frac < AT_BOUND_FRACTION else (
                "upper" if frac > 1.0 - AT_BOUND_FRACTION else None
            )
        if self.transform == "logit":
            edge = float(np.log(AT_BOUND_FRACTION / (1.0 - AT_BOUND_FRACTION)))  # -6.9
            return "lower" if raw < edge else "upper" if raw > -edge else None
        if self.transform == "log":
            return "lower" if raw - float(raw_start) < np.log(AT_BOUND_FRACTION) else None
        return None

    def check_value(self, value: float) -> None:
        """Raise a ValueError naming the parameter if `value` is outside its bounds."""
        v = float(value)
        if not np.isfinite(v):
            raise ValueError(f"{self.path}: initial value {v} is not finite")
        lo_ok = self.lower is None or v > self.lower
        hi_ok = self.upper is None or v < self.upper
        if not (lo_ok and hi_ok):
            raise ValueError(
                f"{self.path}: value {v} is outside its bounds "
                f"({self.lower}, {self.upper}) [{self.unit}]; change the initial "
                "value or the bounds"
            )

    def to_raw(self, value):
        v = jnp.asarray(value, dtype=float)
        if self.transform == "logit":
            p = (v - self.lower) / (self.upper - self.lower)
            return jnp.log(p) - jnp.log1p(-p)
        if self.transform == "log":
            return jnp.log(v - self.lower)
        return v / self.step

    def to_value(self, raw):
        if self.transform == "logit":
            return self.lower + (self.upper - self.lower) * jax.nn.sigmoid(raw)
        if self.transform == "log":
            return self.lower + jnp.exp(raw)
        return self.step * raw

    def value_derivative(self, raw) -> float:
        """d(value)/d(raw) at `raw` (closed form; used for standard errors and priors)."""
        raw = float(raw)
        if self.transform == "logit":
            sig = 1.0 / (1.0 + np.exp(-raw))
            return (self.upper - self.lower) * sig * (1.0 - sig)
        if self.transform == "log":
            return float(np.exp(raw))
        return self.step

    def raw_label(self) -> str:
        inner = self.path if self.lower in (None, 0, 0.0) else f"{self.path} - {self.lower:g}"
        return {
            "logit": f"logit({self.path})",
            "log": f"log({inner})",
            "linear": f"{self.path}/{self.step:g}",
        }[self.transform]

    def prior_residual(self, value):
        return (jnp.log(value) - np.log(self.prior_median)) / self.prior_log_sd


def apply_raw(model, params, raw):
    """`model` with each of `params` set from its raw coordinate `raw[k]` (jit/vmap-safe).

    The one raw-to-model map: fits of time series and of tables, and predictions from a
    fitted posterior, all build their models through it."""
    from greybox._model.parameters import set_values

    return set_values(
        model, [p.path for p in params], [p.to_value(raw[k]) for k, p in enumerate(params)]
    )


def levenberg_marquardt(residuals, raw0, args, *, rtol: float, atol: float, max_steps: int):
    """The one least-squares engine: optimistix Levenberg-Marquardt on `residuals(raw, args)`
    from `raw0`, never throwing. Returns (raw, solved flag, steps taken)."""
    import optimistix as optx

    sol = optx.least_squares(
        residuals,
        optx.LevenbergMarquardt(rtol=rtol, atol=atol),
        raw0,
        args=args,
        max_steps=max_steps,
        throw=False,
    )
    return sol.value, sol.result == optx.RESULTS.successful, sol.stats["num_steps"]
