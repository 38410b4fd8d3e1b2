"""Experiment folders: a TOML description plus one CSV per run -> models and `Experiment`s.

The format is documented in ``experiments/README.md``. Loading checks everything a fit
relies on and raises `greybox.errors.InputError` with ``file:line: field: what is wrong and
how to fix it`` for the first problem found (TOML lines for description problems, CSV lines
with the header as line 1 for data problems). Units are converted to SI here, once, through
the device's `greybox.channels.Channel` declarations; the library never sees a file unit.
"""

from __future__ import annotations

import csv
import dataclasses
import math
import re
import tomllib
from pathlib import Path

import equinox as eqx
import numpy as np

from greybox.channels import PIXELS, Channel
from greybox.data import Experiment
from greybox.errors import InputError
from greybox.freeparams import FreeParameter
from greybox.waveforms import PiecewiseConstant, PulseTrain, from_samples

TOML_NAME = "experiment.toml"
FORMAT_VERSION = 1
ROLES = ("estimation", "validation")
LOG_POWER_TOLERANCE = 0.05  # logged vs described: 5 % of the peak level
TIME_UNITS = {"s": 1.0, "ms": 1e-3}

_TOP_KEYS = {"format", "description", "device", "camera", "fit", "free", "runs"}
_DEVICE_KEYS = {"model", "settings"}
_CAMERA_KEYS = {"fps", "exposure_ms", "um_per_px"}
_FIT_KEYS = {"method", "loss", "n_starts", "seed", "max_steps"}
_FREE_KEYS = {"path", "unit", "lower", "upper", "per_run", "prior_median", "prior_log_sd",
              "initial", "scale"}
_RUN_KEYS = {"name", "file", "role", "y_column", "t_start_s", "settings", "notes"}
_PULSE_KEYS = {"shape", "duty", "n_pulses", "n"}
_STEPS_KEYS = {"shape", "times_s", "end_s"}


# --------------------------------------------------------------------------------------
# TOML: where is a key? (tomllib returns values only; messages need line numbers)


class TomlLines:
    """Best-effort map from key paths to the line that defines them in a TOML text.

    Paths are tuples such as ``("camera", "exposure_ms")`` or ``("runs", 2, "laser",
    "power_mW")`` (array-of-tables elements by 0-based index). `line(*path)` returns the
    line of the longest prefix of `path` that was found, so a missing key points at its table.
    """

    _KEY = re.compile(r"""\s*("(?:[^"\\]|\\.)*"|'[^']*'|[A-Za-z0-9_\-]+)\s*""")

    def __init__(self, text: str):
        self.lines: dict[tuple, int] = {}
        counters: dict[tuple, int] = {}
        current: tuple = ()
        for lineno, raw in enumerate(text.splitlines(), 1):
            s = raw.strip()
            if not s or s.startswith("#"):
                continue
            if s.startswith("[["):
                parts = self._keys(s[2:s.find("]]")])
                counters[tuple(parts)] = counters.get(tuple(parts), -1) + 1
                current = (*parts, counters[tuple(parts)])
                self._record(current, lineno)
            elif s.startswith("["):
                parts = self._keys(s[1:s.find("]")])
                if parts and (parts[0],) in counters:  # [runs.laser] inside the latest [[runs]]
                    parts = [parts[0], counters[(parts[0],)], *parts[1:]]
                current = tuple(parts)
                self._record(current, lineno)
            else:
                key, sep, rest = s.partition("=")
                if not sep:
                    continue
                path = (*current, *self._keys(key))
                self._record(path, lineno)
                if rest.strip().startswith("{"):  # inline table: its keys are on this line
                    for m in re.finditer(r"([A-Za-z0-9_\-]+)\s*=", rest):
                        self._record((*path, m.group(1)), lineno)

    def _keys(self, text: str) -> list:
        parts, pos = [], 0
        while pos < len(text):
            m = self._KEY.match(text, pos)
            if not m:
                break
            parts.append(m.group(1).strip("\"'"))
            pos = m.end()
            if pos < len(text) and text[pos] == ".":
                pos += 1
        return parts

    def _record(self, path: tuple, lineno: int) -> None:
        self.lines.setdefault(path, lineno)

    def line(self, *path) -> int | None:
        for n in range(len(path), 0, -1):
            if path[:n] in self.lines:
                return self.lines[path[:n]]
        return None


def _field_name(path) -> str:
    out = ""
    for p in path:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out


