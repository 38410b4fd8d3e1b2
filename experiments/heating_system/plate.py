"""A lamp-heated steel plate read by a thermocouple (DaISy heating system): a user's device.

A user-written greybox device (not in ``models/``): ``experiment.toml`` names it as
``device = "plate.py:SPEC"``. Temperatures are kelvin inside (the CSV's degC are converted by
the output channel); the lamp drive u is in volts.

    tau_plate dTp/dt = heat - (Tp - Ta) - rad (Tp^4 - Ta^4) / (4 Ta^3)
    heat = P(u) = rise_6V (u / 6 V)^n                (option lamp_lag = false)
    heat = (1 - share) P(u) + share H,  tau_lamp dH/dt = P(u) - H      (lamp_lag = true)
    tau_sensor dTs/dt = Tp - Ts                      (option sensor_lag = true; else Ts = Tp)

- The lamp's heat, in kelvin of steady rise: `rise_6V_K` at the 6 V rest level of the record
  (DaISy: "the steady state input prior to the experiment is 6.0 V"), scaled by (u / 6 V)^n;
  n = 2 (`lamp_exponent`) is a lamp of constant resistance, a halogen filament's resistance
  grows with its temperature, so its power grows more slowly (n < 2).
- Losses: conduction and convection (Tp - Ta) plus radiation, `rad` the radiative conductance
  at ambient relative to the linear one (rad = 0: no radiation; the linearised T^4 term
  equals (Tp - Ta) rad near Ta).
- `tau_plate_s`: the plate's thermal time constant (heat capacity over linear conductance);
  `tau_sensor_s`: the thermocouple's lag behind the plate.
- `lamp_lag`: a share of the heat (`lamp_share`) follows the drive through a first-order lag
  (`tau_lamp_s`): the lamp's housing and reflector warming up, or the plate's mount. H starts
  at rest at the drive before the run (`initial_lamp_V`, a per-run setting: 6 V before the
  DaISy record).
- Plate and thermocouple start at the run's first reading (`run_settings`: `initial_T_K`);
  `ambient_K` is the room (25 C unless a run sets or the fit frees it). States: plate,
  thermocouple (with `sensor_lag`), lamp housing (with `lamp_lag`), in that order.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from greybox import AbstractODEDevice, Channel, DeviceSpec, FreeParameter, Option, ParameterInfo
from greybox.blocks import SensorReadout

REST_V = 6.0  # the record's rest level: the lamp gain is quoted there

INPUTS = (Channel("u", "V", {"V": (1.0, 0.0)}, "lamp drive voltage", minimum=0.0, maximum=20.0),)
OUTPUTS = (Channel("T", "K", {"C": (1.0, 273.15), "K": (1.0, 0.0)}, "thermocouple temperature"),)


class LampPlate(AbstractODEDevice):
    """State (plate temperature, thermocouple temperature) [K] (the plate's alone without
    `sensor_lag`); input the lamp drive [V]; output the thermocouple [K]."""

    rise_6V_K: float
    tau_plate_s: float
    tau_sensor_s: float
    lamp_exponent: float
    rad: float
    ambient_K: float
    initial_T_K: float
    readout: SensorReadout  # the thermocouple: temperature + offset
    lamp_share: float = 0.3
    tau_lamp_s: float = 30.0
    initial_lamp_V: float = REST_V
    sensor_lag: bool = eqx.field(static=True, default=True)
    lamp_lag: bool = eqx.field(static=True, default=False)

    @property
    def n_states(self) -> int:
        return 1 + int(self.sensor_lag) + int(self.lamp_lag)

    @property
    def n_inputs(self) -> int:
        return 1

    @property
    def n_outputs(self) -> int:
        return 1

    def lamp_heat(self, u_V):
        """The lamp's heat at drive `u_V`, in kelvin of steady rise: rise_6V (u / 6 V)^n."""
        drive = jnp.maximum(u_V, 0.0) / REST_V
        # u^n with n free: written through exp/log only where u > 0 (no 0 * log 0 gradient)
        return self.rise_6V_K * jnp.where(
            drive > 0, jnp.exp(self.lamp_exponent * jnp.log(jnp.where(drive > 0, drive, 1.0))), 0.0
        )

    def initial_state(self):
        x = [self.initial_T_K] * (1 + int(self.sensor_lag))
        if self.lamp_lag:  # the lamp at rest at its drive before the run
            x.append(self.lamp_heat(self.initial_lamp_V))
        return jnp.stack([jnp.asarray(v, dtype=float) for v in x])

    def vector_field(self, t, x, u):
        ta = self.ambient_K
        now = self.lamp_heat(u[0])
        plate = x[0]
        heat = now
        if self.lamp_lag:  # a share of the heat comes from the warming lamp housing
            heat = (1.0 - self.lamp_share) * now + self.lamp_share * x[-1]
        loss = (plate - ta) + self.rad * (plate**4 - ta**4) / (4.0 * ta**3)
        dx = [(heat - loss) / self.tau_plate_s]
        if self.sensor_lag:
            dx.append((plate - x[1]) / self.tau_sensor_s)
        if self.lamp_lag:
            dx.append((now - x[-1]) / self.tau_lamp_s)
        return jnp.stack(dx)

    def output(self, x):
        return x[1:2] if self.sensor_lag else x[:1]


