"""Uncertainty bands for simulating a new input waveform with fitted parameters (pure).

Delta method: with raw (transformed) shared parameters r and their posterior covariance C
(from `greybox._estimate.fit`), the simulated camera reading y(t) = f(r) has variance
J C J^T, J = dy/dr computed by forward-mode autodiff through the same simulation code
`greybox._simulate.simulate` uses. Per-run nuisance parameters (camera offset, drift) belong to the
recorded runs, not to a new waveform: they are left out of J and C, and the model keeps its
own values for them (0 for the device defaults), so the output is the displacement from rest.

Two kinds of band, and `Band.kind` says which one a result is:

- confidence band (default): parameter uncertainty only; where the model's response is
  expected to lie.
- prediction interval (`sigma` given): adds the measurement noise sigma^2; where new camera
  readings are expected to fall.

Parameter directions that nothing determined (a "not identifiable" combination: NaN rows
of C, or the fit's `null_directions`) do not widen the band when the output does not depend
on them (e.g. the new response depends only on a product that the data did fix); when it
does depend on them, the band is infinite rather than falsely narrow.
"""

from __future__ import annotations

import functools
from statistics import NormalDist

import jax
import jax.numpy as jnp
import numpy as np

from greybox._compile import jit
from greybox._estimate.band import Band, SampledBand
from greybox._model.device import check_method
from greybox._model.freeparams import apply_raw, as_leaves
from greybox._simulate.schedules import schedule_row
from greybox._simulate.simulate import as_arrays, observe_schedule, require_x64

NEGLIGIBLE_SENSITIVITY = 1e-6  # relative |dy/d direction| treated as "does not depend"


N_PATHS = 200  # sample paths behind a process-noise band


def process_band(
    model,
    free,
    raw,
    covariance_raw,
    inputs,
    t_s,
    *,
    measurement_noise: bool = False,
    level: float = 0.95,
    n_paths: int = N_PATHS,
    seed: int = 0,
    t_start_s: float = 0.0,
) -> SampledBand:
    """The pointwise `level` band of `n_paths` sample paths of a process-noise model
    (`StochasticDevice`): process noise by the SDE's exact discretisation (a linear device;
    otherwise its local linearisation at each step, `sample_paths`), the shared
    parameters drawn from `covariance_raw` (at `raw` when it is not finite), measurement noise
    with `measurement_noise`. `y` is the noise-free response at `raw`."""
    from greybox._simulate.simulate import simulate
    from greybox.stochastic._sde_device import draw_paths

    shared = [p for p in free if not p.per_experiment]
    k = len(shared)
    raw = np.asarray(raw, dtype=float)[:k]
    cov = np.asarray(covariance_raw, dtype=float)[:k, :k]
    rng = np.random.default_rng(seed)
    if cov.size and np.all(np.isfinite(cov)):
        draws = rng.multivariate_normal(raw, 0.5 * (cov + cov.T), size=n_paths)
        what = "parameter draws from the fit's covariance"
    else:
        draws = np.tile(raw, (n_paths, 1))
        what = "parameters at the estimate (their covariance is not finite)"
    t = np.asarray(t_s, dtype=float)
    paths = draw_paths(
        model, shared, draws, inputs, t, t_start_s=t_start_s, seed=seed,
        measurement_noise=measurement_noise,
    )
    at = apply_raw(as_arrays(model), shared, jnp.asarray(raw))
    y = np.asarray(simulate(at.device, inputs, t, t_start_s=t_start_s)).reshape(t.size, -1)
    tail = 50 * (1 - level)
    lo, hi = np.percentile(paths, [tail, 100 - tail], axis=0)
    pct = f"{level * 100:g} %"
    linear = not model.use_ekf
    how = "exact discretisation of the SDE" if linear else "the SDE linearised at each step"
    kind = (
        f"{pct} band of {n_paths} sample paths: process noise ({how}) and {what}"
        + ("; measurement noise added" if measurement_noise else "")
    )
    sd = (hi - lo) / (2 * NormalDist().inv_cdf(0.5 + level / 2))
    return SampledBand(t, y, lo, hi, sd, sd, level, measurement_noise, kind)