class _Toml:
    """A parsed TOML file with helpers that raise located `InputError`s."""

    def __init__(self, path: Path):
        self.path = path
        self.file = str(path)
        if not path.is_file():
            what = "is a folder" if path.exists() else "does not exist"
            raise InputError(f"{what}; an experiment folder needs an {TOML_NAME} describing "
                             "its runs (see experiments/README.md)", file=self.file,
                             field=TOML_NAME)
        try:
            text = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as err:
            raise InputError(f"cannot be read as UTF-8 text ({err}); save it as plain text",
                             file=self.file, line=1, field=TOML_NAME) from None
        self.where = TomlLines(text)
        try:
            self.data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as err:
            msg = str(err)
            m = re.search(r"\(at line (\d+), column \d+\)", msg)
            line = int(m.group(1)) if m else None
            field = "TOML syntax"
            if line is not None:
                key = text.splitlines()[line - 1].partition("=")[0].strip() if \
                    line <= len(text.splitlines()) else ""
                if key and re.fullmatch(r"[A-Za-z0-9_.\-\"']+", key):
                    field = key.strip("\"'")
            what = re.sub(r"\s*\(at line \d+, column \d+\)", "", msg)
            raise InputError(f"not valid TOML ({what}); strings need quotes, numbers none, "
                             "tables are [name] and runs [[runs]]", file=self.file, line=line,
                             field=field) from None

    def error(self, message: str, *path) -> InputError:
        return InputError(message, file=self.file, line=self.where.line(*path),
                          field=_field_name(path) if path else None)

    def check_keys(self, table: dict, allowed: set, *path) -> None:
        for key in table:
            if key not in allowed:
                raise self.error(f"unknown key; allowed here: {', '.join(sorted(allowed))} "
                                 "(check the spelling and the unit suffix)", *path, key)

    def table(self, parent: dict, key: str, *path, required: bool = True) -> dict:
        value = parent.get(key)
        if value is None:
            if required:
                raise self.error(f"missing; add a [{_field_name((*path, key))}] table", *path, key)
            return {}
        if not isinstance(value, dict):
            raise self.error("must be a table", *path, key)
        return value

    def number(self, table: dict, key: str, *path, default=None, required: bool = False,
               positive: bool = False, nonneg: bool = False, unit: str = "") -> float | None:
        if key not in table:
            if required:
                raise self.error(f"missing; give a number{f' in {unit}' if unit else ''}",
                                 *path, key)
            return default
        value = table[key]
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.error(f"{value!r} is not a number; write it without quotes", *path, key)
        value = float(value)
        if not math.isfinite(value):
            raise self.error(f"{value} is not finite; give a finite number", *path, key)
        if positive and not value > 0:
            raise self.error(f"{value:g} must be > 0{f' {unit}' if unit else ''}", *path, key)
        if nonneg and not value >= 0:
            raise self.error(f"{value:g} must be >= 0{f' {unit}' if unit else ''}", *path, key)
        return value

    def integer(self, table: dict, key: str, *path, default=None, minimum: int = 1):
        if key not in table:
            return default
        value = table[key]
        if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
            raise self.error(f"{value!r} must be a whole number >= {minimum}", *path, key)
        return value

    def string(self, table: dict, key: str, *path, default=None, required: bool = False,
               choices=None) -> str | None:
        if key not in table:
            if required:
                raise self.error("missing; give a quoted string", *path, key)
            return default
        value = table[key]
        if not isinstance(value, str) or not value.strip():
            raise self.error(f"{value!r} must be a non-empty quoted string", *path, key)
        if choices is not None and value not in choices:
            raise self.error(f"{value!r} is not one of {', '.join(map(repr, choices))}",
                             *path, key)
        return value


# --------------------------------------------------------------------------------------
# CSV tables


