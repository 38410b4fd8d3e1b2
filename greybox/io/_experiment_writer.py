"""Writing experiment folders: the inverse of `greybox.io._experiment_set`.

Small pieces a script needs to export runs in greybox's format (experiments/README.md):
run CSV text with units in the headers, and the `[[runs]]` TOML tables with their waveform
and per-run settings. Used by the data generators; equally for converting lab data.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np


def format_number(value: float, decimals: int | None = None) -> str:
    """A CSV cell: `decimals` fixed decimals (None: shortest form), "nan" for a missing value."""
    if not np.isfinite(value):
        return "nan"
    return f"{value:g}" if decimals is None else f"{value:.{decimals}f}"


def run_csv(t_s, columns: Mapping[str, tuple], *, time_decimals: int = 6) -> str:
    """CSV text of one run: `t_s` [s] then `columns` {header: (values, decimals or None)}.

    Headers carry their unit (`y_px`, `laser_mW`, ...); NaN values become "nan" (dropped frames).
    """
    t = np.asarray(t_s, dtype=float)
    cols = [(name, np.asarray(values, dtype=float), dec) for name, (values, dec) in columns.items()]
    for name, values, _ in cols:
        if values.shape != t.shape:
            raise ValueError(f"{name}: {values.size} values for {t.size} frame times")
    lines = [",".join(["t_s", *(name for name, _, _ in cols)])]
    for k in range(t.size):
        cells = [f"{t[k]:.{time_decimals}f}", *(format_number(v[k], d) for _, v, d in cols)]
        lines.append(",".join(cells))
    return "\n".join(lines) + "\n"


def inline_table(entries: Mapping) -> str:
    """A TOML inline table; dotted keys (setting paths) are quoted, numbers in shortest form."""

    def key(k):
        return f'"{k}"' if "." in k else k

    def value(v):
        return f'"{v}"' if isinstance(v, str) else f"{v:g}"

    return "{ " + ", ".join(f"{key(k)} = {value(v)}" for k, v in entries.items()) + " }"


def pulse_train_description(
    power_mW: float,
    period_ms: float,
    *,
    n_pulses: int,
    duty: float = 0.5,
    delay_ms: float = 0.0,
    tail_ms: float = 0.0,
) -> dict:
    """The `waveform` table of a pulse-train run (power in mW, times in ms)."""
    return {
        "type": "pulse_train",
        "power_mW": power_mW,
        "period_ms": period_ms,
        "duty": duty,
        "n_pulses": int(n_pulses),
        "delay_ms": delay_ms,
        "tail_ms": tail_ms,
    }


def run_table(
    name: str,
    role: str,
    waveform: Mapping,
    settings: Mapping | None = None,
    file: str | None = None,
) -> str:
    """One `[[runs]]` TOML table (the CSV defaults to `<name>.csv`)."""
    text = (
        f'[[runs]]\nname = "{name}"\nfile = "{file or name + ".csv"}"\nrole = "{role}"\n'
        f"waveform = {inline_table(waveform)}\n"
    )
    if settings:
        text += f"settings = {inline_table(settings)}\n"
    return text
