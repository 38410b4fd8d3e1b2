"""The laser-heated chevron actuator of Yelike (2012), composed from greybox blocks.

laser P(t) [W] -> Gaussian spot on the heated pad -> absorbed q = A F P -> one-node (or
n-node) thermal RC -> mean beam rise kappa theta -> elongation alpha L kappa theta ->
rigid-link chevron kinematics (3.5 mm beams, 2 deg pre-bend) -> quasi-static shuttle ->
camera (exposure average, offset, drift).

Nominal values and ranges: PHYSICS.md §4, §6, §12 (thesis geometry, Si at 800 nm).
What shuttle video identifies (PHYSICS.md §13): the time constant tau (when sampled fast
enough) and the static gain K ∝ A F R kappa alpha L / sin(a); A, F, R, kappa and a enter only
as a product, so a fit frees at most one of them unless priors say more.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from greybox import (
    DISPLACEMENT,
    LASER_POWER,
    AbstractLinearDevice,
    DeviceSpec,
    FreeParameter,
    Option,
    ParameterInfo,
)
from greybox.blocks import (
    AbstractThermal,
    Camera,
    ChevronExact,
    ChevronLinear,
    FirstOrderThermal,
    GaussianSpot,
    QuasiStaticShuttle,
    RectangularFrame,
    ThermalElongation,
)

from ._common import rest_level_offsets
from ._thermal_chevron import AbstractThermalChevron

NAME = "chevron_laser"
INPUTS = (LASER_POWER,)
OUTPUTS = (DISPLACEMENT,)

# Geometry and material of the thesis device [SI]
BEAM_LENGTH_M = 3.5e-3
BEAM_WIDTH_M = 20e-6
BEAM_THICKNESS_M = 100e-6
PAD_SIZE_M = 200e-6
RHO_CP_J_PER_M3K = 1.64e6  # silicon
CTE_SI_PER_K = 2.6e-6


def _nominal_heat_capacity() -> float:
    beams = 2 * BEAM_LENGTH_M * BEAM_WIDTH_M * BEAM_THICKNESS_M
    pad = PAD_SIZE_M**2 * BEAM_THICKNESS_M
    return RHO_CP_J_PER_M3K * (beams + pad)  # ≈ 2.95e-5 J/K


NOMINAL_TAU_S = 0.040
NOMINAL_RESISTANCE_K_PER_W = NOMINAL_TAU_S / _nominal_heat_capacity()


class LaserChevron(AbstractThermalChevron, AbstractLinearDevice):
    """A chevron actuator heated by a laser spot on its pad; output = shuttle displacement [m]."""

    spot: GaussianSpot
    target: RectangularFrame
    absorptance: float
    thermal: AbstractThermal
    elongation: ThermalElongation
    kinematics: ChevronExact | ChevronLinear
    shuttle: QuasiStaticShuttle
    camera: Camera
    initial_rise_K: float = 0.0
    heated_node: int = eqx.field(static=True, default=0)

    def vector_field(self, t, x, u):
        return AbstractLinearDevice.vector_field(self, t, x, u)

    def absorbed_fraction(self):
        """Absorbed watts per watt of laser at the sample: A F."""
        return self.absorptance * self.target.fraction(self.spot)

    def heat_W(self, u, x):
        q = self.absorbed_fraction() * jnp.reshape(u, (-1,))[0]
        return jnp.broadcast_to(q, (self.thermal.n_inputs,))

    def linear_dynamics(self):
        a, b = self.thermal.linear_matrices()
        return a, b * self.absorbed_fraction()

    def static_gain_m_per_W(self):
        """Small-signal steady-state displacement per watt of laser [m/W] (linearised at 0)."""
        import jax

        a, b = self.linear_dynamics()
        theta_per_w = -jnp.linalg.solve(a, b)[self.heated_node, 0]
        return jax.grad(self.stroke)(0.0) * theta_per_w


def build(*, kinematics: str = "exact") -> LaserChevron:
    """The thesis chevron at nominal values (`kinematics`: "exact" or "linear"), filmed at
    0.645 um per pixel with a 10 ms exposure (an experiment's [camera] table replaces both)."""
    angle = np.deg2rad(2.0)
    model = LaserChevron(
        spot=GaussianSpot(waist_m=150e-6),
        target=RectangularFrame.square(0.0, 0.0, PAD_SIZE_M),
        absorptance=0.67,  # Si >= 100 um at 800 nm
        thermal=FirstOrderThermal(
            tau_s=NOMINAL_TAU_S, resistance_K_per_W=NOMINAL_RESISTANCE_K_PER_W
        ),
        elongation=ThermalElongation(
            cte_per_K=CTE_SI_PER_K, length_m=BEAM_LENGTH_M, beam_fraction=0.5
        ),
        kinematics=ChevronExact(length_m=BEAM_LENGTH_M, angle_rad=angle)
        if kinematics == "exact"
        else ChevronLinear(angle),
        shuttle=QuasiStaticShuttle(stiffness_N_per_m=241.5),
        camera=Camera(m_per_px=0.645e-6, exposure_s=0.010),
    )
    return model


PARAMETERS = (
    ParameterInfo(
        "absorptance",
        "1",
        0.67,
        0.40,
        0.70,
        "absorptance of the heated Si pad at 800 nm",
        "product with spot fraction and thermal resistance only",
    ),
    ParameterInfo(
        "spot.waist_m", "m", 150e-6, 25e-6, 500e-6, "1/e^2 spot radius", "not identifiable"
    ),
    ParameterInfo(
        "thermal.tau_s",
        "s",
        NOMINAL_TAU_S,
        1e-3,
        0.2,
        "thermal time constant C/G",
        "identifiable if frames are faster than tau or tau >~ 20-50 ms",
    ),
    ParameterInfo(
        "thermal.resistance_K_per_W",
        "K/W",
        NOMINAL_RESISTANCE_K_PER_W,
        200.0,
        1e4,
        "thermal resistance 1/G",
        "product with absorptance only",
    ),
    ParameterInfo(
        "elongation.beam_fraction", "1", 0.5, 0.3, 1.0, "mean beam rise / pad rise", "product only"
    ),
    ParameterInfo(
        "elongation.cte_per_K", "1/K", CTE_SI_PER_K, 2.5e-6, 3.3e-6, "CTE of Si", "fixed"
    ),
    ParameterInfo(
        "kinematics.angle_rad",
        "rad",
        float(np.deg2rad(2.0)),
        float(np.deg2rad(0.5)),
        float(np.deg2rad(5.0)),
        "chevron pre-bend angle",
        "weak (curvature only)",
    ),
    ParameterInfo(
        "camera.offset_m",
        "m",
        0.0,
        None,
        None,
        "image position of zero displacement",
        "identifiable, one per run",
    ),
    ParameterInfo(
        "camera.drift_m_per_s",
        "m/s",
        0.0,
        None,
        None,
        "stage/focus drift",
        "only with long laser-off segments",
    ),
)


def default_free_parameters(**_options) -> list[FreeParameter]:
    """The standard fit: tau and the gain carrier (absorptance) shared, one offset per run.

    Absorptance carries the static gain K ∝ A F R kappa alpha L / sin(a) while the other
    factors stay fixed (PHYSICS.md §13): freeing the thermal resistance as well needs a prior,
    and the report then shows the two as prior-dominated with only their product determined."""
    return [
        FreeParameter("absorptance", unit="1", lower=0.05, upper=1.0),
        FreeParameter("thermal.tau_s", unit="s", lower=1e-4, upper=2.0),
        FreeParameter("camera.offset_m", unit="m", per_experiment=True, scale=1e-6),
    ]


SPEC = DeviceSpec(
    name="chevron_laser",
    inputs=INPUTS,
    outputs=OUTPUTS,
    build=build,
    parameters=PARAMETERS,
    default_free=default_free_parameters,
    options=(
        Option(
            "kinematics",
            "exact",
            "chevron kinematics: exact rigid-link geometry or its small-stroke linearisation",
            choices=("exact", "linear"),
        ),
    ),
    start_values=rest_level_offsets("camera.offset_m"),
    description=__doc__.split("\n\n")[0],
)