@dataclasses.dataclass(frozen=True)
class CsvTable:
    """A CSV file as text cells: `header`, `rows` (lists of str) and each row's file line."""

    file: str
    header: tuple
    rows: tuple
    lines: tuple

    def column(self, name: str) -> list:
        j = self.header.index(name)
        return [r[j] for r in self.rows]

    def numbers(self, name: str, *, allow_missing: bool = False, nonneg: bool = False,
                what: str = "") -> np.ndarray:
        """Column `name` as floats; empty/nan cells are NaN only if `allow_missing`."""
        out = np.empty(len(self.rows))
        for i, cell in enumerate(self.column(name)):
            text = cell.strip()
            if text == "" or text.lower() in ("nan", "na"):
                if not allow_missing:
                    raise InputError(f"cell is {'empty' if not text else text!r}; every row "
                                     f"needs a {what or 'number'}", file=self.file,
                                     line=self.lines[i], field=name)
                out[i] = np.nan
                continue
            try:
                v = float(text)
            except ValueError:
                raise InputError(f"{text!r} is not a number; use a plain decimal number "
                                 "(point as decimal separator)"
                                 + (" or leave the cell empty / write nan for a dropped frame"
                                    if allow_missing else ""),
                                 file=self.file, line=self.lines[i], field=name) from None
            if not math.isfinite(v):
                raise InputError(f"{text!r} is infinite; give a finite number"
                                 + (" or nan for a dropped frame" if allow_missing else ""),
                                 file=self.file, line=self.lines[i], field=name)
            if nonneg and v < 0:
                raise InputError(f"{v:g} is negative; {what or 'the value'} must be >= 0",
                                 file=self.file, line=self.lines[i], field=name)
            out[i] = v
        return out


def read_csv(path, *, example: str = "t_s,y_px") -> CsvTable:
    """Read a CSV with a header row (line 1, or the first line not starting with '#').

    Lines starting with '#' and blank lines are skipped; every row must have as many cells as
    the header. Cells stay text; convert with `CsvTable.numbers`.
    """
    path = Path(path)
    file = str(path)
    if not path.is_file():
        raise FileNotFoundError(f"{file}: no such file")
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(f"cannot be read as UTF-8 text ({err}); export the table as CSV",
                         file=file, line=1, field="header") from None
    header, rows, lines = None, [], []
    for lineno, cells in enumerate(csv.reader(text.splitlines()), 1):
        if not cells or all(not c.strip() for c in cells) or cells[0].lstrip().startswith("#"):
            continue
        cells = [c.strip() for c in cells]
        if header is None:
            header = cells
            header_line = lineno
            continue
        if len(cells) != len(header):
            raise InputError(f"has {len(cells)} cells but the header has {len(header)} "
                             f"({','.join(header)}); every row needs one cell per column",
                             file=file, line=lineno, field="row")
        rows.append(cells)
        lines.append(lineno)
    if header is None:
        raise InputError(f"the file is empty; the first line must name the columns (e.g. "
                         f"{example}) and each following line holds one frame",
                         file=file, line=1, field="header")
    dup = sorted({h for h in header if header.count(h) > 1})
    if dup:
        raise InputError(f"column {dup[0]!r} appears twice; rename or remove one",
                         file=file, line=header_line, field=dup[0])
    if not rows:
        raise InputError(f"has a header ({','.join(header)}) but no data rows; one row per "
                         "frame is needed", file=file, line=header_line + 1, field="rows")
    return CsvTable(file, tuple(header), tuple(rows), tuple(lines))


def channel_column(table: CsvTable, channel: Channel, *, required: bool,
                   choose: str | None = None, choose_hint: str = "") -> str | None:
    """The one column of `table` holding `channel` (``<name>_<unit>``), checked.

    A column named after the channel with an unknown unit suffix is an error (it is surely
    meant for this channel); several valid columns need `choose`.
    """
    found = []
    for col in table.header:
        if col == channel.name or col.startswith(channel.name + "_"):
            unit = col[len(channel.name) + 1:]
            if unit not in channel.units:
                raise InputError(
                    f"{'no' if not unit else 'unknown'} unit suffix"
                    f"{'' if not unit else f' {unit!r}'}; {channel.description or channel.name}"
                    f" columns must be named one of {', '.join(channel.column_names())}",
                    file=table.file, line=1, field=col)
            found.append(col)
    if choose is not None:
        if choose not in table.header:
            raise InputError(f"column {choose!r} (chosen by y_column) is not in the header "
                             f"({','.join(table.header)})", file=table.file, line=1,
                             field=choose)
        return choose
    if len(found) > 1:
        raise InputError(f"several {channel.name} columns ({', '.join(found)}); say which to "
                         f"use{choose_hint}", file=table.file, line=1, field=found[0])
    if not found:
        if required:
            raise InputError(f"missing column: no {channel.description or channel.name} column "
                             f"in the header ({','.join(table.header)}); name it one of "
                             f"{', '.join(channel.column_names())}", file=table.file, line=1,
                             field=channel.column_names()[0])
        return None
    return found[0]


