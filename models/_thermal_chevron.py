"""The chain every thermally actuated chevron shares, whatever heats it.

heat source -> thermal RC -> mean beam rise -> elongation -> chevron kinematics -> quasi-static
shuttle -> camera. A device supplies the heat source (`heat_W`) and its own fields; the rest is
this one implementation (the laser-heated and the Joule-heated chevron are two compositions).

The thermal block is either the one-node `FirstOrderThermal` (the heated node's rise times
`elongation.beam_fraction` is the mean beam rise) or a `ThermalChain` (its beam nodes give the
mean beam rise directly, `beam_fraction` = 1, optionally through an elongation lag). The
geometry-derived nominal values of a chain are made by `chain_nominals` below.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from greybox import AbstractODEDevice, ParameterInfo
from greybox.blocks import (
    AbstractThermal,
    Camera,
    ChevronExact,
    ChevronLinear,
    QuasiStaticShuttle,
    ThermalChain,
    ThermalElongation,
)

K_SI_W_PER_MK = 148.0  # thermal conductivity of Si at 300 K (PHYSICS.md §12)
RHO_CP_SI_J_PER_M3K = 1.64e6  # volumetric heat capacity of Si (PHYSICS.md §4)


def beam_conductance_W_per_K(length_m, width_m, thickness_m, n_beams=2):
    """Conductance of `n_beams` beams in parallel along their length: n k w h / L [W/K]."""
    return n_beams * K_SI_W_PER_MK * width_m * thickness_m / length_m


def chain_nominals(
    n_nodes: int,
    *,
    length_m: float,
    width_m: float,
    thickness_m: float,
    air_W_per_m2K: float,
    pad_size_m: float | None,
) -> dict:
    """Nominal `ThermalChain` values of a chevron (two half-beams of length L, width w,
    thickness h), from its geometry (PHYSICS.md §4) [derived].

    With a pad (`pad_size_m` = P, laser-heated; node 0 = pad, nodes 1..m = beam segments,
    m = n - 1, each holding a length L/m of both half-beams):
      C_pad = rho c_p P^2 h,  C_seg = rho c_p 2 L w h / m,
      R_beam = L / (2 k w h);  series R: pad -> segment 1 = R_beam / (2m), segment to segment
      = R_beam / m, last segment -> anchor = R_beam / (2m)  (nodes at segment centres),
      air: Ra_pad = 1 / (g P^2),  Ra_seg = m / (g 2 L w).
    Without a pad (`pad_size_m` None, the Joule-heated beams; nodes 0..n-1 = beam segments from
    the shuttle end, which is adiabatic by symmetry, to the anchor): C_seg = rho c_p 2 L w h / n,
    series R = R_beam / n between segment centres and R_beam / (2n) for the last to the anchor,
    Ra_seg = n / (g 2 L w); heat enters the segments equally.
    `air_W_per_m2K` = g is the air-gap conductance per footprint area.
    """
    rc, ell, w, h, g = RHO_CP_SI_J_PER_M3K, length_m, width_m, thickness_m, air_W_per_m2K
    r_beam = 1.0 / beam_conductance_W_per_K(ell, w, h)
    m = n_nodes - 1 if pad_size_m is not None else n_nodes
    if m < 1:
        raise ValueError("thermal_nodes: a pad-fed chain needs at least 2 nodes (pad + beam)")
    seg_c = rc * 2 * ell * w * h / m
    seg_air = m / (g * 2 * ell * w)
    if pad_size_m is not None:
        capacity = (rc * pad_size_m**2 * h,) + (seg_c,) * m
        series = (r_beam / (2 * m),) + (r_beam / m,) * (m - 1) + (r_beam / (2 * m),)
        air = (1.0 / (g * pad_size_m**2),) + (seg_air,) * m
        share = ()
    else:
        capacity = (seg_c,) * m
        series = (r_beam / m,) * (m - 1) + (r_beam / (2 * m),)
        air = (seg_air,) * m
        share = (1.0 / m,) * m
    return {
        "capacity_J_per_K": tuple(float(v) for v in capacity),
        "resistance_K_per_W": tuple(float(v) for v in series),
        "air_resistance_K_per_W": tuple(float(v) for v in air),
        "heat_share": share,
        "beam_nodes": tuple(range(n_nodes - m, n_nodes)),
    }


def chain_parameter_table(thermal: ThermalChain) -> tuple:
    """`ParameterInfo` rows of every named scalar of a chain at its nominal values: the
    optimiser's bounds (x100 around the nominal resistances) and the physical ranges
    (x10 for silicon beams and an air gap; x3 for the capacities, rho c_p V)."""
    rows = []
    n = thermal.n_nodes
    for i, c in enumerate(thermal.capacity_J_per_K):
        rows.append(
            ParameterInfo(
                f"thermal.capacity_J_per_K[{i}]",
                "J/K",
                c,
                c / 3,
                c * 3,
                f"heat capacity of node {i} (rho c_p V from the geometry)",
                "not separable from the resistances (PHYSICS.md §13.4): keep fixed",
            )
        )
    for i, r in enumerate(thermal.resistance_K_per_W):
        to = "the anchor" if i == n - 1 else f"node {i + 1}"
        rows.append(
            ParameterInfo(
                f"thermal.resistance_K_per_W[{i}]",
                "K/W",
                r,
                r / 100,
                r * 100,
                f"series resistance node {i} -> {to} (beam conduction L/(n k w h) share)",
                "through the second time constant and the gain, only if sampled faster than "
                "both time constants; otherwise fix (§13.3)",
                physical=(r / 10, r * 10),  # silicon: override for another material
            )
        )
    for i, r in enumerate(thermal.air_resistance_K_per_W or ()):
        rows.append(
            ParameterInfo(
                f"thermal.air_resistance_K_per_W[{i}]",
                "K/W",
                r,
                r / 100,
                r * 100,
                f"node {i} -> substrate through the air gap",
                "product with the series resistances only: fix",
                physical=(r / 10, r * 10),  # gap height and air conductivity within x10
            )
        )
    if thermal.lag_s is not None:
        rows.append(
            ParameterInfo(
                "thermal.lag_s",
                "s",
                float(thermal.lag_s),
                1e-4,
                1.0,
                "first-order lag between the mean beam rise and the elongation",
                "only if distinct from the thermal time constants and sampled faster than "
                "it: the response depends on the set of time constants, not on which is which",
            )
        )
    return tuple(rows)


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
    camera: eqx.AbstractVar[Camera]

    @property
    def readout(self) -> Camera:
        """The shuttle is filmed: the camera is the readout."""
        return self.camera

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

    def __check_init__(self):
        if not isinstance(self.kinematics, ChevronExact):
            return
        both = (self.kinematics.length_m, self.elongation.length_m)
        if all(isinstance(v, (int, float)) for v in both):
            if not np.isclose(both[0], both[1], rtol=1e-12, atol=0.0):
                raise ValueError(
                    f"kinematics.length_m: {both[0]} m differs from elongation.length_m "
                    f"{both[1]} m; the beam length is stated once (the beam_length_um option)"
                )

    def beam_rise_K(self, x):
        """Rise of the node that heats the beams [K] (a chain: its mean beam rise)."""
        if isinstance(self.thermal, ThermalChain):
            return self.thermal.beam_rise_K(x)
        return x[self.heated_node]

    def drive_rise_K(self, x):
        """Rise the elongation block sees [K]: the heated node, a chain's mean beam rise or
        its elongation-lag state."""
        if isinstance(self.thermal, ThermalChain):
            return self.thermal.elongation_rise_K(x)
        return x[self.heated_node]

    def stroke(self, theta_node_K):
        """Shuttle displacement [m] for a heated-node rise [K] (the static nonlinearity)."""
        return self.shuttle(self.kinematics(self.elongation(theta_node_K)))

    def output(self, x):
        return jnp.reshape(self.stroke(self.drive_rise_K(x)), (1,))


def chain_free_parameters(thermal) -> list:
    """The free parameters a thermal chain adds to a chevron's standard fit: the resistances
    at its two ends (pad side and anchor side), each within x30 of its nominal value, and the
    elongation lag if the structure has one. The capacities stay fixed (from the geometry)."""
    from greybox import FreeParameter

    free = []
    n = thermal.n_nodes
    for i in sorted({0, n - 1}):
        r = float(thermal.resistance_K_per_W[i])
        free.append(
            FreeParameter(
                f"thermal.resistance_K_per_W[{i}]", unit="K/W", lower=r / 30, upper=r * 30
            )
        )
    if thermal.lag_s is not None:
        free.append(FreeParameter("thermal.lag_s", unit="s", lower=1e-4, upper=1.0))
    return free