def prediction_band(
    model,
    free,
    raw,
    covariance_raw,
    inputs,
    t_s,
    *,
    sigma=None,
    null_directions=None,
    level: float = 0.95,
    method: str | None = None,
    t_start_s: float = 0.0,
    rtol: float = 1e-8,
    atol: float = 1e-10,
    max_steps: int = 16384,
) -> Band:
    """Simulate `inputs` at times `t_s` with a pointwise band from the parameter covariance.

    **Arguments:**
    - `model`: the fitted model (shared parameters at their fitted values).
    - `free`: the fit's `FreeParameter`s, in the order of `raw` (shared ones first).
    - `raw`, `covariance_raw`: the fit's raw vector and its covariance (all parameters;
      only the leading shared block is used).
    - `inputs`: waveform in SI (W for laser power); `t_s`: output times [s], increasing.
    - `sigma`: measurement noise per output [SI]; given, the band is a prediction interval.
    - `null_directions`: (k, n_raw) directions nothing determined (see
      `greybox._estimate.identifiability`), if the covariance leaves them out.
    - `level`: coverage of the pointwise band (default 0.95).
    - `method`, `rtol`, `atol`, `max_steps`: the simulation path and the adaptive solver's
      settings (a fit's: `FitResult.posterior.band` passes them).

    **Returns:** a `Band`. **Raises:** `ValueError` for non-finite fitted values (a fit that
    diverged) or a failed simulation.
    """
    require_x64("prediction_band")
    method = check_method(model, method)
    if not 0 < level < 1:
        raise ValueError(f"level: {level} must be in (0, 1)")
    shared = tuple(p for p in free if not p.per_experiment)
    n_shared = len(shared)
    raw = np.asarray(raw, dtype=float)
    cov = np.asarray(covariance_raw, dtype=float)[:n_shared, :n_shared]
    if not np.all(np.isfinite(raw[:n_shared])):
        raise ValueError(
            "raw: fitted values are not finite (the fit diverged); no simulation "
            "or band can be computed"
        )
    nulls = []
    if null_directions is not None and np.size(null_directions):
        nulls = [
            v[:n_shared]
            for v in np.atleast_2d(np.asarray(null_directions, dtype=float))
            if np.linalg.norm(v[:n_shared]) > NEGLIGIBLE_SENSITIVITY
        ]
    t = np.asarray(t_s, dtype=float)
    row = schedule_row(model, inputs, t, t_start_s=t_start_s)
    z, ok, jac = _response_and_jacobian(
        as_arrays(model),
        as_leaves(shared),
        jnp.asarray(raw[:n_shared]),
        row,
        method,
        (float(rtol), float(atol), int(max_steps)),
    )
    if not bool(ok):
        raise ValueError(
            "simulation failed for this waveform (adaptive solver); check the "
            "waveform and the fitted parameters"
        )
    n = t.size
    y = np.asarray(z)[:n]
    var = np.zeros_like(y)
    if n_shared:
        var = delta_variance(np.asarray(jac)[:n], cov, nulls)
    sd_model = np.sqrt(np.clip(var, 0.0, None))
    includes_noise = sigma is not None
    total = var + (
        np.broadcast_to(np.asarray(sigma, dtype=float), y.shape[1:]) ** 2 if includes_noise else 0.0
    )
    sd = np.sqrt(total)
    zq = NormalDist().inv_cdf((1.0 + level) / 2.0)  # on the host, as the residual tests' bands
    return Band(t, y, y - zq * sd, y + zq * sd, sd_model, sd, float(level), includes_noise)


@jit
def _response_and_jacobian(base, shared, raw, row, method, solver):
    """The response to one run's schedule `row` of `base` with the `shared` free parameters at
    `raw`, its success flag, and d response / d raw (None without shared parameters), the
    adaptive solver at `solver` (rtol, atol, max_steps). One compiled function per structure
    (model, free paths, method and solver settings, bucketed schedule shapes):
    the model's values, the parameters' numbers, the raw vector and the waveform are its
    inputs, so the bands of every run of a result, of a new waveform or of another device of
    the structure compile nothing new."""

    rtol, atol, max_steps = solver

    def observe(r):
        return observe_schedule(
            with_shared(base, shared, r),
            row,
            method=method,
            rtol=rtol,
            atol=atol,
            max_steps=max_steps,
        )

    z, ok = observe(raw)
    jac = jax.jacfwd(lambda r: observe(r)[0])(raw) if len(shared) else None
    return z, ok, jac


def delta_variance(g, cov, nulls=()) -> np.ndarray:
    """(N, n_y) variance g C g^T of a response whose sensitivities to the raw coordinates are
    `g` (N, n_y, P), their covariance `cov` (P, P) (delta method). Undetermined directions (the
    coordinates whose covariance is not finite, and the given `nulls`, (P,) vectors) make the
    variance infinite where the response depends on them, and add nothing where it does not."""
    g = np.asarray(g, dtype=float)
    cov = np.asarray(cov, dtype=float)
    unknown = ~np.all(np.isfinite(cov), axis=1)
    nulls = [np.eye(cov.shape[0])[k] for k in np.flatnonzero(unknown)] + list(nulls)
    cov = np.where(unknown[:, None] | unknown[None, :], 0.0, cov)
    var = np.einsum("nyp,pq,nyq->ny", g, (cov + cov.T) / 2, g)
    scale = np.linalg.norm(g, axis=-1) + 1e-300
    for v in nulls:
        depends = np.abs(g @ v) > NEGLIGIBLE_SENSITIVITY * scale * np.linalg.norm(v)
        var = np.where(depends, np.inf, var)
    return var


