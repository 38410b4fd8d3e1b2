"""Piezoresistive force-sensor readings -> force, and averaging of repeated readings (thesis §5.4).

Thesis eq. 5.2 (OCR-garbled) relates the bridge output dU of a piezoresistive cantilever to its
tip deflection d. The surface strain at a resistor a fraction x_r along a cantilever of length l
and thickness h is eps = 3 h d (1 - x_r) / (2 l^2), and a bridge with gauge factor gamma fed by U
gives dU = (1/2) U gamma eps [derived], so

    dU = 0.75 U gamma (1 - x_r) h d / l^2   =>   d = dU l^2 / (0.75 U gamma (1 - x_r) h)   (5.2)

which matches the printed "0.75 . U . gamma . (1 - 0.5) . h" denominator (x_r = 0.5); the OCR shows
l^3 in the numerator, which is dimensionally inconsistent, so l^2 is used. Eq. 5.3: F = C d with
C the sensor stiffness [N/m]. All constants are parameters (the thesis does not list values).
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class ForceSensor:
    """- `length_m`: cantilever length l [m]; `thickness_m`: its thickness h [m] (the thesis
      calls it "width": the dimension in the bending direction).
    - `gauge_factor`: piezoresistive gauge factor gamma [1]; `bridge_V`: bridge supply U [V].
    - `resistor_position`: resistor location x_r / l along the beam [1] (thesis: 0.5).
    - `stiffness_N_per_m`: sensor stiffness C [N/m].
    """

    length_m: float
    thickness_m: float
    gauge_factor: float
    bridge_V: float
    stiffness_N_per_m: float
    resistor_position: float = 0.5

    def __post_init__(self):
        for name in ("length_m", "thickness_m", "gauge_factor", "bridge_V", "stiffness_N_per_m"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name}: {v!r} must be a finite value > 0")
        if not 0 <= self.resistor_position < 1:
            raise ValueError(f"resistor_position: {self.resistor_position} must be in [0, 1)")

    @property
    def volts_per_m(self) -> float:
        """Bridge output per tip deflection, dU / d [V/m] (eq. 5.2 inverted)."""
        return (
            0.75
            * self.bridge_V
            * self.gauge_factor
            * (1 - self.resistor_position)
            * self.thickness_m
            / self.length_m**2
        )

    def deflection_m(self, sensor_V):
        """Tip deflection [m] for a bridge output change [V] (eq. 5.2)."""
        return np.asarray(sensor_V, dtype=float) / self.volts_per_m

    def force_N(self, sensor_V):
        """Force [N] on the sensor for a bridge output change [V] (eqs. 5.2-5.3)."""
        return self.stiffness_N_per_m * self.deflection_m(sensor_V)

    def sensor_V(self, force_N):
        """Bridge output change [V] for a force [N] (inverse of `force_N`)."""
        return np.asarray(force_N, dtype=float) / self.stiffness_N_per_m * self.volts_per_m


def check_voltages(voltage_V, name: str = "voltage_V") -> np.ndarray:
    v = np.asarray(voltage_V, dtype=float).reshape(-1)
    if v.size == 0:
        raise ValueError(f"{name}: no readings; give at least one applied voltage")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{name}: contains NaN or inf; every reading needs its applied voltage")
    if np.any(v < 0):
        raise ValueError(
            f"{name}: negative voltage range (min {v.min():g} V); the actuator "
            "heats with V^2, so record magnitudes >= 0 V"
        )
    return v


@dataclasses.dataclass(frozen=True)
class RepeatAverage:
    """Per distinct applied voltage: mean reading, sample sd, standard error sd / sqrt(n), count."""

    voltage_V: np.ndarray
    mean: np.ndarray
    sd: np.ndarray
    se: np.ndarray
    n: np.ndarray

    @property
    def pooled_se(self) -> np.ndarray:
        """Standard error per voltage from the sd pooled over all voltages (equal scatter
        assumed): steadier than each voltage's own sd when there are only a few repeats."""
        dof = self.n - 1
        pooled_sd = np.sqrt(np.sum(dof * self.sd**2) / np.sum(dof))
        return pooled_sd / np.sqrt(self.n)


def average_repeats(voltage_V, values, *, expected_repeats: int | None = None) -> RepeatAverage:
    """Average repeated readings (`values`, any unit) per applied voltage; NaN = missing reading.

    A voltage whose readings are all missing (zero repeats), `expected_repeats` < 1, or a
    voltage with a different count than `expected_repeats` is a ValueError; the standard error
    needs >= 2 readings per voltage.
    """
    v = check_voltages(voltage_V)
    y = np.asarray(values, dtype=float).reshape(-1)
    if y.shape != v.shape:
        raise ValueError(f"values: {y.size} readings for {v.size} voltages; give one per row")
    if expected_repeats is not None and (
        int(expected_repeats) != expected_repeats or expected_repeats < 1
    ):
        raise ValueError(
            f"expected_repeats: {expected_repeats} repeats per voltage; give a whole "
            "number >= 1 (zero repeats means no data)"
        )
    levels = np.unique(v)
    out = {k: [] for k in ("mean", "sd", "se", "n")}
    for level in levels:
        r = y[(v == level) & np.isfinite(y)]
        if r.size == 0:
            raise ValueError(
                f"values: zero repeats at {level:g} V (every reading missing); "
                "remove that voltage or re-measure it"
            )
        if expected_repeats is not None and r.size != expected_repeats:
            raise ValueError(
                f"values: {r.size} valid repeats at {level:g} V, expected {expected_repeats}"
            )
        if r.size < 2:
            raise ValueError(
                f"values: one reading at {level:g} V; the repeat scatter (standard "
                "error) needs >= 2 repeats per voltage"
            )
        sd = float(np.std(r, ddof=1))
        out["mean"].append(float(r.mean()))
        out["sd"].append(sd)
        out["se"].append(sd / np.sqrt(r.size))
        out["n"].append(r.size)
    return RepeatAverage(levels, *(np.asarray(out[k]) for k in ("mean", "sd", "se", "n")))
