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
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

AT_BOUND_FRACTION = 1e-3  # distance to a bound, as a fraction of the range, that counts as "at"
LOG_SCALED_RATIO = 100.0  # bounds spanning this ratio or more: "at bound" judged in log space


_LIBM_EXP = np.frompyfunc(math.exp, 1, 1)  # the C library's exp, as scipy's expit uses
_LOG_MAX = math.log(np.finfo(float).max)  # exp of anything above overflows


def _expit(x):
    """scipy.special.expit, 1 / (1 + exp(-x)) with the C library's exp (the same numbers to
    the bit; numpy's own exp differs in the last bit for ~2 % of inputs), without importing
    scipy (~0.1 s of a command such as `greybox simulate`)."""
    x = np.asarray(x, dtype=float)
    huge = -x > _LOG_MAX  # exp overflows: expit is 0 there (math.exp would raise)
    e = np.where(huge, np.inf, np.asarray(_LIBM_EXP(np.where(huge, 0.0, -x)), dtype=float))
    return (1.0 / (1.0 + e))[()]


def _xp(*xs):
    """jax.numpy where any of `xs` is a JAX array or tracer, numpy for host numbers: the
    transforms below run inside compiled solvers (where a parameter's bounds, scale and prior
    are traced inputs too) and, per device and parameter, on the host (reports of a batch),
    where an eager JAX call costs ~0.1 ms of dispatch for a scalar."""
    return jnp if any(isinstance(x, jax.Array) for x in xs) else np


class StartOutsideBounds(ValueError):
    """A free parameter's starting value is not strictly inside its bounds."""