def time_column(table: CsvTable) -> np.ndarray:
    """The `t_s` column (seconds, finite); other time spellings get a rename hint."""
    for col in table.header:
        if col != "t_s" and (col in ("t", "time") or re.fullmatch(r"(t|time)_\w+", col)):
            raise InputError("wrong unit suffix: frame times must be seconds in a column "
                             "named t_s (convert, e.g. ms / 1000, and rename the column)",
                             file=table.file, line=1, field=col)
    if "t_s" not in table.header:
        raise InputError(f"missing column: no t_s (frame time in seconds) in the header "
                         f"({','.join(table.header)})", file=table.file, line=1, field="t_s")
    return table.numbers("t_s", what="frame time in seconds")


def _check_increasing(table: CsvTable, t: np.ndarray) -> None:
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        kind = "repeats" if t[i] == t[i - 1] else "goes backwards from"
        raise InputError(f"{t[i]:g} s {kind} the previous row's {t[i - 1]:g} s; frame times "
                         "must be strictly increasing (sort the rows, drop duplicates)",
                         file=table.file, line=table.lines[i], field="t_s")


# --------------------------------------------------------------------------------------
# Waveforms


def _time_key(desc: dict, base: str, path: tuple, where, *, required: bool,
              default: float | None = None) -> tuple:
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
    """(key, value in file units, SI value) of the ``power_<unit>`` entry."""
    keys = [k for k in desc if k.startswith("power_")]
    if not keys:
        raise where(f"missing; give the level as one of "
                    f"{', '.join('power_' + u for u in channel.units if channel.units[u])}",
                    *path, "power")
    if len(keys) > 1:
        raise where("give the level once", *path, keys[1])
    key = keys[0]
    unit = key[len("power_"):]
    if unit not in channel.units or channel.units[unit] is None:
        raise where(f"unknown unit {unit!r}; use one of "
                    f"{', '.join('power_' + u for u in channel.units if channel.units[u])}",
                    *path, key)
    return key, desc[key], unit


def waveform_from_description(desc: dict, channel: Channel, where, path: tuple = ()):
    """A described input waveform -> (PiecewiseConstant in SI, one-line text).

    `desc`: ``{"shape": "pulse", "power_mW": 20, "period_ms": 500, "duty": 0.5,
    "n_pulses": 10, "delay_ms": 300, "tail_ms": 700}`` or ``{"shape": "steps",
    "times_s": [...], "power_mW": [...], "end_s": 12.0}``. `where(message, *path_keys)`
    builds the error to raise (it knows the file and lines).
    """
    if not isinstance(desc, dict):
        raise where("must be a table such as { shape = \"pulse\", power_mW = 20, "
                    "period_ms = 500, duty = 0.5, n_pulses = 10 }", *path)
    shape = desc.get("shape", "pulse")
    if shape not in ("pulse", "steps"):
        raise where(f"{shape!r} is not a waveform shape; use \"pulse\" or \"steps\"",
                    *path, "shape")
    key, level, unit = _level_key(desc, channel, path, where)
    if shape == "pulse":
        allowed = _PULSE_KEYS | {key} | {f"{b}_{u}" for b in ("period", "delay", "tail")
                                         for u in TIME_UNITS}
        for k in desc:
            if k not in allowed:
                raise where(f"unknown key for a pulse train; allowed: {', '.join(sorted(allowed))}",
                            *path, k)
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
        if isinstance(level, bool) or not isinstance(level, (int, float)) or \
                not math.isfinite(level) or level < 0:
            raise where(f"{level!r} must be a number >= 0", *path, key)
        for k, value, ok, fix in ((period_key, period, period > 0, "must be > 0"),
                                  (delay_key, delay, delay >= 0, "cannot be negative"),
                                  (tail_key, tail, tail >= 0, "cannot be negative")):
            if not ok:
                raise where(f"{desc[k]!r} {fix}", *path, k)
        level_si = float(channel.to_si(float(level), unit))
        wave = PulseTrain(level_si, period, float(duty), n, delay_s=delay, tail_s=tail)
        text = (f"pulse train {float(level):g} {unit}, period {period * 1e3:g} ms, duty "
                f"{float(duty) * 100:g} %, {n} pulses, delay {delay * 1e3:g} ms, tail "
                f"{tail * 1e3:g} ms")
        return wave.to_piecewise(), text
    allowed = _STEPS_KEYS | {key}
    for k in desc:
        if k not in allowed:
            raise where(f"unknown key for steps; allowed: {', '.join(sorted(allowed))}", *path, k)
    times, levels = desc.get("times_s"), level
    if not isinstance(times, list) or not isinstance(levels, list) or not times:
        raise where("steps need two equal-length lists: times_s = [...] and "
                    f"{key} = [...]", *path, "times_s")
    if len(times) != len(levels):
        raise where(f"times_s has {len(times)} entries but {key} has {len(levels)}",
                    *path, key)
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
        return InputError(f"{key + ': ' if key else ''}{message} (spec {spec!r}; e.g. "
                          "pulse:power_mW=25,period_ms=300,duty=0.5,n=10)", field="--waveform")

    shape, sep, body = spec.partition(":")
    if not sep or shape != "pulse":
        raise where("expected 'pulse:KEY=VALUE,...' or the path of a CSV with t_s,"
                    f"{channel.name}_<unit> columns")
    desc: dict = {"shape": "pulse"}
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
    _check_increasing(table, t)
    col = channel_column(table, channel, required=True)
    unit = col[len(channel.name) + 1:]
    v = table.numbers(col, nonneg=True, what=f"{channel.description or channel.name} in {unit}")
    end = t[-1] + (float(np.median(np.diff(t))) if t.size > 1 else 0.0)
    wave = from_samples(t, channel.to_si(v, unit), end_s=end, name=col)
    return wave, f"logged trace {Path(path).name} ({t.size} samples, {unit})"


