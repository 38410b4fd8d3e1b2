"""The waveform-description language of experiment files and ``--waveform`` options.

A run's input is a table such as ``{ type = "pulse_train", power_mW = 20, period_ms = 500,
duty = 0.5, n_pulses = 10 }`` (levels are named after the channel and its unit), a list of
``steps``, or ``logged`` (the levels come from the run's CSV).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from greybox._channels import Channel
from greybox._errors import InputError
from greybox._waveforms import PiecewiseConstant, PulseTrain, from_samples
from greybox.io._csv import CsvTable, channel_column, check_increasing, read_csv, time_column

LOG_POWER_TOLERANCE = 0.05  # logged vs described: 5 % of the peak level
TIME_UNITS = {"s": 1.0, "ms": 1e-3}
WAVEFORM_TYPES = ("pulse_train", "steps", "logged")
_PULSE_KEYS = {"type", "duty", "n_pulses", "n"}
_STEPS_KEYS = {"type", "times_s", "end_s"}


# --------------------------------------------------------------------------------------
# Waveforms


def _time_key(
    desc: dict, base: str, path: tuple, where, *, required: bool, default: float | None = None
) -> tuple:
    """(seconds, key) of a time given as ``<base>_s`` or ``<base>_ms`` in `desc`."""
    keys = [f"{base}_{u}" for u in TIME_UNITS if f"{base}_{u}" in desc]
    if len(keys) > 1:
        raise where(f"give {base} once (as {keys[0]} or {keys[1]})", *path, keys[1])
    if not keys:
        if required:
            raise where(f"missing; give {base}_ms or {base}_s", *path, f"{base}_ms")
        return default, f"{base}_s"
    value = desc[keys[0]]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise where(f"{value!r} is not a finite number", *path, keys[0])
    return float(value) * TIME_UNITS[keys[0].rsplit("_", 1)[1]], keys[0]


def _level_key(desc: dict, channel: Channel, path: tuple, where):
    """(key, value as written, unit) of the ``power_<unit>`` entry of a description."""
    keys = [k for k in desc if k.startswith("power_")]
    if not keys:
        raise where(
            f"missing; give the level as one of "
            f"{', '.join('power_' + u for u in channel.units if channel.units[u])}",
            *path,
            "power",
        )
    if len(keys) > 1:
        raise where("give the level once", *path, keys[1])
    key = keys[0]
    unit = key[len("power_") :]
    if unit not in channel.units or channel.units[unit] is None:
        raise where(
            f"unknown unit {unit!r}; use one of "
            f"{', '.join('power_' + u for u in channel.units if channel.units[u])}",
            *path,
            key,
        )
    return key, desc[key], unit


def waveform_from_description(desc: dict, channel: Channel, where, path: tuple = ()):
    """A described input waveform -> (PiecewiseConstant in SI, one-line text).

    `desc`: ``{"type": "pulse_train", "power_mW": 20, "period_ms": 500, "duty": 0.5,
    "n_pulses": 10, "delay_ms": 300, "tail_ms": 700}`` or ``{"type": "steps",
    "times_s": [...], "power_mW": [...], "end_s": 12.0}``. `where(message, *path_keys)`
    builds the error to raise (it knows the file and lines).
    """
    kind = desc.get("type")
    if kind not in ("pulse_train", "steps"):
        raise where(
            f'{kind!r} is not a described waveform type; use "pulse_train", "steps" or "logged"',
            *path,
            "type",
        )
    key, level, unit = _level_key(desc, channel, path, where)
    if kind == "pulse_train":
        allowed = (
            _PULSE_KEYS
            | {key}
            | {f"{b}_{u}" for b in ("period", "delay", "tail") for u in TIME_UNITS}
        )
        for k in desc:
            if k not in allowed:
                raise where(
                    f"unknown key for a pulse train; allowed: {', '.join(sorted(allowed))}",
                    *path,
                    k,
                )
        period, period_key = _time_key(desc, "period", path, where, required=True)
        delay, delay_key = _time_key(desc, "delay", path, where, required=False, default=0.0)
        tail, tail_key = _time_key(desc, "tail", path, where, required=False, default=0.0)
        if "n" in desc and "n_pulses" in desc:
            raise where("give the pulse count once (n_pulses)", *path, "n")
        nkey = "n" if "n" in desc else "n_pulses"
        n = desc.get(nkey)
        if n is None:
            raise where("missing; give the number of pulses n_pulses", *path, "n_pulses")
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise where(f"{n!r} must be a whole number >= 1", *path, nkey)
        duty = desc.get("duty", 0.5)
        if isinstance(duty, bool) or not isinstance(duty, (int, float)) or not 0 < duty <= 1:
            raise where(f"{duty!r} must be the on-fraction, in (0, 1]", *path, "duty")
        if (
            isinstance(level, bool)
            or not isinstance(level, (int, float))
            or not math.isfinite(level)
            or level < 0
        ):
            raise where(f"{level!r} must be a number >= 0", *path, key)
        for k, value, ok, fix in (
            (period_key, period, period > 0, "must be > 0"),
            (delay_key, delay, delay >= 0, "cannot be negative"),
            (tail_key, tail, tail >= 0, "cannot be negative"),
        ):
            if not ok:
                raise where(f"{desc[k]!r} {fix}", *path, k)
        level_si = float(channel.to_si(float(level), unit))
        wave = PulseTrain(level_si, period, float(duty), n, delay_s=delay, tail_s=tail)
        text = (
            f"pulse train {float(level):g} {unit}, period {period * 1e3:g} ms, duty "
            f"{float(duty) * 100:g} %, {n} pulses, delay {delay * 1e3:g} ms, tail "
            f"{tail * 1e3:g} ms"
        )
        return wave.to_piecewise(), text
    allowed = _STEPS_KEYS | {key}
    for k in desc:
        if k not in allowed:
            raise where(f"unknown key for steps; allowed: {', '.join(sorted(allowed))}", *path, k)
    times, levels = desc.get("times_s"), level
    if not isinstance(times, list) or not isinstance(levels, list) or not times:
        raise where(
            f"steps need two equal-length lists: times_s = [...] and {key} = [...]",
            *path,
            "times_s",
        )
    if len(times) != len(levels):
        raise where(f"times_s has {len(times)} entries but {key} has {len(levels)}", *path, key)
    try:
        t = np.array([float(x) for x in times])
        v = np.array([float(x) for x in levels])
    except (TypeError, ValueError):
        raise where("lists must hold numbers only", *path, "times_s") from None
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(v))):
        raise where("lists must hold finite numbers", *path, "times_s")
    if np.any(np.diff(t) <= 0):
        raise where("times must be strictly increasing", *path, "times_s")
    if np.any(v < 0):
        raise where("levels cannot be negative", *path, key)
    end, _ = _time_key(desc, "end", path, where, required=True)
    if end < t[-1]:
        raise where(f"end_s {end:g} is before the last step time {t[-1]:g} s", *path, "end_s")
    wave = PiecewiseConstant(t, channel.to_si(v, unit), end)
    return wave, f"{t.size} steps ({unit}) until {end:g} s"


def parse_waveform_spec(spec: str, channel: Channel):
    """A command-line pulse spec ``pulse:power_mW=25,period_ms=300,duty=0.5,n=10`` ->
    (PiecewiseConstant in SI, text). Raises `InputError` naming ``--waveform``."""

    def where(message, *path):
        key = next((p for p in reversed(path) if isinstance(p, str)), None)
        return InputError(
            f"{key + ': ' if key else ''}{message} (spec {spec!r}; e.g. "
            "pulse:power_mW=25,period_ms=300,duty=0.5,n=10)",
            field="--waveform",
        )

    shape, sep, body = spec.partition(":")
    if not sep or shape != "pulse":
        raise where(
            "expected 'pulse:KEY=VALUE,...' or the path of a CSV with t_s,"
            f"{channel.name}_<unit> columns"
        )
    desc: dict = {"type": "pulse_train"}
    for item in filter(None, (s.strip() for s in body.split(","))):
        k, eq, v = item.partition("=")
        if not eq:
            raise where(f"{item!r} is not KEY=VALUE")
        try:
            num = float(v)
        except ValueError:
            raise where(f"{v!r} is not a number", k.strip()) from None
        desc[k.strip()] = int(num) if k.strip() in ("n", "n_pulses") and num == int(num) else num
    return waveform_from_description(desc, channel, where)


def waveform_from_csv(path, channel: Channel):
    """A logged trace CSV (``t_s`` and one ``<channel>_<unit>`` column) -> (waveform, text)."""
    table = read_csv(path, example=f"t_s,{channel.column_names()[0]}")
    t = time_column(table)
    check_increasing(table, t)
    col = channel_column(table, channel, required=True)
    unit = col[len(channel.name) + 1 :]
    v = table.numbers(col, nonneg=True, what=f"{channel.description or channel.name} in {unit}")
    end = t[-1] + (float(np.median(np.diff(t))) if t.size > 1 else 0.0)
    wave = from_samples(t, channel.to_si(v, unit), end_s=end, name=col)
    return wave, f"logged trace {Path(path).name} ({t.size} samples, {unit})"


def check_log_against_description(
    table: CsvTable,
    col: str,
    logged_si: np.ndarray,
    t: np.ndarray,
    described: PiecewiseConstant,
    channel: Channel,
    unit: str,
    slack_s: float,
    toml_ref: str,
) -> None:
    """Each logged sample must match the described level within 5 % of the peak, allowing
    `slack_s` of timing error at edges."""
    described_levels = np.asarray(described.values).reshape(-1)
    tol = LOG_POWER_TOLERANCE * max(float(np.max(np.abs(described_levels))), 1e-300)
    shifts = np.linspace(-slack_s, slack_s, 9)
    around = np.stack([np.asarray(described(t + s)).reshape(-1) for s in shifts])
    lo, hi = around.min(axis=0) - tol, around.max(axis=0) + tol
    bad = np.flatnonzero((logged_si < lo) | (logged_si > hi))
    if bad.size:
        i = int(bad[0])
        got = float(channel.from_si(logged_si[i], unit))
        want = float(channel.from_si(np.asarray(described(t[i])).reshape(-1)[0], unit))
        raise InputError(
            f"logged {got:g} {unit} at t_s = {t[i]:g} contradicts the waveform "
            f"described in {toml_ref} ({want:g} {unit} there, tolerance "
            f"{LOG_POWER_TOLERANCE:.0%} of the peak); fix the description or the "
            "log, or drop one of them",
            file=table.file,
            line=table.lines[i],
            field=col,
        )
