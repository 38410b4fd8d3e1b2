"""The TCLab temperature-control board (Park et al. 2020), composed from greybox's thermal blocks.

Two transistor heaters (nodes 0 and 1) with a TMP36 sensor on each: a 2-node
`ThermalNetwork` with convection U A and radiation eps sigma A to ambient per node, conduction
Us As and radiation eps sigma As between the heaters, and a first-order lag per sensor:

    m cp dTH1/dt = U A (Ta - TH1) + eps sigma A (Ta^4 - TH1^4) + Us As (TH2 - TH1)
                   + eps sigma As (TH2^4 - TH1^4) + alpha1 Q1          (and symmetric for TH2)
    tau_i dTC_i/dt = TH_i - TC_i                                        (measured TC_i)

Fixed constants are the paper's (Ta = 23 C, m = 4 g, cp = 500 J/(kg K), A = 10 cm^2,
As = 2 cm^2, eps = 0.9). Inputs are heater levels in % of full scale; outputs are the two
sensor temperatures in K, as the sensors read them: each TMP36 reads its node's temperature
plus its own offset (`readout.offset[0]`, `readout.offset[1]`; 0 unless fixed or fitted,
shared by the runs of one board or per run).

Initial state: `initial_T1_K`, `initial_T2_K` are each sensor's *reading* at the start of a
run, per-run known settings: unless a run gives them, each is the sensor's first valid
reading (as in the paper; `run_settings`), the other sensor's when a sensor has no reading in
the run. The model starts heater and sensor i at that reading minus sensor i's offset, so a
fitted offset moves the initial temperatures with it. The ambient temperature is the paper's
23 C unless a run sets `ambient_K` (a per-run setting), frees it per run (`{ path =
"ambient_K", per_run = true }` in [fit] free), or the option `ambient = "first_reading"`
takes it, inside the model, as the mean of the two sensors' first readings minus their
offsets (the board at rest at room temperature when the run starts).

Two structures (static flag `shared_sensor_lag`):
- default (False): one lag per sensor, tau1 and tau2 free (6 parameters: U, Us, alpha1,
  alpha2, tau1, tau2). The two TMP36 sensors are separate parts glued on separately, so their
  lags need not agree; on the paper's two-heater estimation run this structure is strongly
  preferred by AIC and BIC (`greybox compare`, simulation residuals, estimation data only,
  ambient 23 C: AIC 173.4 vs 388.0; experiments/tclab/results.md).
- True: the paper's structure, one lag shared by both sensors (tau2 is tied to tau1 and is
  not a free parameter; 5 parameters).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from greybox import (
    AbstractLinearDevice,
    AbstractODEDevice,
    Channel,
    DeviceSpec,
    FreeParameter,
    Option,
    ParameterInfo,
)
from greybox.blocks import STEFAN_BOLTZMANN, SensorReadout, ThermalNetwork

NAME = "tclab"
_PCT = {"pct": (1.0, 0.0)}
_TEMP = {"C": (1.0, 273.15), "K": (1.0, 0.0)}
INPUTS = (
    Channel("H1", "%", _PCT, "heater 1 level, % of full scale", minimum=0.0, maximum=100.0),
    Channel("H2", "%", _PCT, "heater 2 level, % of full scale", minimum=0.0, maximum=100.0),
)
OUTPUTS = (
    Channel("T1", "K", _TEMP, "sensor 1 temperature (TMP36 on heater 1)"),
    Channel("T2", "K", _TEMP, "sensor 2 temperature (TMP36 on heater 2)"),
)

# Park et al. (2020) fixed constants [SI]
AMBIENT_K = 273.15 + 23.0
MASS_KG = 0.004
CP_J_PER_KGK = 500.0
AREA_M2 = 10e-4
AREA_BETWEEN_M2 = 2e-4
EMISSIVITY = 0.9

# The paper's estimates (tclab_estimate.txt), used as starting values. The paper has one
# sensor lag tau = 20.68 s shared by both sensors; both per-sensor lags start there.
PAPER_TAU_S = 20.679715136
PUBLISHED = {
    "U_W_per_m2K": 5.5992939361,
    "Us_W_per_m2K": 20.378532582,
    "alpha1_W_per_pct": 0.01295874691,
    "alpha2_W_per_pct": 0.0060915026081,
    "tau1_s": PAPER_TAU_S,
    "tau2_s": PAPER_TAU_S,
}


class AbstractTCLab(AbstractODEDevice):
    """Two heaters, two lagged sensors; input u = (Q1, Q2) [%], output (TC1, TC2) [K].

    - `U_W_per_m2K`: convection coefficient to ambient; `Us_W_per_m2K`: heater-to-heater
      conductance per area.
    - `alpha1_W_per_pct`, `alpha2_W_per_pct`: heater power per % of full scale [W/%].
    - `tau1_s`, `tau2_s`: sensor 1 and sensor 2 lag time constants [s].
    - `shared_sensor_lag` (static): True = the paper's structure, both sensors lag with
      `tau1_s` and `tau2_s` is ignored; False (default) = one lag per sensor.
    - `initial_T1_K`, `initial_T2_K`: sensor 1 and 2 readings at t_start [K]; heater and
      sensor i start at `initial_Ti_K - readout.offset[i]`.
    - `readout`: the two sensors' offsets (`offset = (o1, o2)` [K]: reading = temperature + o).
    - `ambient_from_readings` (static): True = ambient is the mean of the true initial
      temperatures (the board at rest when the run starts) and `ambient_K` is not used.
    - fixed: `ambient_K`, `mass_kg`, `cp_J_per_kgK`, `area_m2`, `area_between_m2`, `emissivity`.
    - `radiation`: include the T^4 terms (static); `TCLab` has them, `LinearTCLab` (a linear
      network, simulated exactly by ZOH) does not.
    """

    U_W_per_m2K: float
    Us_W_per_m2K: float
    alpha1_W_per_pct: float
    alpha2_W_per_pct: float
    tau1_s: float
    tau2_s: float
    readout: SensorReadout
    initial_T1_K: float = AMBIENT_K
    initial_T2_K: float = AMBIENT_K
    ambient_K: float = AMBIENT_K
    mass_kg: float = MASS_KG
    cp_J_per_kgK: float = CP_J_PER_KGK
    area_m2: float = AREA_M2
    area_between_m2: float = AREA_BETWEEN_M2
    emissivity: float = EMISSIVITY
    radiation: bool = eqx.field(static=True, default=True)
    shared_sensor_lag: bool = eqx.field(static=True, default=False)
    ambient_from_readings: bool = eqx.field(static=True, default=False)

    def true_initial_K(self):
        """Heater and sensor temperatures at t_start (2,) [K]: first readings minus offsets."""
        first = jnp.stack(
            [
                jnp.asarray(self.initial_T1_K, dtype=float),
                jnp.asarray(self.initial_T2_K, dtype=float),
            ]
        )
        return first - self.readout.offsets(2)

    def ambient_temperature_K(self):
        """The ambient [K]: `ambient_K`, or the mean true initial temperature (the board at rest
        when the run starts) with `ambient_from_readings`."""
        if self.ambient_from_readings:
            return jnp.mean(self.true_initial_K())
        return jnp.asarray(self.ambient_K, dtype=float)

    def sensor_tau_s(self):
        """Sensor lag time constants (2,) [s]; tau2 is tau1 in the paper's shared structure."""
        tau2 = self.tau1_s if self.shared_sensor_lag else self.tau2_s
        return jnp.stack([jnp.asarray(self.tau1_s, dtype=float), jnp.asarray(tau2, dtype=float)])

    def network(self) -> ThermalNetwork:
        """2-node network with a lagged sensor on each heater node (states: rises over ambient)."""
        f = lambda v: jnp.asarray(v, dtype=float)  # noqa: E731
        rad_ground = rad_between = None
        if self.radiation:
            rad_ground = jnp.stack([f(self.emissivity * STEFAN_BOLTZMANN * self.area_m2)] * 2)
            rad_between = jnp.stack([f(self.emissivity * STEFAN_BOLTZMANN * self.area_between_m2)])
        return ThermalNetwork(
            capacitance_J_per_K=jnp.stack([f(self.mass_kg * self.cp_J_per_kgK)] * 2),
            ground_conductance_W_per_K=jnp.stack([f(self.U_W_per_m2K * self.area_m2)] * 2),
            coupling_conductance_W_per_K=jnp.stack([f(self.Us_W_per_m2K * self.area_between_m2)]),
            couplings=((0, 1),),
            input_nodes=(0, 1),
            radiation_ground_W_per_K4=rad_ground,
            radiation_coupling_W_per_K4=rad_between,
            ambient_K=self.ambient_temperature_K(),
            sensor_nodes=(0, 1),
            sensor_tau_s=self.sensor_tau_s(),
        )

    @property
    def n_states(self) -> int:
        return 4

    @property
    def n_inputs(self) -> int:
        return 2

    @property
    def n_outputs(self) -> int:
        return 2

    def initial_state(self):
        rise = self.true_initial_K() - self.ambient_temperature_K()
        return jnp.concatenate([rise, rise])  # heaters and sensors start at the same reading

    def heat_W(self, u_pct):
        """Heater powers [W] for levels `u_pct` (2,) [%]."""
        return jnp.stack([self.alpha1_W_per_pct, self.alpha2_W_per_pct]) * u_pct

    def vector_field(self, t, x, u):
        return self.network().derivative(x, self.heat_W(u))

    def output(self, x):
        """Sensor temperatures [K] (the readout adds each sensor's offset)."""
        return self.ambient_temperature_K() + x[2:]


