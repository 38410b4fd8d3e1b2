"""The waveform-description language of experiment files and ``--waveform`` options.

A run's input is a table such as ``{ type = "pulse_train", power_mW = 20, period_ms = 500,
duty = 0.5, n_pulses = 10 }`` (levels are named after the channel and its unit), a list of
``steps``, or ``logged`` (the levels come from the run's CSV).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from greybox._model.channels import Channel
from greybox._model.errors import InputError
from greybox._model.waveforms import PiecewiseConstant, PulseTrain, from_samples, stack_channels
from greybox.io._csv import (
    ColumnRef,
    CsvTable,
    channel_numbers,
    check_increasing,
    excerpt,
    find_column,
    read_csv,
    time_column,
)
from greybox.io._units import from_si

LOG_POWER_TOLERANCE = 0.05  # logged vs described: 5 % of the peak level
TIME_UNITS = {"s": 1.0, "ms": 1e-3}
WAVEFORM_TYPES = ("pulse_train", "steps", "logged")
MAX_PULSES = 100_000  # a pulse train's switching times are all materialised
MAX_STEPS = 1_000_000
MIN_EDGE_S = 1e-6  # shortest pulse or gap: below it the switching times are not distinct
_PULSE_KEYS = {"type", "duty", "n_pulses", "n"}
_STEPS_KEYS = {"type", "times_s", "end_s"}


def _duration(t_s: float) -> str:
    """A duration in ms below 10 s (a laser's pulses), in s above (a lamp's: "400 s", not
    "400000 ms")."""
    return f"{t_s * 1e3:g} ms" if t_s < 10.0 else f"{t_s:g} s"


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
    if isinstance(value, int) and not isinstance(value, bool) and abs(value) > 1e300:
        value = math.inf  # a huge TOML integer: refused below, not an OverflowError
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise where(f"{excerpt(value)} is not a finite number", *path, keys[0])
    return float(value) * TIME_UNITS[keys[0].rsplit("_", 1)[1]], keys[0]


def _level_key(desc: dict, channel: Channel, path: tuple, where):
    """(key, value as written, unit) of the level entry of a description.

    The level is named after the input channel and its unit (``laser_mW``, ``V_V``,
    ``H1_pct``); ``power_<unit>`` is accepted too (the laser's historic name)."""
    units = [u for u in channel.units if channel.units[u]]
    prefixes = (f"{channel.name}_", "power_")
    keys = [k for k in desc if k.startswith(prefixes)]
    if not keys:
        raise where(
            f"missing; give the level as one of {', '.join(channel.name + '_' + u for u in units)}",
            *path,
            f"{channel.name}_{units[0]}",
        )
    if len(keys) > 1:
        raise where("give the level once", *path, keys[1])
    key = keys[0]
    unit = key.split("_", 1)[1] if key.startswith("power_") else key[len(channel.name) + 1 :]
    if unit not in units:
        key = key if len(key) <= 40 else excerpt(key)
        raise where(
            f"unknown unit {unit!r}; use one of {', '.join(channel.name + '_' + u for u in units)}",
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
            f"{excerpt(kind)} is not a described waveform type; use "
            '"pulse_train", "steps" or "logged"',
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
                    k if isinstance(k, str) and len(k) <= 40 else excerpt(k),
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
            raise where(f"{excerpt(n)} must be a whole number >= 1", *path, nkey)
        if n > MAX_PULSES:
            raise where(
                f"{n} pulses is more than {MAX_PULSES}; describe a shorter train (split the "
                "recording into runs)",
                *path,
                nkey,
            )
        duty = desc.get("duty", 0.5)
        if isinstance(duty, bool) or not isinstance(duty, (int, float)) or not 0 < duty <= 1:
            raise where(f"{excerpt(duty)} must be the on-fraction, in (0, 1]", *path, "duty")
        if (
            isinstance(level, bool)
            or not isinstance(level, (int, float))
            or abs(level) > 1e300
            or not math.isfinite(level)
            or level < 0
        ):
            raise where(f"{excerpt(level)} must be a number >= 0", *path, key)
        for k, value, ok, fix in (
            (period_key, period, period > 0, "must be > 0"),
            (delay_key, delay, delay >= 0, "cannot be negative"),
            (tail_key, tail, tail >= 0, "cannot be negative"),
        ):
            if not ok:
                raise where(f"{excerpt(desc[k])} {fix}", *path, k)
        on, off = float(duty) * period, (1.0 - float(duty)) * period
        if on < MIN_EDGE_S or (duty < 1 and off < MIN_EDGE_S):
            short, k = (on, "duty") if on < MIN_EDGE_S else (off, "duty")
            if period < 2 * MIN_EDGE_S:
                k = period_key
            raise where(
                f"gives a {'pulse' if on < MIN_EDGE_S else 'gap'} of {short:.3g} s (period "
                f"{period:g} s x duty {float(duty):g}); pulses and gaps must last at least "
                f"{MIN_EDGE_S:g} s",
                *path,
                k,
            )
        end_s = delay + n * period + tail
        if not math.isfinite(end_s) or end_s > 1e7:
            raise where(
                f"the train lasts {end_s:g} s (delay + n_pulses x period + tail); describe "
                "at most 1e7 s",
                *path,
                period_key,
            )
        level_si = float(channel.to_si(float(level), unit))
        problem = channel.check_range(np.array([level_si]))
        if problem:
            raise where(problem, *path, key)
        wave = PulseTrain(level_si, period, float(duty), n, delay_s=delay, tail_s=tail)
        text = (
            f"pulse train {float(level):g} {unit}, period {_duration(period)}, duty "
            f"{float(duty) * 100:g} %, {n} pulses, delay {_duration(delay)}, tail "
            f"{_duration(tail)}"
        )
        return wave.to_piecewise(), text
    allowed = _STEPS_KEYS | {key}
    for k in desc:
        if k not in allowed:
            raise where(
                f"unknown key for steps; allowed: {', '.join(sorted(allowed))}",
                *path,
                k if isinstance(k, str) and len(k) <= 40 else excerpt(k),
            )
    times, levels = desc.get("times_s"), level
    if not isinstance(times, list) or not isinstance(levels, list) or not times:
        raise where(
            f"steps need two equal-length lists: times_s = [...] and {key} = [...]",
            *path,
            "times_s",
        )
    if len(times) > MAX_STEPS:
        raise where(f"{len(times)} steps; at most {MAX_STEPS}", *path, "times_s")
    if len(times) != len(levels):
        raise where(f"times_s has {len(times)} entries but {key} has {len(levels)}", *path, key)
    try:
        t = np.array([float(x) for x in times])
        v = np.array([float(x) for x in levels])
    except (TypeError, ValueError, OverflowError):
        raise where("lists must hold (finite) numbers only", *path, "times_s") from None
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(v))):
        raise where("lists must hold finite numbers", *path, "times_s")
    if np.any(np.diff(t) <= 0):
        raise where("times must be strictly increasing", *path, "times_s")
    problem = channel.check_range(channel.to_si(v, unit))
    if problem:
        raise where(f"a level of {problem}, outside the {channel.name} channel's range", *path, key)
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
        key = excerpt(key) if key is not None and len(key) > 40 else key
        return InputError(
            f"{key + ': ' if key else ''}{message} (spec {excerpt(spec, 80)}; e.g. "
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
            raise where(f"{excerpt(item)} is not KEY=VALUE")
        try:
            num = float(v)
        except ValueError:
            raise where(f"{excerpt(v)} is not a number", k.strip()) from None
        if k.strip() in ("n", "n_pulses") and math.isfinite(num) and num == int(num):
            num = int(num)
        desc[k.strip()] = num
    return waveform_from_description(desc, channel, where)


def waveform_from_csv(path, channel):
    """A logged trace CSV (a time column and one ``<channel>_<unit>`` column per input) ->
    (waveform in SI, text). `channel`: one `Channel`, or the device's input channels (every
    one must be a column; the waveform then has one level per channel)."""
    channels = (channel,) if isinstance(channel, Channel) else tuple(channel)
    table = read_csv(path, example="t_s," + ",".join(c.column_names()[0] for c in channels))
    t, tref = time_column(table)
    check_increasing(table, t, tref.column)
    end = t[-1] + (float(np.median(np.diff(t))) if t.size > 1 else 0.0)
    waves, units = [], []
    for ch in channels:
        ref = find_column(table, ch, required=True)
        v = channel_numbers(table, ch, ref, what=f"{ch.description or ch.name} in {ref.unit}")
        waves.append(from_samples(t, v, end_s=end, name=ref.column))
        units.append(ref.column)
    wave = waves[0] if len(waves) == 1 else stack_channels(waves)
    return wave, f"logged trace {Path(path).name} ({t.size} samples, {', '.join(units)})"


def parse_channel_specs(specs, channels):
    """Command-line waveforms for a multi-input device -> (waveform in SI, text).

    `specs`: strings ``NAME=pulse:KEY=VALUE,...`` or ``NAME=const:LEVEL`` (LEVEL in the
    channel's SI unit, or ``const:H2_pct=0``), one per input channel; a single spec without
    ``NAME=`` drives the only input of a single-input device. Every input needs one."""
    channels = tuple(channels)
    by_name = {c.name: c for c in channels}
    given: dict = {}
    for spec in specs:
        name, eq, body = spec.partition("=")
        if not eq or name not in by_name or not body.startswith(("pulse:", "const:")):
            if len(channels) == 1 and spec.startswith(("pulse:", "const:")):
                name, body = channels[0].name, spec
            else:
                raise InputError(
                    f"{excerpt(spec, 80)}: give one spec per input as NAME=pulse:... or "
                    f"NAME=const:LEVEL with NAME one of {', '.join(by_name)} (e.g. "
                    f"{channels[0].name}=pulse:{channels[0].name}_"
                    f"{next(iter(channels[0].units))}=50,period_s=600,duty=0.5,n=3), or a "
                    "CSV with every input column",
                    field="--waveform",
                )
        if name in given:
            raise InputError(f"{name}: given twice", field="--waveform")
        given[name] = body
    missing = [c.name for c in channels if c.name not in given]
    if missing:
        raise InputError(
            f"no waveform for input {', '.join(missing)}; give NAME=pulse:... or NAME=const:0 "
            "for every input",
            field="--waveform",
        )
    waves, texts = [], []
    for ch in channels:
        body = given[ch.name]
        if body.startswith("const:"):
            wave, text = _constant_spec(body, ch)
        else:
            wave, text = parse_waveform_spec(body, ch)
        waves.append(wave)
        texts.append(f"{ch.name}: {text}")
    if len(waves) == 1:
        return waves[0], texts[0]
    end = max(float(w.end_s) for w in waves)
    waves = [_extend(w, end) for w in waves]
    return stack_channels(waves), "; ".join(texts)


def _extend(wave, end_s: float):
    """`wave` held at its last level until `end_s` (channels of one waveform share an end)."""
    if float(wave.end_s) >= end_s:
        return wave
    return PiecewiseConstant(np.asarray(wave.times_s), np.asarray(wave.values), end_s)


def _constant_spec(body: str, channel: Channel):
    from greybox.io._units import channel_conversion

    text = body[len("const:") :].strip()
    key, eq, value = text.partition("=")
    unit = channel.si_unit
    if eq:
        if not key.startswith(channel.name + "_"):
            raise InputError(
                f"{excerpt(key)}: name the level {channel.name}_<unit>", field="--waveform"
            )
        unit, text = key[len(channel.name) + 1 :], value
    try:
        level = float(text)
        conv = channel_conversion(channel, unit) if unit != channel.si_unit else (1.0, 0.0)
    except ValueError as err:
        raise InputError(
            f"{channel.name}=const:{excerpt(text)}: {err}", field="--waveform"
        ) from None
    si = level * conv[0] + conv[1]
    problem = channel.check_range(np.array([si]))
    if not math.isfinite(si) or problem:
        raise InputError(f"{channel.name}=const: {problem or 'not finite'}", field="--waveform")
    # a constant has no end of its own: one second, extended to the other channels' end
    return PiecewiseConstant(np.array([0.0]), np.array([si]), 1.0), f"constant {level:g} {unit}"


def check_log_against_description(
    table: CsvTable,
    ref: ColumnRef,
    logged_si: np.ndarray,
    t: np.ndarray,
    described: PiecewiseConstant,
    channel: Channel,
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
        col, unit = ref.column, ref.unit
        got = float(from_si(logged_si[i], ref.conv))
        want = float(from_si(np.asarray(described(t[i])).reshape(-1)[0], ref.conv))
        raise InputError(
            f"logged {got:g} {unit} at t_s = {t[i]:g} contradicts the waveform "
            f"described in {toml_ref} ({want:g} {unit} there, tolerance "
            f"{LOG_POWER_TOLERANCE:.0%} of the peak); fix the description or the "
            "log, or drop one of them",
            file=table.file,
            line=table.lines[i],
            field=col,
        )
