"""Load the DaISy hair-dryer record shipped next to this file."""

from pathlib import Path

import numpy as np

from greybox.blackbox import UniformData

DT_S = 0.08  # sampling interval [s] (MathWorks, dryer2)


def load_dryer() -> UniformData:
    """The full 1000-sample record: u = heater voltage [V], y = thermocouple voltage [V]."""
    raw = np.loadtxt(Path(__file__).with_name("dryer.dat"))
    return UniformData(raw[:, 0], raw[:, 1], DT_S, name="DaISy hair dryer")