class TCLab(AbstractTCLab):
    """The paper's board with radiation (nonlinear: simulated by the adaptive path)."""


class LinearTCLab(AbstractTCLab, AbstractLinearDevice):
    """The board without radiation terms: a linear network, simulated exactly by ZOH."""

    def __check_init__(self):
        if self.radiation:
            raise ValueError("LinearTCLab: radiation must be False (use TCLab with radiation)")

    def linear_dynamics(self):
        a, b = self.network().linear_matrices()
        return a, b * jnp.stack([self.alpha1_W_per_pct, self.alpha2_W_per_pct])[None, :]

    def vector_field(self, t, x, u):
        return AbstractLinearDevice.vector_field(self, t, x, u)


def build(
    *, radiation: bool = True, shared_sensor_lag: bool = False, ambient: str = "fixed"
) -> AbstractTCLab:
    """TCLab at the paper's published estimates (both sensor lags at the paper's 20.68 s,
    both sensor offsets 0); `shared_sensor_lag=True` is the paper's one-lag structure; without
    `radiation` the board is linear; `ambient = "first_reading"` computes each run's ambient
    from its first readings and the sensor offsets inside the model."""
    if ambient not in AMBIENT_RULES:
        raise ValueError(f"ambient: {ambient!r} is not one of {AMBIENT_RULES}")
    cls = TCLab if radiation else LinearTCLab
    return cls(
        **PUBLISHED,
        readout=SensorReadout(offset=(0.0, 0.0)),
        radiation=radiation,
        shared_sensor_lag=shared_sensor_lag,
        ambient_from_readings=ambient == "first_reading",
    )


