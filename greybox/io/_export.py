"""Export a fitted grey-box model as a python-control state-space system (optional
dependency, imported lazily), with its parameter covariance kept alongside.

python-control's `StateSpace` holds matrices only, so the uncertainty travels in the
returned `StateSpaceExport`: the shared fitted parameters (paths, SI values) and their
covariance in SI (delta method from the fit's raw covariance). A linear device
(`AbstractLinearDevice`) is exported exactly (dx/dt = A x + B u, y = C x + y0); any other
ODE device is linearised at an operating point (default: its initial state, inputs 0) by
forward-mode differentiation, in deviation variables (x - x_op, u - u_op, y - y_op).
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True, eq=False)
class StateSpaceExport:
    """- `system`: python-control `StateSpace` (continuous, or discrete with `dt` by ZOH), in
      deviation variables: states x - `x_op`, inputs u - `u_op`, outputs y - `y_op` [SI].
      A linear device is exported in absolute states and inputs (`x_op`, `u_op` zero) and
      `y_op` is its output offset y(x = 0) (the ambient temperature of a thermal model): the
      steady state of a constant input u is y_op + dcgain @ u. A linearisation is about
      (`x_op`, `u_op`); `dx_op` = f(x_op, u_op) is zero only at an equilibrium.
    - `linearised`: False when the device is linear (exact), True for a linearisation.
    - `parameter_paths`, `parameter_values`: the shared fitted parameters [SI];
      `covariance`: their covariance [SI, in the units of the paths] (NaN rows for values
      the data did not determine); None when no fit was given.
    """

    system: object
    x_op: np.ndarray
    u_op: np.ndarray
    y_op: np.ndarray
    linearised: bool
    dt: float | None
    dx_op: np.ndarray | None = None
    parameter_paths: tuple = ()
    parameter_values: np.ndarray | None = None
    covariance: np.ndarray | None = None


def _shared_covariance(free, raw, covariance_raw):
    shared = [p for p in free if not p.per_experiment]
    k = len(shared)
    raw = np.asarray(raw, dtype=float)[:k]
    cov = np.asarray(covariance_raw, dtype=float)[:k, :k]
    d = np.array([p.value_derivative(r) for p, r in zip(shared, raw)])
    values = np.array([float(p.to_value(r)) for p, r in zip(shared, raw)])
    return tuple(p.path for p in shared), values, d[:, None] * cov * d[None, :]


def to_state_space(
    model,
    *,
    dt: float | None = None,
    x_op=None,
    u_op=None,
    fit=None,
) -> StateSpaceExport:
    """A fitted grey-box `model` as a python-control state space, with its covariance.

    **Arguments:**
    - `model`: a device model (e.g. `FitResult.model`, `FittedModel.model`).
    - `dt`: None for continuous time, else the sample time [s] of a ZOH discretisation.
    - `x_op`, `u_op`: the operating point of a linearisation (default: the model's initial
      state and zero inputs); ignored for the matrices of a linear device, which are exact.
    - `fit`: a `FitResult` or a `FittedModel` (from `load_params`): its `free`, `raw` and
      `covariance_raw` give the parameter covariance kept alongside.

    **Returns:** a `StateSpaceExport`. **Raises:** `ImportError` without python-control;
    `ValueError` for a device without a vector field (a stepped device).
    """
    import jax
    import jax.numpy as jnp

    from greybox._model.device import AbstractLinearDevice, AbstractODEDevice

    try:
        import control
    except ImportError as err:  # pragma: no cover - optional dependency
        raise ImportError("to_state_space needs python-control: pip install control") from err
    if not isinstance(model, (AbstractODEDevice, AbstractLinearDevice)):
        raise ValueError(f"model: {type(model).__name__} has no continuous vector field to export")
    n_u = int(model.n_inputs)
    x0 = jnp.asarray(model.initial_state() if x_op is None else x_op, dtype=float)
    u0 = jnp.zeros(n_u) if u_op is None else jnp.asarray(u_op, dtype=float).reshape(n_u)
    if isinstance(model, AbstractLinearDevice):
        # exact and global: absolute states and inputs, y = C x + y_op with y_op = y(x = 0)
        a, b = model.linear_dynamics()
        x0, u0 = jnp.zeros_like(x0), jnp.zeros(n_u)
        linearised = False
    else:
        a = jax.jacfwd(lambda x: model.vector_field(0.0, x, u0))(x0)
        b = jax.jacfwd(lambda u: model.vector_field(0.0, x0, u))(u0)
        linearised = True
    dx0 = model.vector_field(0.0, x0, u0)
    c = jax.jacfwd(model.output)(x0)
    y0 = model.output(x0)
    a, b, c = (np.asarray(m, dtype=float) for m in (a, b, c))
    d = np.zeros((c.shape[0], b.shape[1]))
    sys = control.ss(a, b, c, d)
    if dt is not None:
        if not dt > 0:
            raise ValueError(f"dt: {dt} must be > 0 s (or None for continuous time)")
        sys = control.c2d(sys, float(dt), method="zoh")
    paths, values, cov = (), None, None
    if fit is not None:
        paths, values, cov = _shared_covariance(fit.free, fit.raw, fit.covariance_raw)
    return StateSpaceExport(
        system=sys,
        x_op=np.asarray(x0),
        u_op=np.asarray(u0),
        y_op=np.asarray(y0, dtype=float),
        linearised=linearised,
        dt=dt,
        dx_op=np.asarray(dx0, dtype=float),
        parameter_paths=paths,
        parameter_values=values,
        covariance=cov,
    )