def _check_log_against_description(table: CsvTable, col: str, logged_si: np.ndarray,
                                   t: np.ndarray, described: PiecewiseConstant, channel: Channel,
                                   unit: str, slack_s: float, toml_ref: str) -> None:
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
        raise InputError(f"logged {got:g} {unit} at t_s = {t[i]:g} contradicts the waveform "
                         f"described in {toml_ref} ({want:g} {unit} there, tolerance "
                         f"{LOG_POWER_TOLERANCE:.0%} of the peak); fix the description or the "
                         "log, or drop one of them", file=table.file, line=table.lines[i],
                         field=col)


# --------------------------------------------------------------------------------------
# The experiment set


@dataclasses.dataclass(frozen=True)
class RunInfo:
    """What the report says about one run's file (the numbers live in its `Experiment`)."""

    name: str
    role: str
    file: str
    y_column: str
    n_rows: int
    n_valid: int
    waveform: str  # one-line description of the input
    input_source: str  # "described", "logged" or "described (log checked)"


@dataclasses.dataclass(frozen=True)
class ExperimentSet:
    """A loaded experiment folder: everything `greybox fit` needs, in SI.

    - `device`: the device module (`models.<name>`); `model`: its default model with the
      [camera] settings and the fixed [device.settings] applied.
    - `camera`: {"fps", "exposure_s", "m_per_px"}; `fixed`: {path: SI value}.
    - `estimation`, `validation`: `Experiment`s by role; `runs`: `RunInfo` per run.
    - `free`: `FreeParameter`s to fit; `fit_options`: keyword arguments for `greybox.fit`.
    """

    name: str
    directory: Path
    description: str
    device_name: str
    device: object
    model: object
    camera: dict
    fixed: dict
    estimation: tuple
    validation: tuple
    runs: tuple
    free: tuple
    fit_options: dict

    def run_info(self, name: str) -> RunInfo:
        return next(r for r in self.runs if r.name == name)


def configure_model(device, camera: dict, fixed: dict):
    """`device.default_model()` with the camera settings and the fixed values applied."""
    from greybox.parameters import set_values

    model = device.default_model()
    cam = model.camera
    new_cam = type(cam)(m_per_px=float(camera["m_per_px"]), exposure_s=float(camera["exposure_s"]),
                        offset_m=cam.offset_m, drift_m_per_s=cam.drift_m_per_s,
                        n_quadrature=cam.n_quadrature)
    model = eqx.tree_at(lambda m: m.camera, model, new_cam)
    return set_values(model, list(fixed), [float(v) for v in fixed.values()])


def _parameter_units(device) -> dict:
    return {p.path: p.unit for p in getattr(device, "PARAMETERS", ())}