AMBIENT_RULES = ("fixed", "first_reading")

PARAMETERS = (
    ParameterInfo(
        "U_W_per_m2K",
        "W/(m^2 K)",
        PUBLISHED["U_W_per_m2K"],
        1.0,
        100.0,
        "convection coefficient heater -> ambient",
        "identifiable (steady state)",
        physical=(1.0, 50.0),  # still air ~2-25, a fan up to ~50 [W/(m^2 K)]
    ),
    ParameterInfo(
        "Us_W_per_m2K",
        "W/(m^2 K)",
        PUBLISHED["Us_W_per_m2K"],
        0.01,
        1000.0,
        "heater-to-heater conductance per area",
        "identifiable from cross-heating",
        physical=(0.0, 300.0),  # boards differ in spacing and glue: from ~0 to solid contact
    ),
    ParameterInfo(
        "alpha1_W_per_pct",
        "W/%",
        PUBLISHED["alpha1_W_per_pct"],
        1e-4,
        0.1,
        "heater 1 power per % of full scale",
        "identifiable when Q1 moves",
        physical=(5e-4, 0.05),  # 0.05 W to 5 W at full scale (TCLab heaters: ~1-3 W)
    ),
    ParameterInfo(
        "alpha2_W_per_pct",
        "W/%",
        PUBLISHED["alpha2_W_per_pct"],
        1e-4,
        0.1,
        "heater 2 power per % of full scale",
        "identifiable when Q2 moves",
        physical=(5e-4, 0.05),  # 0.05 W to 5 W at full scale (TCLab heaters: ~1-3 W)
    ),
    ParameterInfo(
        "tau1_s",
        "s",
        PAPER_TAU_S,
        0.05,
        500.0,
        "sensor 1 lag time constant (both sensors' lag when shared_sensor_lag)",
        "identifiable (shape of the T1 response)",
        physical=(0.1, 300.0),  # a TMP36 from bare contact (~1 s) to potted (minutes)
    ),
    ParameterInfo(
        "tau2_s",
        "s",
        PAPER_TAU_S,
        0.05,
        500.0,
        "sensor 2 lag time constant (ignored when shared_sensor_lag)",
        "identifiable (shape of the T2 response)",
        physical=(0.1, 300.0),
    ),
    ParameterInfo(
        "initial_T1_K",
        "K",
        AMBIENT_K,
        None,
        None,
        "sensor 1's reading at the start of the run (heater and sensor 1 start at it "
        "minus sensor 1's offset)",
        "known per run (default: sensor 1's first valid reading)",
    ),
    ParameterInfo(
        "initial_T2_K",
        "K",
        AMBIENT_K,
        None,
        None,
        "sensor 2's reading at the start of the run (heater and sensor 2 start at it "
        "minus sensor 2's offset)",
        "known per run (default: sensor 2's first valid reading)",
    ),
    ParameterInfo(
        "ambient_K",
        "K",
        AMBIENT_K,
        250.0,
        330.0,
        "ambient (room) temperature; 23 C is the paper's room: set each run's own with "
        "[[runs]] settings = { ambient_K = ... }, take it from each run's first readings "
        '([model] ambient = "first_reading") or free it per run '
        '({ path = "ambient_K", per_run = true } in [fit] free)',
        "per run: known setting, or fitted per run from a rest segment",
    ),
    ParameterInfo(
        "readout.offset[0]",
        "K",
        0.0,
        -5.0,
        5.0,
        "sensor 1 (TMP36) offset: reading = temperature + offset; free it shared (a property "
        "of the board) or per run",
        'identifiable against a known ambient; with ambient = "first_reading" only the '
        "difference of the two offsets is (a common shift moves ambient, initial "
        "temperatures and readings together; fix one offset at 0)",
    ),
    ParameterInfo(
        "readout.offset[1]",
        "K",
        0.0,
        -5.0,
        5.0,
        "sensor 2 (TMP36) offset: reading = temperature + offset; free it shared (a property "
        "of the board) or per run",
        "as readout.offset[0]: the difference of the offsets is identifiable, their common "
        "part only against a known ambient",
    ),
    ParameterInfo(
        "area_m2",
        "m^2",
        AREA_M2,
        2e-4,
        3e-3,
        "convecting and radiating area per heater (the paper's 10 cm^2)",
        "weak: trades off with U (convection sees only U A; radiation alone separates them)",
    ),
)


