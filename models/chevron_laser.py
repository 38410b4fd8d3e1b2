"""The laser-heated chevron actuator of Yelike (2012), composed from greybox blocks.

laser P(t) [W] -> Gaussian spot on the heated pad -> absorbed q = A F P -> one-node (or
n-node) thermal RC -> mean beam rise kappa theta -> elongation alpha L kappa theta ->
rigid-link chevron kinematics (3.5 mm beams, 2 deg pre-bend) -> quasi-static shuttle ->
camera (exposure average, offset, drift).

Nominal values and ranges: PHYSICS.md §4, §6, §12 (thesis geometry, Si at 800 nm).
What shuttle video identifies (PHYSICS.md §13): the time constant tau (when sampled fast
enough) and the static gain K ∝ A F R kappa alpha L / sin(a); A, F, R, kappa and a enter only
as a product, so a fit frees at most one of them unless priors say more.

Structural options ([model] in experiment.toml):

- `thermal_nodes` = 1 (default): one node, tau dtheta/dt = R q - theta, mean beam rise
  kappa theta with kappa = 0.5. n >= 2: a `ThermalChain` pad -> n - 1 beam segments ->
  anchor, each node also cooled through the air gap; the mean of the beam nodes is the mean
  beam rise (kappa = 1).
- `elongation_lag`: a first-order lag `thermal.lag_s` between the mean beam rise and the
  elongation (with one node the thermal block is then a one-node `ThermalChain`).
- `beam_length_um`, `angle_deg`, `beam_width_um`, `beam_thickness_um`: the geometry, stated
  once. The elongation and the kinematics get the same length, and the nominal thermal values
  follow from it [derived, PHYSICS.md §4]:
    C = rho c_p (2 L w h + P^2 h),  G = 2 k w h / L + g_air (2 L w + P^2),
    one node: tau = C / G, R = 1 / G (the air-gap conductance per area g_air is calibrated
    so that the thesis device has tau = 40 ms exactly: the default model is unchanged);
    chains: `chain_nominals` in `_thermal_chevron.py` (same C, R_beam = L / (2 k w h), g_air).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from greybox import AbstractLinearDevice, DeviceSpec, FreeParameter, Option, ParameterInfo
from greybox.blocks import (
    AbstractThermal,
    Camera,
    ChevronExact,
    ChevronLinear,
    FirstOrderThermal,
    GaussianSpot,
    QuasiStaticShuttle,
    RectangularFrame,
    ThermalChain,
    ThermalElongation,
)
from greybox.devices import DISPLACEMENT, LASER_POWER

from ._common import rest_level_offsets
from ._thermal_chevron import (
    AbstractThermalChevron,
    beam_conductance_W_per_K,
    chain_free_parameters,
    chain_nominals,
    chain_parameter_table,
)

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
NOMINAL_LAG_S = 0.010  # elongation lag [assumed]: a few ms of beam diffusion not in the nodes


def _nominal_heat_capacity(
    length_m=BEAM_LENGTH_M, width_m=BEAM_WIDTH_M, thickness_m=BEAM_THICKNESS_M
) -> float:
    beams = 2 * length_m * width_m * thickness_m
    pad = PAD_SIZE_M**2 * thickness_m
    return RHO_CP_J_PER_M3K * (beams + pad)  # ≈ 2.95e-5 J/K for the thesis device


def _footprint_m2(length_m=BEAM_LENGTH_M, width_m=BEAM_WIDTH_M) -> float:
    """Area facing the substrate: two half-beams and the pad [m^2]."""
    return 2 * length_m * width_m + PAD_SIZE_M**2


NOMINAL_TAU_S = 0.040
NOMINAL_RESISTANCE_K_PER_W = NOMINAL_TAU_S / _nominal_heat_capacity()
# Air-gap conductance per footprint area [W/(m^2 K)], calibrated so that C / G = 40 ms for the
# thesis device (≈ 3.2e3, i.e. k_air / g for an ≈ 8 um effective gap) [derived]
AIR_W_PER_M2K = (
    _nominal_heat_capacity() / NOMINAL_TAU_S
    - beam_conductance_W_per_K(BEAM_LENGTH_M, BEAM_WIDTH_M, BEAM_THICKNESS_M)
) / _footprint_m2()


def _conductance_W_per_K(length_m, width_m, thickness_m) -> float:
    """G = 2 k w h / L (both half-beams to the anchors) + g_air (2 L w + P^2) [W/K]."""
    cond = beam_conductance_W_per_K(length_m, width_m, thickness_m)
    return cond + AIR_W_PER_M2K * _footprint_m2(length_m, width_m)


def one_node_nominals(length_m, width_m, thickness_m) -> tuple[float, float]:
    """(tau [s], R [K/W]) of the one-node model for a geometry: tau = C / G, R = 1 / G.

    Evaluated as a ratio to the thesis device, so that the thesis geometry gives exactly
    tau = 40 ms and R = tau / C, the values the committed data sets were made with."""
    c = _nominal_heat_capacity(length_m, width_m, thickness_m)
    g = _conductance_W_per_K(length_m, width_m, thickness_m)
    c0 = _nominal_heat_capacity()
    g0 = _conductance_W_per_K(BEAM_LENGTH_M, BEAM_WIDTH_M, BEAM_THICKNESS_M)
    tau = NOMINAL_TAU_S * ((c / g) / (c0 / g0))
    return tau, tau / c


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
        theta_per_w = self.drive_rise_K(-jnp.linalg.solve(a, b)[:, 0])
        return jax.grad(self.stroke)(0.0) * theta_per_w


def _thermal_block(thermal_nodes, elongation_lag, length_m, width_m, thickness_m):
    """The thermal block for the structural options, at its geometry-derived nominal values."""
    if thermal_nodes == 1:
        tau, resistance = one_node_nominals(length_m, width_m, thickness_m)
        if not elongation_lag:
            return FirstOrderThermal(tau_s=tau, resistance_K_per_W=resistance)
        c = _nominal_heat_capacity(length_m, width_m, thickness_m)
        return ThermalChain(
            capacity_J_per_K=(c,), resistance_K_per_W=(resistance,), lag_s=NOMINAL_LAG_S
        )
    values = chain_nominals(
        thermal_nodes,
        length_m=length_m,
        width_m=width_m,
        thickness_m=thickness_m,
        air_W_per_m2K=AIR_W_PER_M2K,
        pad_size_m=PAD_SIZE_M,
    )
    return ThermalChain(**values, lag_s=NOMINAL_LAG_S if elongation_lag else None)


def build(
    *,
    kinematics: str = "exact",
    thermal_nodes: int = 1,
    elongation_lag: bool = False,
    beam_length_um: float = 3500.0,
    angle_deg: float = 2.0,
    beam_width_um: float = 20.0,
    beam_thickness_um: float = 100.0,
) -> LaserChevron:
    """The chevron at nominal values for the structural options (see the module docstring),
    filmed at 0.645 um per pixel with a 10 ms exposure (an experiment's [camera] table
    replaces both). The defaults are the thesis device."""
    length = beam_length_um / 1e6  # one length for the elongation and the kinematics
    width, thickness = beam_width_um / 1e6, beam_thickness_um / 1e6
    angle = np.deg2rad(angle_deg)
    model = LaserChevron(
        spot=GaussianSpot(waist_m=150e-6),
        target=RectangularFrame.square(0.0, 0.0, PAD_SIZE_M),
        absorptance=0.67,  # Si >= 100 um at 800 nm
        thermal=_thermal_block(thermal_nodes, elongation_lag, length, width, thickness),
        elongation=ThermalElongation(
            cte_per_K=CTE_SI_PER_K,
            length_m=length,
            beam_fraction=0.5 if thermal_nodes == 1 else 1.0,  # chains give the beam mean
        ),
        kinematics=ChevronExact(length_m=length, angle_rad=angle)
        if kinematics == "exact"
        else ChevronLinear(angle),
        shuttle=QuasiStaticShuttle(stiffness_N_per_m=241.5),
        camera=Camera(m_per_px=0.645e-6, exposure_s=0.010),
    )
    return model


def parameters(**options) -> tuple[ParameterInfo, ...]:
    """The parameter table for the structural options (nominals from the geometry)."""
    model = build(**options)
    thermal = model.thermal
    angle = float(model.kinematics.angle_rad)
    if isinstance(thermal, FirstOrderThermal):
        tau, r = float(thermal.tau_s), float(thermal.resistance_K_per_W)
        thermal_rows = (
            ParameterInfo(
                "thermal.tau_s",
                "s",
                tau,
                min(1e-4, tau / 30),
                max(2.0, tau * 30),
                "thermal time constant C/G",
                "identifiable if frames are faster than tau or tau >~ 20-50 ms",
                # C from rho c_p and the geometry; G within x10 (conduction, air gap)
                physical=(min(1e-3, tau / 10), max(0.2, tau * 10)),
            ),
            ParameterInfo(
                "thermal.resistance_K_per_W",
                "K/W",
                r,
                min(20.0, r / 30),
                max(1e5, r * 30),
                "thermal resistance 1/G",
                "product with absorptance only",
                physical=(min(200.0, r / 10), max(1e4, r * 10)),
            ),
        )
    else:
        thermal_rows = chain_parameter_table(thermal)
    kappa = float(model.elongation.beam_fraction)
    return (
        ParameterInfo(
            "absorptance",
            "1",
            0.67,
            0.01,
            1.0,
            "absorptance of the heated Si pad at 800 nm",
            "product with spot fraction and thermal resistance only",
            # 1 - reflectance of Si thicker than its absorption depth: bare 0.67; thin films
            # move it within ~0.4-0.95 (a metal coating: override in [physical_ranges])
            physical=(0.3, 1.0),
        ),
        ParameterInfo(
            "spot.waist_m", "m", 150e-6, 25e-6, 500e-6, "1/e^2 spot radius", "not identifiable"
        ),
        *thermal_rows,
        ParameterInfo(
            "elongation.beam_fraction",
            "1",
            kappa,
            0.3,
            1.0,
            "mean beam rise / pad rise" if kappa != 1.0 else "mean beam rise / beam-node mean",
            "product only",
        ),
        ParameterInfo(
            "elongation.cte_per_K",
            "1/K",
            CTE_SI_PER_K,
            2.5e-6,
            3.3e-6,
            "CTE of Si",
            "fixed",
            physical=(2.0e-6, 4.5e-6),  # Si from 250 K to 700 K
        ),
        ParameterInfo(
            "kinematics.angle_rad",
            "rad",
            angle,
            min(float(np.deg2rad(0.05)), angle / 10),
            max(float(np.deg2rad(30.0)), angle * 2),
            "chevron pre-bend angle",
            "weak (curvature only)",
            # the mask angle, give or take what etching and buckling change: x2
            physical=(
                min(float(np.deg2rad(0.5)), angle / 2),
                max(float(np.deg2rad(10.0)), 2 * angle),
            ),
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


PARAMETERS = parameters()  # the thesis device (default options)


def default_free_parameters(**options) -> list[FreeParameter]:
    """The standard fit: the thermal dynamics and the gain carrier (absorptance) shared, one
    offset per run.

    One node: tau and absorptance. Absorptance carries the static gain
    K ∝ A F R kappa alpha L / sin(a) while the other factors stay fixed (PHYSICS.md §13):
    freeing the thermal resistance as well needs a prior, and the report then shows the two as
    prior-dominated with only their product determined.
    Chains (or a lag): capacities come from the geometry and stay fixed (§13.4); the first
    and last series resistances (pad -> beam and beam -> anchor: the two thermal time
    constants) and the lag are freed, with absorptance as the gain carrier."""
    offset = FreeParameter("camera.offset_m", unit="m", per_experiment=True, scale=1e-6)
    gain = FreeParameter("absorptance", unit="1", lower=0.05, upper=1.0)
    thermal = build(**options).thermal
    if isinstance(thermal, FirstOrderThermal):
        return [gain, FreeParameter("thermal.tau_s", unit="s", lower=1e-4, upper=2.0), offset]
    return [gain, *chain_free_parameters(thermal), offset]


OPTIONS = (
    Option(
        "kinematics",
        "exact",
        "chevron kinematics: exact rigid-link geometry or its small-stroke linearisation",
        choices=("exact", "linear"),
    ),
    Option(
        "thermal_nodes",
        1,
        "thermal nodes: 1 = one-node RC (tau, R); n >= 2 = pad -> n - 1 beam segments -> anchor",
        minimum=1,
        maximum=8,
    ),
    Option(
        "elongation_lag",
        False,
        "a first-order lag (thermal.lag_s) between the mean beam rise and the elongation",
    ),
    Option(
        "beam_length_um",
        3500.0,
        "length of each half-beam (elongation, kinematics and thermal nominals)",
        minimum=10.0,
        maximum=20000.0,
        unit="um",
    ),
    Option(
        "angle_deg",
        2.0,
        "chevron pre-bend angle from the transverse axis",
        minimum=0.05,
        maximum=30.0,
        unit="deg",
    ),
    Option(
        "beam_width_um",
        20.0,
        "in-plane beam width (thermal nominals)",
        minimum=0.5,
        maximum=500.0,
        unit="um",
    ),
    Option(
        "beam_thickness_um",
        100.0,
        "beam (device layer) thickness (thermal nominals)",
        minimum=0.5,
        maximum=1000.0,
        unit="um",
    ),
)


SPEC = DeviceSpec(
    name="chevron_laser",
    inputs=INPUTS,
    outputs=OUTPUTS,
    build=build,
    parameters=parameters,
    default_free=default_free_parameters,
    options=OPTIONS,
    start_values=rest_level_offsets("camera.offset_m"),
    description=__doc__.split("\n\n")[0],
    state_unit="K",  # temperature rises of the nodes (and of the elongation lag)
)
