"""How a device names its input and output signals and which units files may use for them.

A CSV column is ``<name>_<unit>`` (``laser_mW``, ``y_um``, ``T1_C``). Each unit maps to SI by
``si = scale * value + offset``; the unit ``px`` is special: it is converted with the
experiment's camera scale (um per pixel).
"""

from __future__ import annotations

import dataclasses

PIXELS = "px"


MAX_MAGNITUDE_SI = 1e12  # no input level of a lab device reaches 1e12 SI units (1 TW, 1e12 K)


@dataclasses.dataclass(frozen=True)
class Channel:
    """- `name`: signal name used in column headers (``laser``, ``y``, ``T1``).
    - `si_unit`: unit inside the library (``W``, ``m``, ``K``, ``%``).
    - `units`: {file unit: (scale, offset)} with si = scale * value + offset; include
      ``"px": None`` for camera positions converted with um-per-pixel.
    - `description`: what the signal is, for help texts and reports.
    - `minimum`, `maximum`: physical range of the signal in SI (e.g. 0 for a laser power,
      0-100 for a heater level in %); files with values outside it are refused.
    """

    name: str
    si_unit: str
    units: dict
    description: str = ""
    minimum: float | None = None
    maximum: float | None = None

    def check_range(self, values_si) -> str | None:
        """None if every finite value lies in the channel's range, else what is wrong."""
        import numpy as np

        v = np.asarray(values_si, dtype=float)
        v = v[np.isfinite(v)]
        if v.size and np.max(np.abs(v)) > MAX_MAGNITUDE_SI:  # overflows the model's arithmetic
            return (
                f"{v[np.argmax(np.abs(v))]:g} {self.si_unit} is beyond any physical input "
                f"(|value| > {MAX_MAGNITUDE_SI:g} {self.si_unit}); check the unit"
            )
        if self.minimum is not None and v.size and v.min() < self.minimum:
            return f"{v.min():g} {self.si_unit} is below {self.minimum:g} {self.si_unit}"
        if self.maximum is not None and v.size and v.max() > self.maximum:
            return f"{v.max():g} {self.si_unit} is above {self.maximum:g} {self.si_unit}"
        return None

    def column_names(self) -> list[str]:
        return [f"{self.name}_{u}" for u in self.units]

    def to_si(self, values, unit: str, m_per_px: float | None = None):
        if unit not in self.units:
            raise ValueError(
                f"{self.name}_{unit}: unknown unit {unit!r}; use one of "
                f"{', '.join(self.column_names())}"
            )
        if self.units[unit] is None:
            if m_per_px is None:
                raise ValueError(
                    f"{self.name}_{unit}: pixel values need the camera scale "
                    "(um_per_px) in the experiment description"
                )
            return values * m_per_px
        scale, offset = self.units[unit]
        return values * scale + offset

    def from_si(self, values, unit: str, m_per_px: float | None = None):
        if self.units.get(unit, 0) is None:
            return values / m_per_px
        scale, offset = self.units[unit]
        return (values - offset) / scale


LASER_POWER = Channel(
    "laser", "W", {"mW": (1e-3, 0.0), "W": (1.0, 0.0)}, "laser power at the sample", minimum=0.0
)
DISPLACEMENT = Channel(
    "y",
    "m",
    {"um": (1e-6, 0.0), "nm": (1e-9, 0.0), PIXELS: None},
    "shuttle displacement along its axis",
)