def parameter_table(ambient: str = "fixed", **_options) -> tuple[ParameterInfo, ...]:
    """The parameter table; with ``ambient = "first_reading"`` the model computes the ambient
    from the first readings, so `ambient_K` is not a parameter (neither set nor fitted)."""
    if ambient == "first_reading":
        return tuple(p for p in PARAMETERS if p.path != "ambient_K")
    return PARAMETERS


def default_free_parameters(shared_sensor_lag: bool = False, **_options) -> list[FreeParameter]:
    """U, Us, alpha1, alpha2, tau1 and (unless `shared_sensor_lag`, the paper's five) tau2,
    each within bounds wide enough for TCLab boards in general (not the shipped board's
    values: other boards' heater gains, sensor lags and conductances lie outside the first
    ranges tried); a value outside the narrower physical range is flagged, not refused.
    Use with a model of the same structure."""
    n = 5 if shared_sensor_lag else 6
    return [
        FreeParameter(p.path, unit=p.unit, lower=p.lower, upper=p.upper) for p in PARAMETERS[:n]
    ]


def run_settings(model, experiment, options) -> dict:
    """Per-run defaults read off the run's own data (the file's settings win).

    - `initial_T1_K`, `initial_T2_K`: each sensor's first valid reading (heater and sensor
      start there); a sensor with no reading in the run starts at the other's first reading.

    With ``ambient = "first_reading"`` the model itself takes each run's ambient as the mean
    of these readings minus the sensor offsets (the board at rest at room temperature when
    the run starts: TCLab practice is to wait until it has cooled), so a fitted offset moves
    it; a run that also sets `ambient_K` is refused (two ambients for one run).
    """
    import numpy as np

    y = np.asarray(experiment.y, dtype=float).reshape(experiment.n_frames, -1)
    first = []
    for j in range(y.shape[1]):
        ok = np.flatnonzero(np.isfinite(y[:, j]))
        first.append(float(y[ok[0], j]) if ok.size else None)
    known = [v for v in first if v is not None]
    if not known:
        return {}
    first = [known[0] if v is None else v for v in first]
    if options.get("ambient") == "first_reading" and "ambient_K" in experiment.settings:
        raise ValueError(
            'ambient_K: the run sets the ambient, but [model] ambient = "first_reading" takes '
            "it from the first readings; drop one of them"
        )
    return {"initial_T1_K": first[0], "initial_T2_K": first[1]}


SPEC = DeviceSpec(
    name="tclab",
    inputs=INPUTS,
    outputs=OUTPUTS,
    build=build,
    parameters=parameter_table,
    default_free=default_free_parameters,
    options=(
        Option(
            "shared_sensor_lag",
            False,
            "one lag shared by both sensors (the paper's 5-parameter structure) instead of "
            "one each",
        ),
        Option("radiation", True, "include radiation (T^4) to ambient and between heaters"),
        Option(
            "ambient",
            "fixed",
            "ambient per run: 'fixed' (ambient_K: 23 C, or [experiment]/run settings) or "
            "'first_reading' (each run's mean first sensor reading minus the sensor offsets, "
            "computed in the model: the board starts at rest)",
            choices=AMBIENT_RULES,
        ),
    ),
    run_settings=run_settings,
    description=__doc__.split("\n\n")[0],
    state_unit="K",  # temperatures of the heater and sensor nodes
)