def with_shared(model, free, raw):
    """`model` with each shared (not per-experiment) free parameter set from its raw value.

    `raw` holds the shared raw coordinates first, in the order of `free` (as a fit's `raw`);
    jit/vmap-able, so functions of the fitted model can be mapped over parameter draws.
    """
    return apply_raw(model, [p for p in free if not p.per_experiment], raw)


def raw_draws(raw, covariance_raw, free, n: int, *, seed: int = 0) -> np.ndarray:
    """`n` Gaussian draws (n, n_shared) of the shared raw coordinates from a fit's covariance.

    Raw coordinates are log/logit/linear transforms of the parameters, so draws respect bounds
    and positivity once mapped back. Raises ValueError when a shared parameter's covariance is
    not finite (not identifiable): there is nothing honest to draw from.
    """
    n_shared = sum(not p.per_experiment for p in free)
    mean = np.asarray(raw, dtype=float)[:n_shared]
    cov = np.asarray(covariance_raw, dtype=float)[:n_shared, :n_shared]
    if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(cov))):
        raise ValueError(
            "covariance_raw: not finite for the shared parameters (a parameter is "
            "not identifiable or the fit diverged); free fewer parameters or add "
            "priors before propagating uncertainty"
        )
    rng = np.random.default_rng(seed)
    return rng.multivariate_normal(mean, (cov + cov.T) / 2, size=int(n))


def propagate(fn, model, free, raw, covariance_raw, n: int, *, seed: int = 0) -> np.ndarray:
    """Push `n` parameter draws through `fn(model) -> array`: (n, ...) samples of `fn`.

    The Monte Carlo counterpart of the delta method: use it for quantities that are not
    smooth enough (an optimum, a threshold) or when the interval may be asymmetric. Keep
    the same `fn` object across calls (fits of other devices, other draws) to reuse its
    compiled function; a new `fn` (a lambda written inside a loop) compiles again.
    """
    draws = jnp.asarray(raw_draws(raw, covariance_raw, free, n, seed=seed))
    return np.asarray(_pushed(_static(fn), as_arrays(model), as_leaves(free), draws))


def _static(fn):
    """`fn` as the static argument of a compiled function: itself where it can be hashed (a
    function, a lambda, a bound method), else wrapped in a `functools.partial`, hashed by
    identity (a callable dataclass: compiled again at each call, as every call did before)."""
    try:
        hash(fn)
    except TypeError:
        return functools.partial(fn)
    return fn


@jit
def _pushed(fn, base, free, draws):
    """`fn` of `base` at each row of `draws` (one compiled function per `fn` and structure)."""
    return jax.vmap(lambda r: fn(with_shared(base, free, r)))(draws)


def delta_method(fn, model, free, raw, covariance_raw) -> tuple[np.ndarray, np.ndarray]:
    """(value, covariance) of `fn(model)` to first order in a fit's shared raw parameters.

    `fn(model) -> array` must be differentiable in the parameters (no argmax, bisection or
    thresholds: use `propagate` for those). Its Jacobian J with respect to the shared raw
    coordinates gives cov = J C J^T. Raises ValueError if C is not finite for them. As with
    `propagate`, the same `fn` object reuses its compiled function.
    """
    n_shared = sum(not p.per_experiment for p in free)
    cov = np.asarray(covariance_raw, dtype=float)[:n_shared, :n_shared]
    if not np.all(np.isfinite(cov)):
        raise ValueError(
            "covariance_raw: not finite for the shared parameters (a parameter is "
            "not identifiable); the delta method needs a finite covariance"
        )
    r0 = jnp.asarray(raw, dtype=float)[:n_shared]
    value, jac = _value_and_jacobian(_static(fn), as_arrays(model), as_leaves(free), r0)
    jac = np.asarray(jac).reshape(-1, n_shared)
    return np.asarray(value), jac @ cov @ jac.T


@jit
def _value_and_jacobian(fn, base, free, r0):
    """`fn` of `base` at the shared raw vector `r0` (flattened) and its Jacobian there (one
    compiled function per `fn` and structure)."""

    def of_raw(r):
        return jnp.atleast_1d(fn(with_shared(base, free, r)))

    return of_raw(r0), jax.jacfwd(of_raw)(r0)
