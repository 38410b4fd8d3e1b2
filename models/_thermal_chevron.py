"""The chain every thermally actuated chevron shares, whatever heats it.

heat source -> thermal RC -> mean beam rise -> elongation -> chevron kinematics -> quasi-static
shuttle -> camera. A device supplies the heat source (`heat_W`) and its own fields; the rest is
this one implementation (the laser-heated and the Joule-heated chevron are two compositions).
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax.numpy as jnp

from greybox.blocks import (
    ChevronExact,
    ChevronLinear,
    QuasiStaticShuttle,
    ThermalElongation,
)
from greybox import AbstractODEDevice
from greybox.blocks import AbstractThermal


class AbstractThermalChevron(AbstractODEDevice):
    """One input (laser power [W], voltage [V], ...) heating a chevron; output: shuttle [m].

    Subclasses also define `initial_rise_K` (start temperature rise of every node [K]) and the
    static `heated_node` (thermal node whose rise drives the beams). Both have defaults there,
    so they are not declared as `AbstractVar` here: a dataclass field keeps the position of its
    first declaration, and a defaulted field ahead of the subclass's own fields is an error.
    """

    thermal: eqx.AbstractVar[AbstractThermal]
    elongation: eqx.AbstractVar[ThermalElongation]
    kinematics: eqx.AbstractVar[ChevronExact | ChevronLinear]
    shuttle: eqx.AbstractVar[QuasiStaticShuttle]

    @abc.abstractmethod
    def heat_W(self, u, x):
        """Heat delivered to the thermal block (thermal.n_inputs,) [W] for input `u` (1,)."""

    @property
    def n_states(self) -> int:
        return self.thermal.n_states

    @property
    def n_inputs(self) -> int:
        return 1

    @property
    def n_outputs(self) -> int:
        return 1

    def initial_state(self):
        return jnp.full((self.n_states,), self.initial_rise_K, dtype=float)

    def vector_field(self, t, x, u):
        return self.thermal.derivative(x, self.heat_W(u, x))

    def stroke(self, theta_node_K):
        """Shuttle displacement [m] for a heated-node rise [K] (the static nonlinearity)."""
        return self.shuttle(self.kinematics(self.elongation(theta_node_K)))

    def output(self, x):
        return jnp.reshape(self.stroke(x[self.heated_node]), (1,))
