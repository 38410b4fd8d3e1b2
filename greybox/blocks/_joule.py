"""Joule heating of a resistive structure driven by a voltage (thesis ch. 5 chevrons).

q = V^2 / R(theta),  R(theta) = R0 (1 + tcr theta)

with theta the rise [K] of the node whose temperature sets the resistance (for directly heated
chevron beams: their mean rise). A positive temperature coefficient of resistance (TCR) makes
the heating self-limiting; it also makes the heat input depend on the state, so a device using
this block is linear in the state only when tcr = 0 (PHYSICS.md-style tag: [derived]).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp


class JouleHeating(eqx.Module):
    """- `resistance_ohm`: electrical resistance R0 at ambient [ohm] (> 0; an ohmmeter reading).
    - `tcr_per_K`: temperature coefficient of resistance [1/K] (0 = constant resistance).
    """

    resistance_ohm: float
    tcr_per_K: float = 0.0

    def __check_init__(self):
        r = self.resistance_ohm
        if isinstance(r, (int, float)) and not r > 0:
            raise ValueError(f"resistance_ohm: {r} must be > 0 ohm")

    def resistance(self, theta_K):
        """R(theta) [ohm] at a rise `theta_K` above ambient."""
        return self.resistance_ohm * (1.0 + self.tcr_per_K * theta_K)

    def power_W(self, voltage_V, theta_K=0.0):
        """Dissipated power [W] for an applied voltage [V] at node rise `theta_K` [K]."""
        return voltage_V**2 / self.resistance(theta_K)

    def steady_rise_K(self, voltage_V, resistance_K_per_W):
        """Steady rise [K] of a node with thermal resistance R_th heated by this block.

        Solves theta = R_th V^2 / (R0 (1 + tcr theta)), i.e. tcr theta^2 + theta - R_th V^2/R0 = 0,
        in the cancellation-free form theta = 2 c / (1 + sqrt(1 + 4 tcr c)) with c = R_th V^2 / R0
        (equal to c when tcr = 0).
        """
        c = resistance_K_per_W * voltage_V**2 / self.resistance_ohm
        return 2.0 * c / (1.0 + jnp.sqrt(1.0 + 4.0 * self.tcr_per_K * c))

    @property
    def is_state_independent(self) -> bool:
        """True when the heat input does not depend on temperature (tcr == 0, known concretely).

        A traced (abstract) tcr counts as state-dependent: decide linearity outside `jit`.
        """
        tcr = self.tcr_per_K
        if isinstance(tcr, jax.core.Tracer):
            return False
        return float(tcr) == 0.0