def _settings(doc: _Toml, table, model, *path) -> dict:
    from greybox.parameters import get_value

    if not isinstance(table, dict):
        raise doc.error("must be a table of \"dotted.path\" = value (SI units)", *path)
    out = {}
    for key, value in table.items():
        if isinstance(value, dict):  # unquoted dotted key: thermal.tau_s = 0.04
            flat = _flatten(value, key)
        else:
            flat = {key: value}
        for k, v in flat.items():
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise doc.error(f"{v!r} must be a finite number (SI units)", *path, key)
            try:
                get_value(model, k)
            except ValueError:
                raise doc.error(f"{k!r} is not a parameter of the device model; see its "
                                "parameter table (models/<device>.py PARAMETERS)", *path,
                                key) from None
            out[k] = float(v)
    return out


def _flatten(table: dict, prefix: str) -> dict:
    out = {}
    for k, v in table.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}.{k}"))
        else:
            out[f"{prefix}.{k}"] = v
    return out


def _free_parameters(doc: _Toml, entries, device, model, fixed: dict) -> tuple:
    from greybox.parameters import get_value

    if entries is None:
        return tuple(device.default_free_parameters())
    if not isinstance(entries, list) or not entries:
        raise doc.error("must be one or more [[free]] tables (or leave it out for the "
                        "device's standard fit)", "free")
    units = _parameter_units(device)
    out, seen = [], set()
    for i, e in enumerate(entries):
        doc.check_keys(e, _FREE_KEYS, "free", i)
        p = doc.string(e, "path", "free", i, required=True)
        try:
            get_value(model, p)
        except ValueError:
            known = ", ".join(sorted(units)) or "see models/<device>.py"
            raise doc.error(f"{p!r} is not a parameter of {device.NAME}; known: {known}",
                            "free", i, "path") from None
        if p in seen:
            raise doc.error(f"{p!r} is listed twice", "free", i, "path")
        if p in fixed:
            raise doc.error(f"{p!r} is also fixed in [device.settings]; fit it or fix it",
                            "free", i, "path")
        seen.add(p)
        unit = doc.string(e, "unit", "free", i, default=units.get(p))
        if unit is None:
            raise doc.error("missing; this path is not in the device's parameter table, so "
                            "give its SI unit (e.g. unit = \"s\")", "free", i, "unit")
        per_run = e.get("per_run", False)
        if not isinstance(per_run, bool):
            raise doc.error(f"{per_run!r} must be true or false", "free", i, "per_run")
        kw = {k: doc.number(e, k, "free", i) for k in
              ("lower", "upper", "prior_median", "prior_log_sd", "initial")}
        scale = doc.number(e, "scale", "free", i, default=1.0, positive=True)
        try:
            fp = FreeParameter(p, unit=unit, per_experiment=per_run, scale=scale, **kw)
            if kw["initial"] is not None:
                fp.check_value(kw["initial"])
        except ValueError as err:
            raise doc.error(str(err).split(": ", 1)[-1], "free", i, "path") from None
        out.append(fp)
    return tuple(out)


