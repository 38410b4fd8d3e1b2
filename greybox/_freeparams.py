"""Free parameters of a fit: which model field, how it is transformed, its prior.

The optimiser works on unconstrained raw values; each `FreeParameter` maps raw <-> physical:

- both bounds: ``value = lower + (upper - lower) * sigmoid(raw)`` (bounded, "logit"),
- a lower bound only: ``value = lower + exp(raw)`` (positive, "log"; log-space steps suit
  parameters that span decades),
- no bounds: ``value = scale * raw`` ("linear"; `scale` keeps raw O(1), e.g. 1e-6 for m).

Fields not listed stay fixed at the model's value. A parameter may be shared by all
experiments or estimated once per experiment (offsets, drift, initial temperature). An
optional Gaussian prior on log(value) (median, log-sd) encodes what the data cannot identify.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np


@dataclasses.dataclass(frozen=True)
class FreeParameter:
    """- `path`: dotted field path in the model, e.g. ``"thermal.tau_s"``.
    - `unit`: display unit of the SI value (``"s"``, ``"K/W"``, ``"m"``, ``"1"``).
    - `lower`, `upper`: physical bounds (None = unbounded on that side).
    - `per_experiment`: one value per experiment instead of one shared value.
    - `prior_median`, `prior_log_sd`: Gaussian prior on log(value) (needs a positive value).
    - `initial`: starting value (default: the model's current value).
    - `scale`: typical magnitude, used only by unbounded ("linear") parameters.
    """

    path: str
    unit: str = ""
    lower: float | None = None
    upper: float | None = None
    per_experiment: bool = False
    prior_median: float | None = None
    prior_log_sd: float | None = None
    initial: float | None = None
    scale: float = 1.0

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
        if not self.scale > 0:
            raise ValueError(f"{self.path}: scale must be > 0")

    @property
    def transform(self) -> str:
        if self.lower is not None and self.upper is not None:
            return "logit"
        if self.lower is not None:
            return "log"
        return "linear"

    @property
    def has_prior(self) -> bool:
        return self.prior_median is not None

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
        return v / self.scale

    def to_value(self, raw):
        if self.transform == "logit":
            return self.lower + (self.upper - self.lower) * jax.nn.sigmoid(raw)
        if self.transform == "log":
            return self.lower + jnp.exp(raw)
        return self.scale * raw

    def value_derivative(self, raw) -> float:
        """d(value)/d(raw) at `raw` (closed form; used for standard errors and priors)."""
        raw = float(raw)
        if self.transform == "logit":
            sig = 1.0 / (1.0 + np.exp(-raw))
            return (self.upper - self.lower) * sig * (1.0 - sig)
        if self.transform == "log":
            return float(np.exp(raw))
        return self.scale

    def raw_label(self) -> str:
        inner = self.path if self.lower in (None, 0, 0.0) else f"{self.path} - {self.lower:g}"
        return {
            "logit": f"logit({self.path})",
            "log": f"log({inner})",
            "linear": f"{self.path}/{self.scale:g}",
        }[self.transform]

    def prior_residual(self, value):
        return (jnp.log(value) - np.log(self.prior_median)) / self.prior_log_sd
