"""Periodic steady state under a square wave (PHYSICS.md §5), for any device.

The input alternates between `amplitude` for `duty * T` and `low` (default 0) for the rest of
each period T = 1 / f, starting at a rising edge. Two paths give the cycle that repeats forever:

- "analytic": for dynamics affine in the state, dx/dt = A x + B g(u) (a linear device, or a
  device with `state_affine_form()` such as the Joule-heated chevron at zero TCR), the one-cycle
  fixed point is closed form, x_start = (I - Phi_off Phi_on)^-1 (Phi_off Gamma_on q_on +
  Gamma_off q_off), with exact ZOH matrices (`greybox._simulate.simulate.zoh_matrices`);
  states inside the cycle follow by exact ZOH steps.
- "numerical": otherwise (Joule heating with R(T), radiation) the one-cycle map is integrated
  with `n_steps` exponential Rosenbrock-Euler steps per phase, x+ = x + h phi1(h J) f(x) (exact
  for affine dynamics, second order, stable for stiff decay), and its fixed point is found by
  Newton's method on P(x) - x.

From the cycle: peak-to-peak and time-mean of the first output (displacement [m]). f = 0 is the
quasi-static limit (T -> infinity): the output jumps between the two DC steady states.
Everything is pure, jit- and vmap-able, and differentiable in the model parameters.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from greybox._compile import jit
from greybox._model.device import AbstractStateAffineDevice
from greybox._simulate.simulate import as_arrays, require_x64, zoh_matrices

METHODS = ("auto", "analytic", "numerical")
NEWTON_ITERATIONS = 8  # the one-cycle map is a contraction close to affine: 3-4 suffice


def is_state_affine(model) -> bool:
    """Whether the closed-form path applies (decide outside jit, on a concrete model)."""
    return isinstance(model, AbstractStateAffineDevice) and model.is_state_affine()


def _affine_form(model):
    return model.state_affine_form()


def _u(model, level):
    return jnp.broadcast_to(jnp.asarray(level, dtype=float), (model.n_inputs,))


def steady_state(model, u, *, method: str = "auto", n_iterations: int = 30):
    """State (n_states,) with dx/dt = 0 under the constant input `u` (n_inputs,).

    "analytic" solves A x + B g(u) = 0; "numerical" runs `n_iterations` Newton steps from 0;
    "auto" picks by `is_state_affine` (concrete models only)."""
    u = jnp.broadcast_to(jnp.asarray(u, dtype=float), (model.n_inputs,))
    if method == "analytic" or (method == "auto" and is_state_affine(model)):
        a, b, g = _affine_form(model)
        return -jnp.linalg.solve(a, b @ g(u))

    def newton(m, x):
        f = lambda x: m.vector_field(0.0, x, u)
        return x - jnp.linalg.solve(jax.jacfwd(f)(x), f(x))

    return _converged(newton, model, n_iterations, jnp.zeros(model.n_states))


def _converged(newton, model, n_iterations, x0):
    """Newton iterations on a parameter-detached model, then one differentiable step.

    At a converged root r(x*) = 0 the derivative of one Newton step x* - J^-1 r equals the
    implicit-function derivative -J^-1 dr/dtheta, so parameter derivatives stay exact while the
    differentiated graph holds a single Newton step instead of the whole loop (compile time).
    `newton(model, x)` returns the next iterate.
    """
    fixed = jax.lax.stop_gradient(model)
    x = jax.lax.fori_loop(0, n_iterations, lambda _, x: newton(fixed, x), x0)
    return newton(model, jax.lax.stop_gradient(x))


def _affine_cycle(model, q_on, q_off, t_on, t_off, n_steps):
    a, b, _ = _affine_form(model)
    phi, gam = zoh_matrices(a, b, jnp.stack([t_on, t_off, t_on / n_steps, t_off / n_steps]))
    rhs = phi[1] @ gam[0] @ q_on + gam[1] @ q_off
    x0 = jnp.linalg.solve(jnp.eye(a.shape[0]) - phi[1] @ phi[0], rhs)

    def run(x, p, g, q):
        def step(x, _):
            x = p @ x + g @ q
            return x, x

        return jax.lax.scan(step, x, None, length=n_steps)

    x_mid, on = run(x0, phi[2], gam[2], q_on)
    _, off = run(x_mid, phi[3], gam[3], q_off)
    return jnp.concatenate([x0[None], on, off])


def _rosenbrock_phase(model, x, u, h, n_steps):
    def step(x, _):
        f = lambda x: model.vector_field(0.0, x, u)
        fx, jac = f(x), jax.jacfwd(f)(x)
        _, gam = zoh_matrices(jac, fx[:, None], h[None])
        x = x + gam[0, :, 0]
        return x, x

    return jax.lax.scan(step, x, None, length=n_steps)


def _numerical_cycle(model, u_on, u_off, t_on, t_off, n_steps):
    h_on, h_off = t_on / n_steps, t_off / n_steps

    def newton(m, x):
        def cycle_map(x):
            x_mid, _ = _rosenbrock_phase(m, x, u_on, h_on, n_steps)
            return _rosenbrock_phase(m, x_mid, u_off, h_off, n_steps)[0]

        jac = jax.jacfwd(cycle_map)(x) - jnp.eye(x.shape[0])
        return x - jnp.linalg.solve(jac, cycle_map(x) - x)

    x0 = _converged(newton, model, NEWTON_ITERATIONS, jnp.zeros(model.n_states))
    x_mid, on = _rosenbrock_phase(model, x0, u_on, h_on, n_steps)
    _, off = _rosenbrock_phase(model, x_mid, u_off, h_off, n_steps)
    return jnp.concatenate([x0[None], on, off])


def square_wave_cycle(
    model,
    amplitude,
    frequency_Hz,
    *,
    duty: float = 0.5,
    low: float = 0.0,
    n_steps: int = 64,
    method: str = "analytic",
):
    """The periodic steady-state cycle for frequency_Hz > 0 (pure, jit/vmap-able).

    **Returns:** (t_s (2 n_steps + 1,) from the rising edge, states (2 n_steps + 1, n_states)).
    `method` must be "analytic" or "numerical" here (resolve "auto" with `is_state_affine`).
    """
    period = 1.0 / jnp.asarray(frequency_Hz, dtype=float)
    t_on, t_off = duty * period, (1.0 - duty) * period
    u_on, u_off = _u(model, amplitude), _u(model, low)
    if method == "analytic":
        _, _, g = _affine_form(model)
        states = _affine_cycle(model, g(u_on), g(u_off), t_on, t_off, n_steps)
    elif method == "numerical":
        states = _numerical_cycle(model, u_on, u_off, t_on, t_off, n_steps)
    else:
        raise ValueError(f"method: {method!r}; use 'analytic' or 'numerical'")
    k = jnp.arange(n_steps + 1)
    t = jnp.concatenate([k * t_on / n_steps, t_on + k[1:] * t_off / n_steps])
    return t, states


def _simpson(y, duration):
    w = np.ones(y.shape[0])
    w[1:-1:2], w[2:-1:2] = 4.0, 2.0
    return duration * jnp.sum(w * y) / (3.0 * (y.shape[0] - 1))


def _response_one(model, amplitude, frequency_Hz, duty, low, n_steps, method):
    """(mean, peak-to-peak) of output 0 for one (amplitude, frequency) point; f = 0 is DC."""
    f_safe = jnp.where(frequency_Hz > 0, frequency_Hz, 1.0)
    _, states = square_wave_cycle(
        model, amplitude, f_safe, duty=duty, low=low, n_steps=n_steps, method=method
    )
    y = jax.vmap(model.output)(states)[:, 0]
    t = 1.0 / f_safe
    mean = (_simpson(y[: n_steps + 1], duty * t) + _simpson(y[n_steps:], (1 - duty) * t)) / t
    pp = jnp.max(y) - jnp.min(y)
    y_on = model.output(steady_state(model, _u(model, amplitude), method=method))[0]
    y_off = model.output(steady_state(model, _u(model, low), method=method))[0]
    dc = frequency_Hz == 0
    return (
        jnp.where(dc, duty * y_on + (1 - duty) * y_off, mean),
        jnp.where(dc, jnp.abs(y_on - y_off), pp),
    )


@jit
def _response_jit(model, amplitude, frequency_Hz, duty, low, n_steps, method):
    return jax.vmap(lambda a, f: _response_one(model, a, f, duty, low, n_steps, method))(
        amplitude, frequency_Hz
    )


def resolve_method(model, method: str) -> str:
    """'auto' -> 'analytic' for state-affine models, else 'numerical' (concrete model needed)."""
    if method not in METHODS:
        raise ValueError(f"method: {method!r} is unknown; use one of {METHODS}")
    if method == "auto":
        return "analytic" if is_state_affine(model) else "numerical"
    if method == "analytic" and not is_state_affine(model):
        raise ValueError(
            "method: the closed-form cycle needs dynamics affine in the state "
            "(e.g. tcr_per_K = 0 and no radiation); use method='numerical' or 'auto'"
        )
    return method


def _check(amplitude, frequency_Hz, duty, n_steps):
    a = np.asarray(amplitude, dtype=float)
    f = np.asarray(frequency_Hz, dtype=float)
    if not np.all(np.isfinite(a)):
        raise ValueError("amplitude: contains NaN or inf; give finite input levels")
    if not np.all(np.isfinite(f)) or np.any(f < 0):
        raise ValueError("frequency_Hz: must be finite and >= 0 Hz (0 = DC limit)")
    if not 0 < duty < 1:
        raise ValueError(f"duty: {duty} must be in (0, 1) for a square wave")
    if int(n_steps) != n_steps or n_steps < 2 or n_steps % 2:
        raise ValueError(f"n_steps: {n_steps} must be an even integer >= 2 (Simpson's rule)")
    return np.broadcast_arrays(a, f)


def square_wave_response(
    model,
    amplitude,
    frequency_Hz,
    *,
    duty: float = 0.5,
    low: float = 0.0,
    n_steps: int = 64,
    method: str = "auto",
):
    """Periodic steady-state mean and peak-to-peak of the first output, elementwise.

    **Arguments:**
    - `model`: a device (e.g. `models.electrothermal_chevron.default_model()`).
    - `amplitude`: high level of the square wave in the device's input units (V); array.
    - `frequency_Hz`: square-wave frequency [Hz] (>= 0, 0 = DC limit), broadcast with `amplitude`.
    - `duty`: on-fraction; `low`: the low level (default 0).
    - `n_steps`: samples per phase (even; max/min and Simpson mean are taken over them).
    - `method`: "auto", "analytic" (state-affine models) or "numerical".

    **Returns:** (mean, peak_to_peak) in SI (m), numpy arrays of the broadcast shape.
    """
    require_x64("square_wave_response")
    a, f = _check(amplitude, frequency_Hz, duty, n_steps)
    method = resolve_method(model, method)
    mean, pp = _response_jit(
        as_arrays(model),
        jnp.asarray(a.reshape(-1)),
        jnp.asarray(f.reshape(-1)),
        float(duty),
        float(low),
        int(n_steps),
        method,
    )
    return np.asarray(mean).reshape(a.shape), np.asarray(pp).reshape(a.shape)


def response_function(
    model, *, duty: float = 0.5, low: float = 0.0, n_steps: int = 64, method: str = "numerical"
):
    """A pure function (model, amplitude (N,), frequency_Hz (N,)) -> (mean (N,), pp (N,)) [SI].

    The method is fixed now, so the function can be traced with abstract parameters (inside a
    fit). The default "numerical" is right for any parameter values (and exact for affine
    dynamics); "analytic" ignores state dependence, so choose it only when every parameter that
    could break affinity (e.g. `joule.tcr_per_K`) stays fixed at a value where `model` is affine.
    """
    method = resolve_method(model, method)

    def respond(m, amplitude, frequency_Hz):
        return jax.vmap(lambda a, f: _response_one(m, a, f, duty, low, n_steps, method))(
            amplitude, frequency_Hz
        )

    return respond


def response_surface(model, amplitudes, frequencies_Hz, **kwargs):
    """Mean and peak-to-peak (each (n_amplitudes, n_frequencies), SI) on a full grid."""
    a, f = np.meshgrid(
        np.asarray(amplitudes, float), np.asarray(frequencies_Hz, float), indexing="ij"
    )
    return square_wave_response(model, a, f, **kwargs)
