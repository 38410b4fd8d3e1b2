"""The electro-thermal chevron of Yelike (2012) ch. 5, composed from greybox blocks.

voltage V(t) [V] -> Joule power V^2 / (R0 (1 + tcr theta)) -> one-node (or n-node) thermal RC
-> mean beam rise kappa theta -> elongation alpha L kappa theta -> rigid-link chevron kinematics
-> quasi-static shuttle -> (interferometer / camera) displacement [m].

The thesis (ch. 5) drove "large" chevrons with a 0-25 V square wave at 0-400 Hz, measured the
shuttle with a Veeco Wyko NT1100 interferometer and the force with a piezoresistive sensor; it
gives no geometry for them. Nominal values (tags as in PHYSICS.md):

- geometry of the thesis chevron, L = 3.5 mm, a = 2 deg, w = 20 um, h = 100 um, one pair
  [assumed: the ch. 5 devices are taken to share the ch. 1-3 layout];
- the thermal node is the mean beam temperature, kappa = 1: the beams are heated directly [derived];
- tau = 7 ms: air-gap-dominated cooling over a 2 um gap (PHYSICS.md §4 table, 7.3 ms) [derived];
- R_th = 300 K/W = tau / C with C = rho c_p V_beams = 2.3e-5 J/K [derived];
- R0 = 2 kOhm (doped Si, rho_e ~ 0.05 Ohm cm over 2 x 3.5 mm x 20 x 100 um) [assumed];
- TCR = 1e-3 /K (moderately doped Si) [assumed];
- E = 169 GPa, alpha = 2.6e-6 /K (PHYSICS.md §12) [recalled/published].

At 24 V DC this gives a ~80 K mean beam rise and a ~19 um stroke; at 400 Hz the swing is ~10 %
of that (tau = 7 ms against a 2.5 ms period).

Structural options ([model]): `thermal_nodes` = 1 (the one-node RC above) or n >= 2, a
`ThermalChain` of n beam segments from the shuttle end (adiabatic by symmetry) to the anchor,
Joule heat shared equally, each segment cooled through the air gap, with nominals from the
geometry [derived]: C_seg = rho c_p 2 L w h / n, series R = L / (2 k w h n) between segment
centres (half of it for the last one to the anchor), air R = n / (g 2 L w) with g calibrated
so the uniformly heated beams have the one-node steady gain: 1 / R_th = 6 k w h / L + g 2 L w
(g ≈ 2.0e4 W/(m^2 K)); `elongation_lag` adds a first-order lag `thermal.lag_s` between the
mean beam rise and the elongation. The TCR acts on the mean beam rise (not the lagged one).

What an amplitude-frequency table of peak-to-peak strokes identifies: tau (from the roll-off in
frequency), the gain R_th alpha L / (R0 sin a) (the stroke scale), and the TCR (the curvature in
V^2 beyond the known chevron kinematics). R_th, R0, alpha and kappa enter only as a product, so a
fit frees R_th and holds R0 (measured) and the material values fixed.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from greybox import (
    AbstractStateAffineDevice,
    Channel,
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
    JouleHeating,
    QuasiStaticShuttle,
    ThermalChain,
    ThermalElongation,
    chevron_blocked_force_N,
    chevron_stiffness_N_per_m,
)
from greybox.devices import DISPLACEMENT

from . import _surface as surface  # noqa: F401  (polynomial response surfaces of ch. 5)
from ._force_sensor import ForceSensor, RepeatAverage, average_repeats  # noqa: F401
from ._thermal_chevron import (
    AbstractThermalChevron,
    chain_free_parameters,
    chain_nominals,
    chain_parameter_table,
)

NAME = "electrothermal_chevron"
VOLTAGE = Channel("V", "V", {"V": (1.0, 0.0), "mV": (1e-3, 0.0)}, "voltage across the chevron")
INPUTS = (VOLTAGE,)
OUTPUTS = (DISPLACEMENT,)

BEAM_LENGTH_M = 3.5e-3
BEAM_WIDTH_M = 20e-6
BEAM_THICKNESS_M = 100e-6
ANGLE_RAD = float(np.deg2rad(2.0))
RHO_CP_J_PER_M3K = 1.64e6
CTE_SI_PER_K = 2.6e-6
YOUNGS_SI_PA = 169e9
NOMINAL_TAU_S = 0.007
NOMINAL_RESISTANCE_K_PER_W = 300.0
NOMINAL_R0_OHM = 2000.0
NOMINAL_TCR_PER_K = 1e-3
NOMINAL_LAG_S = 0.002  # elongation lag [assumed]
K_SI_W_PER_MK = 148.0
# Air-gap conductance per footprint area [W/(m^2 K)] that gives uniformly Joule-heated beams
# (mean rise q L / (6 k w h) by conduction alone) the one-node gain R_th [derived]
AIR_W_PER_M2K = (
    1.0 / NOMINAL_RESISTANCE_K_PER_W
    - 6 * K_SI_W_PER_MK * BEAM_WIDTH_M * BEAM_THICKNESS_M / BEAM_LENGTH_M
) / (2 * BEAM_LENGTH_M * BEAM_WIDTH_M)


class ElectrothermalChevron(AbstractThermalChevron, AbstractStateAffineDevice):
    """A Joule-heated chevron; input = voltage [V], output = shuttle displacement [m].

    Not linear in the `simulate` sense (the input enters as V^2); when the TCR is 0 and the
    thermal block is linear, `state_affine_form()` gives dx/dt = A x + B g(u) with g(V) = V^2/R0,
    which the periodic steady state uses in closed form.
    """

    joule: JouleHeating
    thermal: AbstractThermal
    elongation: ThermalElongation
    kinematics: ChevronExact | ChevronLinear
    shuttle: QuasiStaticShuttle
    camera: Camera
    youngs_Pa: float = YOUNGS_SI_PA
    beam_width_m: float = BEAM_WIDTH_M
    beam_thickness_m: float = BEAM_THICKNESS_M
    initial_rise_K: float = 0.0
    n_pairs: int = eqx.field(static=True, default=1)
    heated_node: int = eqx.field(static=True, default=0)

    def is_state_affine(self) -> bool:
        """True when dx/dt = A x + B g(u) (constant resistance, linear thermal block)."""
        return bool(self.thermal.is_linear and self.joule.is_state_independent)

    def vector_field(self, t, x, u):
        return AbstractThermalChevron.vector_field(self, t, x, u)

    def heat_W(self, u, x):
        """Heat input (thermal.n_inputs,) [W] for input `u` (1,) [V] and state `x`."""
        q = self.joule.power_W(jnp.reshape(u, (-1,))[0], self.beam_rise_K(x))
        return jnp.broadcast_to(q, (self.thermal.n_inputs,))

    def state_affine_form(self):
        """(A, B, g) with dx/dt = A x + B g(u); only when `is_state_affine` (tcr = 0)."""
        a, b = self.thermal.linear_matrices()

        def heat(u):
            return self.heat_W(u, jnp.zeros(self.n_states))

        return a, b, heat

    def dc_rise_K(self, voltage_V):
        """Steady heated-node rise [K] under a constant voltage (closed form, one-node model)."""
        if not isinstance(self.thermal, FirstOrderThermal):
            from greybox.waveforms import steady_state

            return self.beam_rise_K(steady_state(self, jnp.reshape(voltage_V, (1,))))
        return self.joule.steady_rise_K(voltage_V, self.thermal.resistance_K_per_W)

    def stiffness_N_per_m(self):
        """Shuttle-direction stiffness of the beam pairs [N/m] (PHYSICS.md §6)."""
        return chevron_stiffness_N_per_m(
            self.youngs_Pa,
            self.beam_width_m,
            self.beam_thickness_m,
            self.kinematics.length_m,
            self.kinematics.angle_rad,
            self.n_pairs,
        )

    def blocked_force_N(self, voltage_V):
        """Blocked force 2 n E A alpha dT sin a [N] at a DC voltage, dT = mean beam rise."""
        rise = self.elongation.beam_fraction * self.dc_rise_K(voltage_V)
        return chevron_blocked_force_N(
            self.youngs_Pa,
            self.beam_width_m,
            self.beam_thickness_m,
            self.elongation.cte_per_K,
            rise,
            self.kinematics.angle_rad,
            self.n_pairs,
        )

    def sensor_force_N(self, voltage_V, sensor_stiffness_N_per_m):
        """Force on a sensor of stiffness C [N/m] touching the shuttle: F_block C / (C + k_y).

        The chevron acts as a force source with internal stiffness k_y in series with the sensor
        spring, so a compliant sensor reads less than the blocked force [derived].
        """
        k = self.stiffness_N_per_m()
        return (
            self.blocked_force_N(voltage_V)
            * sensor_stiffness_N_per_m
            / (sensor_stiffness_N_per_m + k)
        )


def _thermal_block(thermal_nodes: int, elongation_lag: bool):
    lag = NOMINAL_LAG_S if elongation_lag else None
    if thermal_nodes == 1:
        if lag is None:
            return FirstOrderThermal(
                tau_s=NOMINAL_TAU_S, resistance_K_per_W=NOMINAL_RESISTANCE_K_PER_W
            )
        return ThermalChain(
            capacity_J_per_K=(NOMINAL_TAU_S / NOMINAL_RESISTANCE_K_PER_W,),
            resistance_K_per_W=(NOMINAL_RESISTANCE_K_PER_W,),
            lag_s=lag,
        )
    values = chain_nominals(
        thermal_nodes,
        length_m=BEAM_LENGTH_M,
        width_m=BEAM_WIDTH_M,
        thickness_m=BEAM_THICKNESS_M,
        air_W_per_m2K=AIR_W_PER_M2K,
        pad_size_m=None,
    )
    return ThermalChain(**values, lag_s=lag)


def build(
    *, kinematics: str = "exact", thermal_nodes: int = 1, elongation_lag: bool = False
) -> ElectrothermalChevron:
    """The nominal electro-thermal chevron (`kinematics`: "exact" or "linear"; thermal
    structure: see the module docstring)."""
    stiffness = float(
        chevron_stiffness_N_per_m(
            YOUNGS_SI_PA, BEAM_WIDTH_M, BEAM_THICKNESS_M, BEAM_LENGTH_M, ANGLE_RAD
        )
    )
    model = ElectrothermalChevron(
        joule=JouleHeating(resistance_ohm=NOMINAL_R0_OHM, tcr_per_K=NOMINAL_TCR_PER_K),
        thermal=_thermal_block(thermal_nodes, elongation_lag),
        elongation=ThermalElongation(
            cte_per_K=CTE_SI_PER_K, length_m=BEAM_LENGTH_M, beam_fraction=1.0
        ),
        kinematics=ChevronExact(BEAM_LENGTH_M, ANGLE_RAD)
        if kinematics == "exact"
        else ChevronLinear(ANGLE_RAD),
        shuttle=QuasiStaticShuttle(stiffness_N_per_m=stiffness),
        camera=Camera(m_per_px=1e-6, exposure_s=0.0),
    )
    return model


_ONE_NODE_ROWS = (
    ParameterInfo(
        "thermal.tau_s",
        "s",
        NOMINAL_TAU_S,
        5e-4,
        0.1,
        "thermal time constant C/G",
        "identifiable from the frequency roll-off (0-400 Hz)",
    ),
    ParameterInfo(
        "thermal.resistance_K_per_W",
        "K/W",
        NOMINAL_RESISTANCE_K_PER_W,
        30.0,
        3000.0,
        "mean beam rise per watt",
        "product with 1/R0, alpha, kappa only",
    ),
)
_OTHER_ROWS = (
    ParameterInfo(
        "joule.resistance_ohm",
        "ohm",
        NOMINAL_R0_OHM,
        100.0,
        1e5,
        "electrical resistance at ambient",
        "fixed (measured)",
    ),
    ParameterInfo(
        "joule.tcr_per_K",
        "1/K",
        NOMINAL_TCR_PER_K,
        -2e-3,
        5e-3,
        "temperature coefficient of resistance",
        "identifiable from curvature in V^2",
    ),
    ParameterInfo(
        "elongation.cte_per_K", "1/K", CTE_SI_PER_K, 2.5e-6, 3.3e-6, "CTE of Si", "fixed"
    ),
    ParameterInfo(
        "kinematics.angle_rad",
        "rad",
        ANGLE_RAD,
        float(np.deg2rad(0.5)),
        float(np.deg2rad(5.0)),
        "chevron pre-bend angle",
        "fixed from layout",
    ),
    ParameterInfo("youngs_Pa", "Pa", YOUNGS_SI_PA, 130e9, 169e9, "Young's modulus of Si", "fixed"),
)


def parameters(**options) -> tuple[ParameterInfo, ...]:
    """The parameter table for the structural options."""
    thermal = build(**options).thermal
    rows = (
        _ONE_NODE_ROWS if isinstance(thermal, FirstOrderThermal) else chain_parameter_table(thermal)
    )
    return (*rows, *_OTHER_ROWS)


PARAMETERS = parameters()


def default_free_parameters(**options) -> list[FreeParameter]:
    """The amplitude-frequency table fit: tau, R_th and the TCR (R0 measured, geometry known).

    A chain frees its first and last series resistances (the time constants and the gain;
    a one-node chain its capacity and resistance) and the lag instead of tau and R_th."""
    tcr = FreeParameter("joule.tcr_per_K", unit="1/K", scale=1e-3)
    thermal = build(**options).thermal
    if isinstance(thermal, FirstOrderThermal):
        return [
            FreeParameter("thermal.tau_s", unit="s", lower=1e-4, upper=1.0),
            FreeParameter("thermal.resistance_K_per_W", unit="K/W", lower=1.0, upper=1e4),
            tcr,
        ]
    n = thermal.n_nodes
    free = []
    if n == 1:
        c = float(thermal.capacity_J_per_K[0])
        free.append(
            FreeParameter("thermal.capacity_J_per_K[0]", unit="J/K", lower=c / 30, upper=c * 30)
        )
    free += chain_free_parameters(thermal)
    return [*free, tcr]


def force_predictor(sensor_stiffness_N_per_m: float):
    """A pure function (model, voltage_V (N,)) -> force on the sensor (N,) [N] for `fit_table`."""
    import jax

    def predict(model, voltage_V):
        return jax.vmap(lambda v: model.sensor_force_N(v, sensor_stiffness_N_per_m))(voltage_V)

    return predict


def force_free_parameters() -> list[FreeParameter]:
    """DC force against voltage identifies the heating gain (R_th, with R0 measured) and the TCR."""
    return [
        FreeParameter("thermal.resistance_K_per_W", unit="K/W", lower=1.0, upper=1e4),
        FreeParameter("joule.tcr_per_K", unit="1/K", scale=1e-3),
    ]


SPEC = DeviceSpec(
    name="electrothermal_chevron",
    inputs=INPUTS,
    outputs=OUTPUTS,
    build=build,
    parameters=parameters,
    default_free=default_free_parameters,
    options=(
        Option(
            "kinematics",
            "exact",
            "chevron kinematics: exact rigid-link geometry or its small-stroke linearisation",
            choices=("exact", "linear"),
        ),
        Option(
            "thermal_nodes",
            1,
            "thermal nodes: 1 = one-node RC (tau, R); n >= 2 = n Joule-heated beam segments",
            minimum=1,
            maximum=8,
        ),
        Option(
            "elongation_lag",
            False,
            "a first-order lag (thermal.lag_s) between the mean beam rise and the elongation",
        ),
    ),
    description=__doc__.split("\n\n")[0],
    state_unit="K",  # temperature rises of the thermal nodes
)