def _load_run(doc: _Toml, i: int, entry: dict, directory: Path, device, model, camera: dict,
              known_names: set):
    path = ("runs", i)
    if not isinstance(entry, dict):
        raise doc.error("each run is a [[runs]] table", *path)
    inputs = tuple(device.INPUTS)
    outputs = tuple(device.OUTPUTS)
    doc.check_keys(entry, _RUN_KEYS | {c.name for c in inputs}, *path)
    name = doc.string(entry, "name", *path, required=True)
    if name in known_names:
        raise doc.error(f"run name {name!r} is used twice; names must be unique", *path, "name")
    if not re.fullmatch(r"[A-Za-z0-9_.\-]+", name):
        raise doc.error(f"{name!r}: use letters, digits, '_', '-' or '.' only (it names "
                        "figure files)", *path, "name")
    role = doc.string(entry, "role", *path, required=True, choices=ROLES)
    rel = doc.string(entry, "file", *path, required=True)
    csv_path = directory / rel
    if not csv_path.is_file():
        raise doc.error(f"{csv_path} does not exist; put the run's CSV there or fix the "
                        "file name (relative to the experiment folder)", *path, "file")
    t_start = doc.number(entry, "t_start_s", *path, default=0.0)
    settings = _settings(doc, entry.get("settings", {}), model, *path, "settings")
    y_choice = doc.string(entry, "y_column", *path)

    table = read_csv(csv_path)
    t = time_column(table)
    _check_increasing(table, t)
    ys, y_cols = [], []
    for ch in outputs:
        col = channel_column(table, ch, required=True, choose=y_choice if len(outputs) == 1
                             else None, choose_hint=f" with y_column = \"...\" in run {name!r} "
                             f"of {doc.file}")
        unit = col[len(ch.name) + 1:]
        v = table.numbers(col, allow_missing=True, what=f"{ch.name} reading in {unit}")
        if not np.isfinite(v).any():
            raise InputError(f"every reading is empty or NaN ({v.size} rows); a run needs at "
                             "least one tracked frame (check the tracker output)",
                             file=table.file, line=table.lines[0], field=col)
        ys.append(ch.to_si(v, unit, camera["m_per_px"]) if unit == PIXELS else ch.to_si(v, unit))
        y_cols.append(col)
    y = np.column_stack(ys)
    valid = np.all(np.isfinite(y), axis=1)
    if valid.sum() >= 3:
        interval = float(np.median(np.diff(t[valid])))
        expected = 1.0 / camera["fps"]
        if not expected / 3 <= interval <= 3 * expected:
            hint = (" (t_s looks like milliseconds: divide by 1000)"
                    if 300 * expected <= interval <= 3000 * expected else "")
            raise InputError(f"median frame interval {interval:g} s does not match 1/fps = "
                             f"{expected:g} s from [camera] fps in {doc.file}{hint}; t_s must "
                             "be seconds and fps the camera's frame rate", file=table.file,
                             line=table.lines[0], field="t_s")

    levels, sources, texts = [], [], []
    for ch in inputs:
        desc = entry.get(ch.name)
        col = channel_column(table, ch, required=False)
        logged = None
        if col is not None:
            unit = col[len(ch.name) + 1:]
            v = table.numbers(col, nonneg=True,
                              what=f"logged {ch.description or ch.name} in {unit}")
            logged = (col, unit, ch.to_si(v, unit))
        if desc is None and logged is None:
            raise doc.error(f"run {name!r} has no {ch.name} waveform: describe it here "
                            f"({ch.name} = {{ shape = \"pulse\", power_mW = ..., period_ms = "
                            f"..., duty = 0.5, n_pulses = ... }}) or log it in a "
                            f"{ch.column_names()[0]} column of {csv_path.name}", *path, ch.name)
        if desc is not None:
            wave, text = waveform_from_description(desc, ch, doc.error, (*path, ch.name))
            source = "described"
            if logged is not None:
                slack = max(1.0 / camera["fps"], camera["exposure_s"])
                ref = f"{doc.file}:{doc.where.line(*path, ch.name)}"
                _check_log_against_description(table, logged[0], logged[2], t, wave, ch,
                                               logged[1], slack, ref)
                source = "described (log checked)"
        else:
            end = t[-1] + (float(np.median(np.diff(t))) if t.size > 1 else 0.0)
            wave = from_samples(t, logged[2], end_s=end, name=logged[0])
            text = f"logged in {logged[0]} ({t.size} samples, held between samples)"
            source = "logged"
        levels.append(wave)
        sources.append(source)
        texts.append(text)
    if len(levels) == 1:
        inputs_wave = levels[0]
    else:
        from greybox.waveforms import stack_channels

        inputs_wave = stack_channels(levels)
    try:
        exp = Experiment(name, t, y if y.shape[1] > 1 else y[:, 0], inputs_wave,
                         t_start_s=t_start, role=role, settings=settings)
    except ValueError as err:
        raise InputError(str(err), file=table.file) from None
    info = RunInfo(name, role, str(csv_path), ",".join(y_cols), t.size, int(valid.sum()),
                   "; ".join(texts), "; ".join(sources))
    return exp, info


def _initial_offset(free: tuple, estimation: tuple) -> tuple:
    """Start per-run camera offsets at the median rest reading of the estimation runs.

    The fitter starts every run's offset from one value; a camera reading is the image
    position (hundreds of um), so starting from 0 puts the fit far from the data. The rest
    reading of a run is the median of its frames before the input first switches on (all
    frames if there are fewer than three such frames).
    """
    rest = []
    for e in estimation:
        levels = np.asarray(e.inputs.values).reshape(len(e.inputs.times_s), -1)
        on = e.inputs.times_s[np.any(levels != 0, axis=1)]
        y = e.y[:, 0]
        pick = y[(e.t_s < (on[0] if on.size else np.inf)) & np.isfinite(y)]
        rest.append(np.median(pick) if pick.size >= 3 else np.nanmedian(y))
    start = float(np.median(rest))
    return tuple(dataclasses.replace(p, initial=start)
                 if p.path == "camera.offset_m" and p.per_experiment and p.initial is None
                 else p for p in free)


