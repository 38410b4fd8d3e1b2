"""A heated plate (time constant 60 s) read through a sensor that lags it by 10 ms, written
as a user's `AbstractODEDevice`: a stiff device (tests/test_stiff_method.py). Its SPEC lets
an experiment folder name this file."""

import jax.numpy as jnp

import greybox
from greybox.blocks import SensorReadout

GAIN_K_PER_W, TAU_PLATE_S, TAU_SENSOR_S, T_AMB = 40.0, 60.0, 0.01, 295.0


class LaggedPlate(greybox.AbstractODEDevice):
    gain_K_per_W: float
    tau_plate_s: float
    tau_sensor_s: float
    readout: SensorReadout

    @property
    def n_states(self):
        return 2

    @property
    def n_inputs(self):
        return 1

    @property
    def n_outputs(self):
        return 1

    def initial_state(self):
        return jnp.full((2,), T_AMB)

    def vector_field(self, t, x, u):
        plate = (self.gain_K_per_W * u[0] - (x[0] - T_AMB)) / self.tau_plate_s
        return jnp.stack([plate, (x[0] - x[1]) / self.tau_sensor_s])

    def output(self, x):
        return x[1:]


def build(gain_K_per_W=GAIN_K_PER_W, tau_plate_s=TAU_PLATE_S):
    return LaggedPlate(
        gain_K_per_W=gain_K_per_W,
        tau_plate_s=tau_plate_s,
        tau_sensor_s=TAU_SENSOR_S,
        readout=SensorReadout(),
    )


FREE = [
    greybox.FreeParameter("gain_K_per_W", unit="K/W", lower=0.0),
    greybox.FreeParameter("tau_plate_s", unit="s", lower=0.0),
]

SPEC = greybox.DeviceSpec(
    name="lagged_plate",
    inputs=(greybox.Channel("P", "W", {"W": (1.0, 0.0)}, "heater power", minimum=0.0),),
    outputs=(greybox.Channel("T", "K", {"K": (1.0, 0.0), "C": (1.0, 273.15)}, "sensor"),),
    build=lambda: build(30.0, 100.0),  # starting values a user would guess
    parameters=(
        greybox.ParameterInfo("gain_K_per_W", "K/W", 30.0, 0.1, 1e3, "rise per W", "identifiable"),
        greybox.ParameterInfo("tau_plate_s", "s", 100.0, 1.0, 1e4, "plate", "identifiable"),
        greybox.ParameterInfo("tau_sensor_s", "s", TAU_SENSOR_S, None, None, "lag", "fixed"),
        greybox.ParameterInfo("readout.offset", "K", 0.0, None, None, "sensor zero", "per run"),
    ),
    default_free=FREE,
    state_unit="K",
)
