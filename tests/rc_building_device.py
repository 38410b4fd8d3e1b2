"""Stochastic RC building models as a user writes them (DEVELOPING.md): CTSM-R's Ti, TiTe and
TiTeTh structures (indoor air, envelope and heater nodes; inputs ambient temperature, heater
power and solar irradiance; temperatures in K, powers in W).

    nodes = 3:  Ci dTi = ((Te - Ti)/Rie + (Th - Ti)/Rih + Aw Ps) dt
                Ce dTe = ((Ti - Te)/Rie + (Ta - Te)/Rea) dt
                Ch dTh = ((Ti - Th)/Rih + Ph) dt
    nodes = 2:  no heater node: Ph heats the air directly
    nodes = 1:  the air alone: Ci dTi = ((Ta - Ti)/Rea + Ph + Aw Ps) dt

`SPEC` reads the air and the envelope (three nodes, the structure of tests/rc3_reference.py);
`SPEC_AIR` reads the air only and takes `nodes` as a structural option (the candidates of a
structure comparison). The tests copy this file into an experiment's device folder.
"""

import equinox as eqx
import jax.numpy as jnp

import greybox
from greybox.blocks import SensorReadout

_TEMP = {"K": (1.0, 0.0), "C": (1.0, 273.15)}
INPUTS = (
    greybox.Channel("Ta", "K", _TEMP, "ambient temperature"),
    greybox.Channel("Ph", "W", {"W": (1.0, 0.0), "kW": (1e3, 0.0)}, "heater power"),
    greybox.Channel("Ps", "W/m^2", {"Wpm2": (1.0, 0.0)}, "solar irradiance"),
)
AIR = greybox.Channel("Ti", "K", _TEMP, "indoor air temperature")
ENVELOPE = greybox.Channel("Te", "K", _TEMP, "envelope temperature")


class RCBuilding(greybox.AbstractLinearDevice):
    Ci: float
    Ce: float
    Ch: float
    Rie: float
    Rea: float
    Rih: float
    Aw: float
    Ti0: float
    Te0: float
    Th0: float
    readout: SensorReadout
    nodes: int = eqx.field(static=True, default=3)
    outputs_read: int = eqx.field(static=True, default=2)

    @property
    def n_states(self):
        return self.nodes

    @property
    def n_inputs(self):
        return 3

    @property
    def n_outputs(self):
        return self.outputs_read

    def initial_state(self):
        x0 = jnp.stack([jnp.asarray(v, float) for v in (self.Ti0, self.Te0, self.Th0)])
        return x0[: self.nodes]

    def linear_dynamics(self):
        ci, ce, ch = self.Ci, self.Ce, self.Ch
        rie, rea, rih, aw = self.Rie, self.Rea, self.Rih, self.Aw
        if self.nodes == 1:
            a = jnp.array([[-1 / (rea * ci)]])
            b = jnp.array([[1 / (rea * ci), 1 / ci, aw / ci]])
        elif self.nodes == 2:
            a = jnp.array(
                [
                    [-1 / (rie * ci), 1 / (rie * ci)],
                    [1 / (rie * ce), -1 / (rie * ce) - 1 / (rea * ce)],
                ]
            )
            b = jnp.array([[0.0, 1 / ci, aw / ci], [1 / (rea * ce), 0.0, 0.0]])
        else:
            a = jnp.array(
                [
                    [-1 / (rie * ci) - 1 / (rih * ci), 1 / (rie * ci), 1 / (rih * ci)],
                    [1 / (rie * ce), -1 / (rie * ce) - 1 / (rea * ce), 0.0],
                    [1 / (rih * ch), 0.0, -1 / (rih * ch)],
                ]
            )
            b = jnp.array([[0.0, 0.0, aw / ci], [1 / (rea * ce), 0.0, 0.0], [0.0, 1 / ch, 0.0]])
        return a, b

    def output(self, x):
        return x[: self.outputs_read]


# start values a factor 3-4 from the truth of tests/rc3_reference.py
NOMINAL = {
    "Ci": 5.0e6,
    "Ce": 3.0e6,
    "Ch": 1.2e6,
    "Rie": 1.2e-2,
    "Rea": 2.4e-3,
    "Rih": 6.0e-3,
    "Aw": 1.0,
}
_INFO = {
    "Ci": ("J/K", 1e4, 1e9, "heat capacity of the indoor air"),
    "Ce": ("J/K", 1e4, 1e9, "heat capacity of the envelope"),
    "Ch": ("J/K", 1e3, 1e9, "heat capacity of the heater"),
    "Rie": ("K/W", 1e-5, 1.0, "resistance air - envelope"),
    "Rea": ("K/W", 1e-5, 1.0, "resistance envelope - ambient (air - ambient with one node)"),
    "Rih": ("K/W", 1e-5, 1.0, "resistance air - heater"),
    "Aw": ("m^2", 1e-2, 100.0, "effective window area (solar gain)"),
}
USED = {1: ("Ci", "Rea", "Aw"), 2: ("Ci", "Ce", "Rie", "Rea", "Aw"), 3: tuple(NOMINAL)}
STATES = {1: ("Ti0",), 2: ("Ti0", "Te0"), 3: ("Ti0", "Te0", "Th0")}


def _builder(outputs_read: int):
    def build(*, nodes: int = 3):
        return RCBuilding(
            **NOMINAL, Ti0=293.0, Te0=288.0, Th0=295.0, readout=SensorReadout(),
            nodes=nodes, outputs_read=outputs_read,
        )

    return build


def parameter_table(*, nodes: int = 3):
    rows = [
        greybox.ParameterInfo(k, _INFO[k][0], NOMINAL[k], _INFO[k][1], _INFO[k][2], _INFO[k][3])
        for k in USED[nodes]
    ]
    rows += [
        greybox.ParameterInfo(k, "K", 293.0, None, None, "initial temperature of a node")
        for k in STATES[nodes]
    ]
    return tuple(rows)


def default_free(*, nodes: int = 3):
    return [
        greybox.FreeParameter(k, unit=_INFO[k][0], lower=_INFO[k][1], upper=_INFO[k][2])
        for k in USED[nodes]
    ]


SPEC = greybox.DeviceSpec(
    name="rc_building",
    inputs=INPUTS,
    outputs=(AIR, ENVELOPE),
    build=_builder(2),
    parameters=parameter_table,
    default_free=default_free,
    options=(greybox.Option("nodes", 3, "thermal nodes (3: air, envelope, heater)", choices=(3,)),),
)
SPEC_AIR = greybox.DeviceSpec(
    name="rc_building_air",
    inputs=INPUTS,
    outputs=(AIR,),
    build=_builder(1),
    parameters=parameter_table,
    default_free=default_free,
    options=(
        greybox.Option(
            "nodes", 3, "thermal nodes: 1 air, 2 + envelope, 3 + heater", choices=(1, 2, 3)
        ),
    ),
)