def load_experiment_set(directory) -> ExperimentSet:
    """Load and check an experiment folder (``experiment.toml`` + run CSVs).

    Raises `InputError` (``file:line: field: problem and fix``) for the first problem.
    """
    import models
    from greybox.fit import LOSSES
    from greybox.simulate import METHODS

    directory = Path(directory)
    if not directory.is_dir():
        raise InputError(f"{directory} is not a folder; give the experiment folder that holds "
                         f"{TOML_NAME}", file=str(directory), field="EXPERIMENT_DIR")
    doc = _Toml(directory / TOML_NAME)
    data = doc.data
    doc.check_keys(data, _TOP_KEYS)
    version = data.get("format", FORMAT_VERSION)
    if version != FORMAT_VERSION:
        raise doc.error(f"{version!r}: this greybox reads format = {FORMAT_VERSION}", "format")
    description = data.get("description", "")
    if not isinstance(description, str):
        raise doc.error("must be a quoted string", "description")

    dev = doc.table(data, "device")
    doc.check_keys(dev, _DEVICE_KEYS, "device")
    device_name = doc.string(dev, "model", "device", required=True)
    try:
        device = models.load(device_name)
    except ValueError:
        raise doc.error(f"unknown device model {device_name!r}; known: "
                        f"{', '.join(models.available())} (a module in models/)",
                        "device", "model") from None

    cam = doc.table(data, "camera")
    doc.check_keys(cam, _CAMERA_KEYS, "camera")
    camera = {
        "fps": doc.number(cam, "fps", "camera", required=True, positive=True, unit="frames/s"),
        "exposure_s": doc.number(cam, "exposure_ms", "camera", required=True, nonneg=True,
                                 unit="ms (0 = instantaneous)") * 1e-3,
        "m_per_px": doc.number(cam, "um_per_px", "camera", required=True, positive=True,
                               unit="um per pixel") * 1e-6,
    }
    if camera["exposure_s"] > 1.0 / camera["fps"] * 1.0001:
        raise doc.error(f"{camera['exposure_s'] * 1e3:g} ms is longer than one frame interval "
                        f"(1/fps = {1e3 / camera['fps']:g} ms); check fps and exposure_ms",
                        "camera", "exposure_ms")
    base = configure_model(device, camera, {})
    fixed = _settings(doc, dev.get("settings", {}), base, "device", "settings")
    model = configure_model(device, camera, fixed)

    fitopt = doc.table(data, "fit", required=False)
    doc.check_keys(fitopt, _FIT_KEYS, "fit")
    fit_options = {
        "method": doc.string(fitopt, "method", "fit", default="zoh", choices=METHODS),
        "loss": doc.string(fitopt, "loss", "fit", default="huber", choices=LOSSES),
        "n_starts": doc.integer(fitopt, "n_starts", "fit", default=1),
        "seed": doc.integer(fitopt, "seed", "fit", default=0, minimum=0),
        "max_steps": doc.integer(fitopt, "max_steps", "fit", default=200),
    }
    if fit_options["method"] == "zoh" and not model.is_linear:
        raise doc.error("the exact 'zoh' path needs a linear device; use method = \"adaptive\"",
                        "fit", "method")
    free = _free_parameters(doc, data.get("free"), device, model, fixed)

    runs = data.get("runs")
    if not isinstance(runs, list) or not runs:
        raise doc.error("no runs; add one [[runs]] table per CSV (name, file, role, and the "
                        "laser waveform)", "runs")
    experiments, infos, names = [], [], set()
    for i, entry in enumerate(runs):
        exp, info = _load_run(doc, i, entry, directory, device, model, camera, names)
        names.add(exp.name)
        experiments.append(exp)
        infos.append(info)
    estimation = tuple(e for e in experiments if e.role == "estimation")
    validation = tuple(e for e in experiments if e.role == "validation")
    if not estimation or sum(int(e.mask.all(axis=1).sum()) for e in estimation) == 0:
        raise doc.error("the estimation set has zero frames: no run has role = "
                        "\"estimation\" (with tracked frames); mark at least one run for "
                        "estimation", "runs", 0, "role")
    free = _initial_offset(free, estimation)
    return ExperimentSet(
        name=directory.resolve().name, directory=directory, description=description,
        device_name=device_name, device=device, model=model, camera=camera, fixed=fixed,
        estimation=estimation, validation=validation, runs=tuple(infos), free=free,
        fit_options=fit_options)
