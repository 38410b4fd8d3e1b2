"""Beam elongation, chevron kinematics and the quasi-static shuttle (PHYSICS.md §6-7). SI units."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp


def okada_tokumaru_cte(temperature_K):
    """Linear CTE of silicon [1/K] (Okada & Tokumaru 1984); 2.57e-6 at 300 K."""
    t = temperature_K
    return (3.725 * (1.0 - jnp.exp(-5.88e-3 * (t - 124.0))) + 5.548e-4 * t) * 1e-6


class ThermalElongation(eqx.Module):
    """Beam elongation dL = cte * L * theta_beam, with theta_beam = beam_fraction * theta_node.

    - `cte_per_K`: thermal expansion coefficient [1/K] (used when `temperature_dependent` is off).
    - `length_m`: beam length [m]; `beam_fraction`: mean beam rise / heated-node rise (kappa).
    - `temperature_dependent`: integrate Okada-Tokumaru alpha(T) from `reference_K` instead.
    """

    cte_per_K: float
    length_m: float
    beam_fraction: float = 0.5
    reference_K: float = 300.0
    temperature_dependent: bool = eqx.field(static=True, default=False)

    def __call__(self, theta_node_K):
        rise = self.beam_fraction * theta_node_K
        if self.temperature_dependent:  # midpoint rule of the integral of alpha(T) dT
            return okada_tokumaru_cte(self.reference_K + rise / 2) * self.length_m * rise
        return self.cte_per_K * self.length_m * rise


class ChevronExact(eqx.Module):
    """Rigid-link chevron (PHYSICS.md §0.2, corrected thesis eq. 2.1).

    y = sqrt(L^2 sin^2 a + 2 L dL + dL^2) - L sin a, for pre-bend `angle_rad` (from the transverse
    axis) and beam `length_m` [m]. Smooth for dL > -L sin^2(a) / 2.
    """

    length_m: float
    angle_rad: float

    def __call__(self, elongation_m):
        ls = self.length_m * jnp.sin(self.angle_rad)
        growth = 2.0 * self.length_m * elongation_m + elongation_m**2
        # (sqrt(ls^2 + g) - ls) rewritten as g / (sqrt(ls^2 + g) + ls): no cancellation at tiny dL
        return growth / (jnp.sqrt(ls**2 + growth) + ls)


class ChevronLinear(eqx.Module):
    """Linearised chevron: y = dL / sin a (valid while dL << L sin^2(a) / 2)."""

    angle_rad: float

    def __call__(self, elongation_m):
        return elongation_m / jnp.sin(self.angle_rad)


def chevron_stiffness_N_per_m(youngs_Pa, width_m, thickness_m, length_m, angle_rad, n_pairs=1):
    """Shuttle-direction stiffness of n beam pairs: 2n[(EA/L) sin^2 a + (12EI/L^3) cos^2 a]."""
    area = width_m * thickness_m
    inertia = thickness_m * width_m**3 / 12.0
    s, c = jnp.sin(angle_rad), jnp.cos(angle_rad)
    return (
        2
        * n_pairs
        * (youngs_Pa * area / length_m * s**2 + 12 * youngs_Pa * inertia / length_m**3 * c**2)
    )


def chevron_blocked_force_N(
    youngs_Pa, width_m, thickness_m, cte_per_K, rise_K, angle_rad, n_pairs=1
):
    """Blocked force of n beam pairs: 2 n E A alpha dT sin a [N]."""
    return 2 * n_pairs * youngs_Pa * width_m * thickness_m * cte_per_K * rise_K * jnp.sin(angle_rad)


class QuasiStaticShuttle(eqx.Module):
    """Quasi-static compliant shuttle: y = gain * y_free - load_N / stiffness (PHYSICS.md §7).

    Inertia and damping are dropped: the mechanical resonance (kHz) is far above the thermal
    bandwidth and the camera rate. `gain` is a lever/linkage ratio (1 for a bare shuttle).
    """

    stiffness_N_per_m: float
    load_N: float = 0.0
    gain: float = 1.0

    def __call__(self, free_stroke_m):
        return self.gain * free_stroke_m - self.load_N / self.stiffness_N_per_m
