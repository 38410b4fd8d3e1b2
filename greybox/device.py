"""The interface a device model implements so `simulate` and `fit` can drive it.

A device maps an input vector u(t) (laser power [W], heater levels, ...) through state
dynamics dx/dt = f(t, x, u) to a physical output y(x) (displacement [m], temperature [K]),
observed through its `camera` block. Linear devices also expose (A, B) so the exact
zero-order-hold path can be used.
"""

from __future__ import annotations

import abc

import equinox as eqx

from greybox.blocks.camera import Camera


class AbstractDevice(eqx.Module):
    camera: eqx.AbstractVar[Camera]

    @property
    @abc.abstractmethod
    def n_states(self) -> int: ...

    @property
    @abc.abstractmethod
    def n_inputs(self) -> int: ...

    @property
    @abc.abstractmethod
    def n_outputs(self) -> int: ...

    @property
    @abc.abstractmethod
    def is_linear(self) -> bool:
        """True when dx/dt = A x + B u exactly (the ZOH path is then exact)."""

    @abc.abstractmethod
    def initial_state(self):
        """State at the start of an experiment, shape (n_states,)."""

    @abc.abstractmethod
    def vector_field(self, t, x, u):
        """dx/dt for time `t` [s], state `x` (n_states,), input `u` (n_inputs,)."""

    @abc.abstractmethod
    def linear_dynamics(self):
        """(A (n, n), B (n, n_inputs)) for linear devices; raise ValueError otherwise."""

    @abc.abstractmethod
    def output(self, x):
        """Physical output (n_outputs,) in SI for state `x`."""


class AbstractSteppedDevice(AbstractDevice):
    """A device whose simulation is not an ODE (e.g. per-step quasi-static contact maps).

    It implements `observe_schedule(sched, method)` itself, returning the camera readings
    (N, n_y) and a success flag from one row of `greybox.simulate.pad_schedules`; `fit`,
    `simulate` and `validate` then work unchanged (masks, robust loss, covariance).
    """

    @abc.abstractmethod
    def observe_schedule(self, sched: dict, method: str):
        """(readings (N, n_y) in SI, success flag) for one padded schedule row."""
