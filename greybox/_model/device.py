"""What a device can do, as abstract classes, and the one place that dispatches on it.

A device maps inputs u(t) (laser power [W], heater levels, a reference position ...) to
physical outputs y (displacement [m], temperature [K]) observed through its `camera` block
(the readout: exposure average, offset, drift). Its capability is its class:

- `AbstractODEDevice`: dx/dt = f(t, x, u), simulated by the adaptive diffrax path;
- `AbstractStateAffineDevice`: dx/dt = A x + B g(u) (closed-form periodic steady state);
- `AbstractLinearDevice`: dx/dt = A x + B u, which the exact zero-order-hold path simulates;
- `AbstractSteppedDevice`: not an ODE (a per-step map such as quasi-static contacts); it
  produces its own camera readings from a schedule.

`simulation_methods`, `default_method` and `check_method` are the only code that decides
which simulation path a device may use.
"""

import abc

import equinox as eqx
import jax.numpy as jnp

from greybox.blocks._camera import AbstractReadout, Camera

# the ODE solver's paths: "stiff" is the adaptive one with an implicit solver, for a device
# whose time scales lie far apart (a fast sensor lag beside a slow plate): the explicit one
# takes steps of the fastest scale over the whole record
ODE_METHODS = ("adaptive", "stiff")
METHODS = ("zoh", *ODE_METHODS)


class AbstractDevice(eqx.Module):
    """Anything `simulate` and `fit` can drive: inputs in, readings out.

    `readout` turns the physical outputs into the readings of the files: a `Camera` for a
    filmed device (a `camera` field, with `readout` a property returning it) or a
    `SensorReadout` for a sensor."""

    # (no `from __future__ import annotations` in this module: equinox must see this
    # annotation as an AbstractVar for a subclass's `readout` property to satisfy it)
    readout: eqx.AbstractVar[AbstractReadout]

    @property
    @abc.abstractmethod
    def n_inputs(self) -> int: ...

    @property
    @abc.abstractmethod
    def n_outputs(self) -> int: ...


class AbstractODEDevice(AbstractDevice):
    """dx/dt = f(t, x, u) with a physical output y(x)."""

    @property
    @abc.abstractmethod
    def n_states(self) -> int: ...

    @abc.abstractmethod
    def initial_state(self):
        """State at the start of an experiment, shape (n_states,)."""

    @abc.abstractmethod
    def vector_field(self, t, x, u):
        """dx/dt for time `t` [s], state `x` (n_states,), input `u` (n_inputs,)."""

    @abc.abstractmethod
    def output(self, x):
        """Physical output (n_outputs,) in SI for state `x`."""


class AbstractStateAffineDevice(AbstractODEDevice):
    """dx/dt = A x + B g(u): linear in the state, any static map g of the input."""

    @abc.abstractmethod
    def state_affine_form(self):
        """(A (n, n), B (n, m), g: u -> (m,)) with dx/dt = A x + B g(u)."""

    def is_state_affine(self) -> bool:
        """Whether the affine form holds at these parameter values (a concrete check, outside
        jit; e.g. an electro-thermal chevron is affine only with a zero TCR)."""
        return True

    def vector_field(self, t, x, u):
        a, b, g = self.state_affine_form()
        return a @ x + b @ g(u)


class AbstractLinearDevice(AbstractStateAffineDevice):
    """dx/dt = A x + B u: the exact zero-order-hold path applies."""

    @abc.abstractmethod
    def linear_dynamics(self):
        """(A (n, n), B (n, n_inputs))."""

    def state_affine_form(self):
        a, b = self.linear_dynamics()
        return a, b, lambda u: jnp.reshape(u, (-1,))

    def vector_field(self, t, x, u):
        a, b = self.linear_dynamics()
        return a @ x + b @ jnp.reshape(u, (-1,))


class AbstractSteppedDevice(AbstractDevice):
    """A device whose simulation is not an ODE (e.g. per-step quasi-static contact maps).

    It implements `observe_schedule(sched, method)` itself, returning the camera readings
    (N, n_y) and a success flag from one row of the stacked schedules
    (`greybox._simulate.schedules`); `fit`, `simulate` and `validate` then work unchanged
    (masks, robust loss, covariance).
    """

    @property
    @abc.abstractmethod
    def n_states(self) -> int: ...

    @abc.abstractmethod
    def observe_schedule(self, sched: dict, method: str):
        """(readings (N, n_y) in SI, success flag) for one padded schedule row."""


def simulation_methods(model) -> tuple[str, ...]:
    """The simulation paths `model` supports, the exact one first."""
    if isinstance(model, (AbstractLinearDevice, AbstractSteppedDevice)):
        return METHODS  # a stepped device steps on the ZOH grid whatever the name
    if isinstance(model, AbstractODEDevice):
        return ODE_METHODS
    raise TypeError(
        f"{type(model).__name__} is not a greybox device: subclass AbstractLinearDevice, "
        "AbstractStateAffineDevice, AbstractODEDevice or AbstractSteppedDevice"
    )


def default_method(model) -> str:
    """Exact ZOH where the device is linear (or stepped), adaptive otherwise."""
    return simulation_methods(model)[0]


def check_method(model, method: str | None) -> str:
    """`method` (None = the device's default) checked against what the device supports."""
    if method is None:
        return default_method(model)
    if method not in METHODS:
        raise ValueError(f"method: {method!r} is unknown; use one of {METHODS}")
    allowed = simulation_methods(model)
    if method not in allowed:
        raise ValueError(
            f"method: {method!r} needs a linear device and {type(model).__name__} is not "
            f"linear; use method = {allowed[0]!r} ({' or '.join(map(repr, allowed[1:]))} for time "
            "scales far apart), or leave method out for the device default"
        )
    return method


def with_camera(model, *, exposure_s: float | None = None, m_per_px: float | None = None):
    """`model` with its camera's exposure time [s] and/or image scale [m/px] replaced.

    The exposure is structural (it sets the quadrature nodes), so it cannot be changed as a
    parameter value; this rebuilds the camera block with every other field kept. A device
    read out by a sensor, not a camera, has neither: asking for them is an error."""
    if exposure_s is None and m_per_px is None:
        return model
    cam = model.readout
    if not isinstance(cam, Camera):
        raise ValueError(
            f"camera: {type(model).__name__} is read out by a {type(cam).__name__}, not a "
            "camera; it has no exposure or image scale"
        )
    new_cam = type(cam)(
        m_per_px=cam.m_per_px if m_per_px is None else float(m_per_px),
        exposure_s=cam.exposure_s if exposure_s is None else float(exposure_s),
        offset_m=cam.offset_m,
        drift_m_per_s=cam.drift_m_per_s,
        n_quadrature=cam.n_quadrature,
    )
    return eqx.tree_at(lambda m: m.camera, model, new_cam)  # a camera device's field