@dataclasses.dataclass(frozen=True)
class FreeParameter:
    """- `path`: dotted field path in the model, e.g. ``"thermal.tau_s"``.
    - `unit`: display unit of the SI value (``"s"``, ``"K/W"``, ``"m"``, ``"1"``).
    - `lower`, `upper`: physical bounds (None = unbounded on that side).
    - `per_experiment`: one value per experiment instead of one shared value.
    - `prior_median`, `prior_log_sd`: Gaussian prior on log(value) (needs a positive value).
    - `initial`: starting value (default: the model's current value). Not part of the
      parameter's identity (equality, hash).
    - `scale`: typical magnitude [unit], used only by unbounded ("linear") parameters; None
      derives it from the starting value when fitting (see the module docstring).

    A JAX pytree: the numbers (bounds, scale, prior) are its leaves, so two parameters that
    differ only in them, or in where they start, share one compiled solver (`as_leaves`).
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
        object.__setattr__(self, "_log_scaled", self._spans_decades())

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
        parameter's scale is logarithmic, and "at bound" is judged in log space. Decided
        once, from the numbers the parameter was made with: it chooses a branch of the
        compiled solver, so it is part of the parameter's structure (`as_leaves`)."""
        return self._log_scaled

    def _spans_decades(self) -> bool:
        return bool(
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
        return 1.0 if self.scale is None else self.scale * 1.0  # a traced scale stays traced

    def with_scale_from(self, start: float) -> FreeParameter:
        """This parameter with `scale` derived from the starting value `start` when it is None
        (|start|, or 1 for a start of 0); bounded parameters and explicit scales are kept."""
        if self.transform != "linear" or self.scale is not None:
            return self
        v = abs(float(start))
        return dataclasses.replace(self, scale=v if np.isfinite(v) and v > 0 else 1.0)

    def bound_side(self, raw, raw_start):
        """-1 (on the lower bound), +1 (on the upper) or 0 at `raw` (see the module docstring;
        `raw_start`: where the fit started, for a lower bound only). jit-safe: the one
        definition of "at bound", read on the host by `bound_hit` and inside the optimiser's
        stall test (`levenberg_marquardt`)."""
        xp = _xp(raw, self.lower, self.upper)
        raw = xp.asarray(raw, dtype=float)
        if self.log_scaled:
            # judged where the parameter lives: the fraction of the log range from a bound
            lo, hi = xp.log(self.lower), xp.log(self.upper)
            frac = (xp.log(xp.maximum(self.to_value(raw), self.lower)) - lo) / (hi - lo)
            upper = xp.where(frac > 1.0 - AT_BOUND_FRACTION, 1, 0)
            return xp.where(frac < AT_BOUND_FRACTION, -1, upper)
        if self.transform == "logit":
            edge = float(np.log(AT_BOUND_FRACTION / (1.0 - AT_BOUND_FRACTION)))  # -6.9
            return xp.where(raw < edge, -1, xp.where(raw > -edge, 1, 0))
        if self.transform == "log":
            return xp.where(raw - raw_start < np.log(AT_BOUND_FRACTION), -1, 0)
        return xp.zeros((), dtype=int)

    def bound_hit(self, raw: float, raw_start: float) -> str | None:
        """ "lower" or "upper" when the value at `raw` sits on that bound (`bound_side`), else
        None. `raw_start` is where the fit started (for a lower bound only)."""
        side = int(self.bound_side(float(raw), float(raw_start)))
        return {-1: "lower", 1: "upper", 0: None}[side]

    def check_value(self, value: float) -> None:
        """Raise a ValueError naming the parameter if `value` is outside its bounds."""
        v = float(value)
        if not np.isfinite(v):
            raise ValueError(f"{self.path}: initial value {v} is not finite")
        lo_ok = self.lower is None or v > self.lower
        hi_ok = self.upper is None or v < self.upper
        if not (lo_ok and hi_ok):
            raise StartOutsideBounds(
                f"{self.path}: starting value {v:g} is not strictly inside its bounds "
                f"({self.lower}, {self.upper}) [{self.unit}] (the fit maps the interior onto "
                "the real line, so a start on a bound has no image); give it an initial "
                "value inside them, or move the bound"
            )

    def to_raw(self, value):
        xp = _xp(value, self.lower, self.upper, self.scale)
        v = xp.asarray(value, dtype=float)
        with np.errstate(divide="ignore", invalid="ignore"):  # NaN/inf as JAX gives them
            if self.transform == "logit":
                p = (v - self.lower) / (self.upper - self.lower)
                return xp.log(p) - xp.log1p(-p)
            if self.transform == "log":
                return xp.log(v - self.lower)
            return v / self.step

    def to_value(self, raw):
        xp = _xp(raw, self.lower, self.upper, self.scale)
        if self.transform == "logit":
            sigmoid = jax.nn.sigmoid if xp is jnp else _expit
            return self.lower + (self.upper - self.lower) * sigmoid(raw)
        if self.transform == "log":
            with np.errstate(over="ignore"):
                return self.lower + xp.exp(raw)
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
        median = _xp(self.prior_median).log(self.prior_median)
        return (jnp.log(value) - median) / self.prior_log_sd


class _Unkeyed:
    """A value carried in a pytree's static part that takes no part in its identity (every
    `_Unkeyed` equals every other): a parameter's starting value, read on the host only."""

    __slots__ = ("value",)

    def __init__(self, value):
        self.value = value

    def __eq__(self, other):
        return isinstance(other, _Unkeyed)

    def __hash__(self):
        return 0


_NUMBERS = ("lower", "upper", "prior_median", "prior_log_sd", "scale")


def _flatten(p: FreeParameter):
    # the numbers are leaves (None where absent: a bound, scale or prior that is not there is
    # structure); path, unit, sharing and the log-scale flag are the parameter's identity
    aux = (p.path, p.unit, p.per_experiment, p.log_scaled, _Unkeyed(p.initial))
    return tuple(getattr(p, k) for k in _NUMBERS), aux


def _unflatten(aux, numbers) -> FreeParameter:
    # no __init__: the leaves may be tracers or JAX's placeholders, which the checks of a
    # parameter made by hand cannot judge (they were checked when it was made)
    p = object.__new__(FreeParameter)
    path, unit, per_experiment, log_scaled, initial = aux
    fields = dict(zip(_NUMBERS, numbers), path=path, unit=unit, per_experiment=per_experiment)
    for k, v in (*fields.items(), ("initial", initial.value), ("_log_scaled", log_scaled)):
        object.__setattr__(p, k, v)
    return p


jax.tree_util.register_pytree_node(FreeParameter, _flatten, _unflatten)


def as_leaves(params) -> tuple:
    """`params` with their numbers (bounds, scale, prior) as float64 numpy arrays: inputs of a
    compiled solver, not part of its identity, so a device whose bounds, derived scale or
    prior differ from the last one's reuses its compiled solver (issue 24, item 1). Only the
    structure is: which numbers are there, whether the bounds span decades, path, unit and
    sharing. On the host the arrays act as the numbers did."""
    return tuple(jax.tree.map(lambda x: np.asarray(x, dtype=float), p) for p in params)


def pinned_fn(params, raw_start):
    """raw -> whether any of `params` is on a bound (`FreeParameter.bound_side`), judged
    from `raw_start` (jit-safe; the optimiser's stall test)."""
    if not params:
        return None

    def pinned(raw):
        sides = [p.bound_side(raw[k], raw_start[k]) for k, p in enumerate(params)]
        return jnp.any(jnp.stack(sides) != 0)

    return pinned


def apply_raw(model, params, raw):
    """`model` with each of `params` set from its raw coordinate `raw[k]` (jit/vmap-safe).

    The one raw-to-model map: fits of time series and of tables, and predictions from a
    fitted posterior, all build their models through it."""
    from greybox._model.parameters import set_values

    return set_values(
        model, [p.path for p in params], [p.to_value(raw[k]) for k, p in enumerate(params)]
    )


STALL_WINDOW = 20  # steps over which a start must still lower its cost ...
STALL_RTOL = 1e-6  # ... by more than this fraction, or it has stalled;
STALL_RTOL_AT_BOUND = 1e-4  # ... by more than this while a parameter is on a bound
MIN_STEP_BOUND = 256  # the static loop bound of every step budget up to it (the default 200)


def step_bound(max_steps: int) -> int:
    """The static loop bound of a solve whose budget `max_steps` is an input of the program:
    `MIN_STEP_BOUND`, or the next power of two above a larger budget (few programs)."""
    return max(MIN_STEP_BOUND, 1 << max(int(max_steps) - 1, 0).bit_length())


@functools.cache
def _stall_solver():
    """`optx.LevenbergMarquardt` that also stops when the cost has stalled: the cost at the
    last accepted point fell by no more than `stall_rtol` (relative) over the last `window`
    steps, or by no more than `bound_rtol` while `pinned(raw)` (a parameter on a bound).
    That is what a start does while a parameter chases a bound in its transformed
    coordinate (raw -> +-inf, each step a smaller gain, the tolerances on raw never met):
    its step budget would go on a cost that no longer moves and a verdict ("at bound")
    that no longer changes. The step sequence is optimistix's own (the inner solver's
    state is carried unchanged), so a start that converges before it stalls ends exactly
    where plain Levenberg-Marquardt ends."""
    import equinox as eqx
    import optimistix as optx

    class StallStop(optx.AbstractLeastSquaresSolver):
        inner: optx.LevenbergMarquardt
        window: int = eqx.field(static=True)
        stall_rtol: float
        bound_rtol: float
        pinned: object  # raw -> bool: a parameter on its bound (None: never)
        cap: object = None  # the step budget as an input of the program (None: optimistix's)

        @property
        def rtol(self):
            return self.inner.rtol

        @property
        def atol(self):
            return self.inner.atol

        @property
        def norm(self):
            return self.inner.norm

        def init(self, fn, y, args, options, f_struct, aux_struct, tags):
            inner = self.inner.init(fn, y, args, options, f_struct, aux_struct, tags)
            ring = jnp.full(self.window + 1, jnp.inf)
            return inner, ring, jnp.array(0), jnp.array(False)

        def step(self, fn, y, args, options, state, tags):
            inner, ring, k, _ = state
            y, inner, aux = self.inner.step(fn, y, args, options, inner, tags)
            # the cost at the last accepted point (a rejected step leaves it unchanged)
            loss = 0.5 * jnp.sum(inner.f_info.residual**2)
            ring = ring.at[k % (self.window + 1)].set(loss)
            old = ring[(k + 1) % (self.window + 1)]  # the cost `window` steps ago
            tol = self.stall_rtol
            if self.pinned is not None:
                tol = jnp.where(self.pinned(y), self.bound_rtol, tol)
            stalled = (k >= self.window) & (old - loss <= tol * jnp.abs(loss))
            return y, (inner, ring, k + 1, stalled), aux

        def terminate(self, fn, y, args, options, state, tags):
            done, result = self.inner.terminate(fn, y, args, options, state[0], tags)
            if self.cap is None:
                return done | state[3], result
            # the budget spent, as optimistix's own `max_steps` ends a solve: converging or
            # stalling on the last step still counts as such
            out = state[2] >= self.cap
            spent = optx.RESULTS.where(
                out & ~done & ~state[3], optx.RESULTS.nonlinear_max_steps_reached, result
            )
            return done | state[3] | out, spent

        def postprocess(self, fn, y, aux, args, options, state, tags, result):
            return self.inner.postprocess(fn, y, aux, args, options, state[0], tags, result)

    return StallStop


def levenberg_marquardt(
    residuals,
    raw0,
    args,
    *,
    rtol: float,
    atol: float,
    max_steps: int,
    stall_window: int | None = STALL_WINDOW,
    stall_rtol: float = STALL_RTOL,
    pinned=None,
    step_cap=None,
    has_aux: bool = False,
    end_point: bool = False,
):
    """The one least-squares engine: optimistix Levenberg-Marquardt on `residuals(raw, args)`
    from `raw0`, never throwing. Returns (raw, solved flag, steps taken, stalled flag), and
    with `end_point` also the solver's last accepted evaluation, which is at `raw`:
    (residual vector, its linearisation as a lineax operator, aux or None); `has_aux`:
    `residuals` returns (residual vector, aux).

    `stall_window`, `stall_rtol`, `pinned`: a start whose cost fell by no more than
    `stall_rtol` (relative; `STALL_RTOL_AT_BOUND` while `pinned(raw)` is true) over
    `stall_window` steps stops there, not solved and flagged stalled (`_stall_solver`);
    None runs to the tolerances or `max_steps` only. `rtol` and `atol` may be arrays (inputs
    of the compiled program); `step_cap` (an integer array, with a stall window) is then the
    step budget and `max_steps` only the loop's static bound (`step_bound`), so one program
    serves every budget up to it."""
    import optimistix as optx

    from greybox._model.householder import lm_linear_solver

    lm = optx.LevenbergMarquardt(rtol=rtol, atol=atol, linear_solver=lm_linear_solver())
    solver = lm if stall_window is None else _stall_solver()(
        lm, int(stall_window), float(stall_rtol), STALL_RTOL_AT_BOUND, pinned, step_cap
    )
    sol = optx.least_squares(
        residuals, solver, raw0, args=args, has_aux=has_aux, max_steps=max_steps, throw=False
    )
    ok = sol.result == optx.RESULTS.successful
    inner = sol.state if stall_window is None else sol.state[0]
    stalled = jnp.array(False) if stall_window is None else sol.state[3] & ~inner.terminate
    out = (sol.value, ok & ~stalled, sol.stats["num_steps"], stalled)
    if not end_point:
        return out
    # optimistix's Gauss-Newton state holds the point it returns with its evaluation
    # (`f_info`, `aux`: replaced on each accepted step only)
    return (*out, (inner.f_info.residual, inner.f_info.jac, inner.aux if has_aux else None))