def build(*, sensor_lag: bool = True, lamp_lag: bool = False, ambient_C: float = 25.0):
    return LampPlate(
        rise_6V_K=80.0,
        tau_plate_s=100.0,
        tau_sensor_s=5.0,
        lamp_exponent=2.0,
        rad=0.0,
        ambient_K=ambient_C + 273.15,
        initial_T_K=ambient_C + 273.15,
        readout=SensorReadout(),
        sensor_lag=sensor_lag,
        lamp_lag=lamp_lag,
    )


def run_settings(model, experiment, options) -> dict:
    """Both states start at the run's first valid reading (the file's settings win)."""
    import numpy as np

    y = np.asarray(experiment.y, dtype=float).reshape(-1)
    ok = np.flatnonzero(np.isfinite(y))
    return {"initial_T_K": float(y[ok[0]])} if ok.size else {}


PARAMETERS = (
    ParameterInfo(
        "rise_6V_K",
        "K",
        80.0,
        1.0,
        2000.0,
        "steady rise at 6 V without radiation",
        "identifiable (steady levels)",
        physical=(1.0, 2000.0),
    ),
    ParameterInfo(
        "tau_plate_s",
        "s",
        100.0,
        1.0,
        1e4,
        "plate time constant",
        "identifiable (step shapes)",
        physical=(1.0, 1e4),
    ),
    ParameterInfo(
        "tau_sensor_s",
        "s",
        5.0,
        0.01,
        1e3,
        "thermocouple lag",
        "from the first seconds of a step",
        physical=(0.01, 1e3),
    ),
    ParameterInfo(
        "lamp_exponent",
        "1",
        2.0,
        0.5,
        4.0,
        "heat ~ u^n",
        "from the steady levels of two or more drives",
        physical=(1.0, 2.5),
    ),
    ParameterInfo(
        "rad",
        "1",
        0.0,
        0.0,
        50.0,
        "radiative / linear conductance at ambient",
        "confounded with the exponent on two drive levels",
        physical=(0.0, 50.0),
    ),
    ParameterInfo("ambient_K", "K", 298.15, 250.0, 330.0, "room temperature", "fixed (25 C)"),
    ParameterInfo(
        "initial_T_K", "K", 298.15, None, None, "temperature at the first reading", "known per run"
    ),
    ParameterInfo(
        "lamp_share",
        "1",
        0.3,
        0.0,
        1.0,
        "share of the heat that lags (the lamp housing)",
        "with lamp_lag",
        physical=(0.0, 1.0),
    ),
    ParameterInfo(
        "tau_lamp_s",
        "s",
        30.0,
        1.0,
        1e3,
        "the lamp housing's warm-up",
        "with lamp_lag",
        physical=(1.0, 1e3),
    ),
    ParameterInfo(
        "initial_lamp_V", "V", REST_V, None, None, "the drive before the run", "known per run"
    ),
    ParameterInfo("readout.offset", "K", 0.0, None, None, "thermocouple zero", "per run"),
)

SPEC = DeviceSpec(
    name="lamp_plate",
    inputs=INPUTS,
    outputs=OUTPUTS,
    build=build,
    parameters=PARAMETERS,
    default_free=[
        FreeParameter("rise_6V_K", unit="K", lower=0.0),
        FreeParameter("tau_plate_s", unit="s", lower=0.0),
        FreeParameter("tau_sensor_s", unit="s", lower=0.0),
    ],
    options=(
        Option("sensor_lag", True, "the thermocouple lags the plate (a second state)"),
        Option("lamp_lag", False, "a share of the lamp's heat lags its drive (a state)"),
        Option("ambient_C", 25.0, "room temperature", minimum=-50.0, maximum=60.0, unit="C"),
    ),
    run_settings=run_settings,
    state_unit="K",
    description=__doc__.split("\n\n")[0],
)
