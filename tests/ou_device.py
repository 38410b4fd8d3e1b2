"""The scalar OU process of tests/ou_reference.py as greybox objects: the one-node RC
building (tests/rc_building_device.py) wrapped with process noise on the air node."""

import numpy as np

import greybox
from greybox.blocks import SensorReadout
from tests import ou_reference as ou
from tests.rc_building_device import RCBuilding

STRUCTURE = greybox.NoiseStructure(process_groups=(("air", (0,)),))
FREE = (
    greybox.FreeParameter("Ci", "J/K", lower=0.0),
    greybox.FreeParameter("Rea", "K/W", lower=0.0),
    greybox.FreeParameter("process.air", "K^2/s", lower=0.0),
    greybox.FreeParameter("measurement.Ti", "K", lower=0.0),
)
NAMES = ("Ci", "Rea", "q", "sd")  # tests/ou_reference.py's names of FREE, in order


def inputs(t_end: float) -> greybox.PiecewiseConstant:
    """(Ta, Ph, Ps): constant ambient, the reference's heater square wave, no sun."""
    sw = np.arange(0.0, t_end, ou.PERIOD / 2)
    levels = np.column_stack([np.full(sw.size, ou.TA), ou.heater(sw), np.zeros(sw.size)])
    return greybox.PiecewiseConstant(sw, levels, float(t_end))


def experiment(y, name: str = "ou") -> greybox.Experiment:
    t = ou.frames(y.size)
    return greybox.Experiment(name, t, np.asarray(y)[:, None], inputs(float(t[-1]) + ou.DT))


def model(p: dict):
    """The stochastic device at parameters `p` (keys `NAMES`)."""
    dev = RCBuilding(
        Ci=p["Ci"], Ce=1.0, Ch=1.0, Rie=1.0, Rea=p["Rea"], Rih=1.0, Aw=0.0,
        Ti0=ou.T0, Te0=0.0, Th0=0.0, readout=SensorReadout(), nodes=1, outputs_read=1,
    )
    values = {"process.air": p["q"], "measurement.Ti": p["sd"]}
    return greybox.stochastic.stochastic_device(dev, STRUCTURE, outputs=("Ti",), values=values)
