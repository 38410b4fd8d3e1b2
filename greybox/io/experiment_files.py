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
from greybox.device import AbstractSteppedDevice
from greybox.errors import InputError
from greybox.freeparams import FreeParameter
from greybox.waveforms import PiecewiseConstant, PulseTrain, from_samples, stack_channels

TOML_NAME = "experiment.toml"
ROLES = ("estimation", "validation")
LOG_POWER_TOLERANCE = 0.05  # logged vs described: 5 % of the peak level
TIME_UNITS = {"s": 1.0, "ms": 1e-3}
WAVEFORM_TYPES = ("pulse_train", "steps", "logged")

_TOP_KEYS = {"experiment", "camera", "fit", "runs"}
_EXPERIMENT_KEYS = {"device", "description", "settings"}
_CAMERA_KEYS = {"fps", "exposure_ms", "um_per_px"}
_FIT_KEYS = {"method", "loss", "n_starts", "seed", "max_steps", "free"}
_FREE_KEYS = {
    "path",
    "unit",
    "lower",
    "upper",
    "per_run",
    "prior_median",
    "prior_log_sd",
    "initial",
    "scale",
}
_RUN_KEYS = {"name", "file", "role", "waveform", "settings", "y_column", "t_start_s", "notes"}
_PULSE_KEYS = {"type", "duty", "n_pulses", "n"}
_STEPS_KEYS = {"type", "times_s", "end_s"}


# --------------------------------------------------------------------------------------
# TOML: where is a key? (tomllib returns values only; messages need line numbers)


class TomlLines:
    """Best-effort map from key paths to the line that defines them in a TOML text.

    Paths are tuples such as ``("camera", "exposure_ms")`` or ``("runs", 2, "waveform",
    "power_mW")`` (array elements by 0-based index). `line(*path)` returns the
    line of the longest prefix of `path` that was found, so a missing key points at its table.
    """

    _KEY = re.compile(r"""\s*("(?:[^"\\]|\\.)*"|'[^']*'|[A-Za-z0-9_\-]+)\s*""")

    def __init__(self, text: str):
        self.lines: dict[tuple, int] = {}
        counters: dict[tuple, int] = {}
        current: tuple = ()
        array = None  # (path, next element index) while inside a multi-line array
        for lineno, raw in enumerate(text.splitlines(), 1):
            s = (
                raw.split(" #")[0].strip()
                if "#" in raw and not raw.strip().startswith("#")
                else raw.strip()
            )
            if not s or s.startswith("#"):
                continue
            if array is None and s.startswith("[["):
                parts = self._keys(s[2 : s.find("]]")])
                counters[tuple(parts)] = counters.get(tuple(parts), -1) + 1
                current = (*parts, counters[tuple(parts)])
                self._record(current, lineno)
            elif array is None and s.startswith("["):
                parts = self._keys(s[1 : s.find("]")])
                if parts and (parts[0],) in counters:  # [runs.laser] inside the latest [[runs]]
                    parts = [parts[0], counters[(parts[0],)], *parts[1:]]
                current = tuple(parts)
                self._record(current, lineno)
            elif array is not None:  # inside a multi-line array: one element per line
                array_path, index = array
                if s[0] in "\"'{0123456789-+.tf":
                    self._record((*array_path, index), lineno)
                    self._inline_keys((*array_path, index), s, lineno)
                    array = (array_path, index + 1)
                if s.startswith("]") or s.rstrip(",").endswith("]") and s.count("]") > s.count("["):
                    array = None
            else:
                key, sep, rest = s.partition("=")
                if not sep:
                    continue
                path = (*current, *self._keys(key))
                self._record(path, lineno)
                rest = rest.strip()
                if rest.startswith("{"):  # inline table: its keys are on this line
                    self._inline_keys(path, rest, lineno)
                elif rest.startswith("["):
                    if rest.count("[") > rest.count("]"):
                        array = (path, 0)
                    else:  # a one-line array: every element is on this line
                        for k in range(rest.count(",") + 1):
                            self._record((*path, k), lineno)

    def _inline_keys(self, path: tuple, text: str, lineno: int) -> None:
        for m in re.finditer(r"([A-Za-z0-9_\-]+)\s*=", text):
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
        self.file = str(path)
        if not path.is_file():
            what = "is a folder" if path.exists() else "does not exist"
            raise InputError(
                f"{what}; an experiment folder needs an {TOML_NAME} describing "
                "its runs (see experiments/README.md)",
                file=self.file,
                field=TOML_NAME,
            )
        try:
            text = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as err:
            raise InputError(
                f"cannot be read as UTF-8 text ({err}); save it as plain text",
                file=self.file,
                line=1,
                field=TOML_NAME,
            ) from None
        self.where = TomlLines(text)
        try:
            self.data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as err:
            msg = str(err)
            m = re.search(r"\(at line (\d+), column \d+\)", msg)
            line = int(m.group(1)) if m else None
            field = "TOML syntax"
            if line is not None:
                key = (
                    text.splitlines()[line - 1].partition("=")[0].strip()
                    if line <= len(text.splitlines())
                    else ""
                )
                if key and re.fullmatch(r"[A-Za-z0-9_.\-\"']+", key):
                    field = key.strip("\"'")
            what = re.sub(r"\s*\(at line \d+, column \d+\)", "", msg)
            raise InputError(
                f"not valid TOML ({what}); strings need quotes, numbers none, "
                "tables are [name] and runs [[runs]]",
                file=self.file,
                line=line,
                field=field,
            ) from None

    def error(self, message: str, *path) -> InputError:
        return InputError(
            message,
            file=self.file,
            line=self.where.line(*path),
            field=_field_name(path) if path else None,
        )

    def check_keys(self, table: dict, allowed: set, *path) -> None:
        for key in table:
            if key not in allowed:
                raise self.error(
                    f"unknown key; allowed here: {', '.join(sorted(allowed))} "
                    "(check the spelling and the unit suffix)",
                    *path,
                    key,
                )

    def table(self, parent: dict, key: str, *path, required: bool = True) -> dict:
        value = parent.get(key)
        if value is None:
            if required:
                raise self.error(f"missing; add a [{_field_name((*path, key))}] table", *path, key)
            return {}
        if not isinstance(value, dict):
            raise self.error("must be a table", *path, key)
        return value

    def number(
        self,
        table: dict,
        key: str,
        *path,
        default=None,
        positive: bool = False,
        nonneg: bool = False,
        unit: str = "",
    ) -> float | None:
        if key not in table:
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

    def string(
        self, table: dict, key: str, *path, default=None, required: bool = False, choices=None
    ) -> str | None:
        if key not in table:
            if required:
                raise self.error("missing; give a quoted string", *path, key)
            return default
        value = table[key]
        if not isinstance(value, str) or not value.strip():
            raise self.error(f"{value!r} must be a non-empty quoted string", *path, key)
        if choices is not None and value not in choices:
            raise self.error(f"{value!r} is not one of {', '.join(map(repr, choices))}", *path, key)
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

    def numbers(
        self, name: str, *, allow_missing: bool = False, nonneg: bool = False, what: str = ""
    ) -> np.ndarray:
        """Column `name` as floats; empty/nan cells are NaN only if `allow_missing`."""
        out = np.empty(len(self.rows))
        for i, cell in enumerate(self.column(name)):
            text = cell.strip()
            if text == "" or text.lower() in ("nan", "na"):
                if not allow_missing:
                    raise InputError(
                        f"cell is {'empty' if not text else text!r}; every row "
                        f"needs a {what or 'number'}",
                        file=self.file,
                        line=self.lines[i],
                        field=name,
                    )
                out[i] = np.nan
                continue
            try:
                v = float(text)
            except ValueError:
                raise InputError(
                    f"{text!r} is not a number; use a plain decimal number "
                    "(point as decimal separator)"
                    + (
                        " or leave the cell empty / write nan for a dropped frame"
                        if allow_missing
                        else ""
                    ),
                    file=self.file,
                    line=self.lines[i],
                    field=name,
                ) from None
            if not math.isfinite(v):
                raise InputError(
                    f"{text!r} is infinite; give a finite number"
                    + (" or nan for a dropped frame" if allow_missing else ""),
                    file=self.file,
                    line=self.lines[i],
                    field=name,
                )
            if nonneg and v < 0:
                raise InputError(
                    f"{v:g} is negative; {what or 'the value'} must be >= 0",
                    file=self.file,
                    line=self.lines[i],
                    field=name,
                )
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
        raise InputError(
            f"cannot be read as UTF-8 text ({err}); export the table as CSV",
            file=file,
            line=1,
            field="header",
        ) from None
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
            raise InputError(
                f"has {len(cells)} cells but the header has {len(header)} "
                f"({','.join(header)}); every row needs one cell per column",
                file=file,
                line=lineno,
                field="row",
            )
        rows.append(cells)
        lines.append(lineno)
    if header is None:
        raise InputError(
            f"the file is empty; the first line must name the columns (e.g. "
            f"{example}) and each following line holds one frame",
            file=file,
            line=1,
            field="header",
        )
    dup = sorted({h for h in header if header.count(h) > 1})
    if dup:
        raise InputError(
            f"column {dup[0]!r} appears twice; rename or remove one",
            file=file,
            line=header_line,
            field=dup[0],
        )
    if not rows:
        raise InputError(
            f"has a header ({','.join(header)}) but no data rows; one row per frame is needed",
            file=file,
            line=header_line + 1,
            field="rows",
        )
    return CsvTable(file, tuple(header), tuple(rows), tuple(lines))


def channel_column(
    table: CsvTable,
    channel: Channel,
    *,
    required: bool,
    choose: str | None = None,
    choose_hint: str = "",
) -> str | None:
    """The one column of `table` holding `channel` (``<name>_<unit>``), checked.

    A column named after the channel with an unknown unit suffix is an error (it is surely
    meant for this channel); several valid columns need `choose`.
    """
    found = []
    for col in table.header:
        if col == channel.name or col.startswith(channel.name + "_"):
            unit = col[len(channel.name) + 1 :]
            if unit not in channel.units:
                raise InputError(
                    f"{'no' if not unit else 'unknown'} unit suffix"
                    f"{'' if not unit else f' {unit!r}'}; {channel.description or channel.name}"
                    f" columns must be named one of {', '.join(channel.column_names())}",
                    file=table.file,
                    line=1,
                    field=col,
                )
            found.append(col)
    if choose is not None:
        if choose not in table.header:
            raise InputError(
                f"column {choose!r} (chosen by y_column) is not in the header "
                f"({','.join(table.header)})",
                file=table.file,
                line=1,
                field=choose,
            )
        return choose
    if len(found) > 1:
        raise InputError(
            f"several {channel.name} columns ({', '.join(found)}); say which to use{choose_hint}",
            file=table.file,
            line=1,
            field=found[0],
        )
    if not found:
        if required:
            raise InputError(
                f"missing column: no {channel.description or channel.name} column "
                f"in the header ({','.join(table.header)}); name it one of "
                f"{', '.join(channel.column_names())}",
                file=table.file,
                line=1,
                field=channel.column_names()[0],
            )
        return None
    return found[0]


def time_column(table: CsvTable) -> np.ndarray:
    """The `t_s` column (seconds, finite); other time spellings get a rename hint."""
    for col in table.header:
        if col != "t_s" and (col in ("t", "time") or re.fullmatch(r"(t|time)_\w+", col)):
            raise InputError(
                "wrong unit suffix: frame times must be seconds in a column "
                "named t_s (convert, e.g. ms / 1000, and rename the column)",
                file=table.file,
                line=1,
                field=col,
            )
    if "t_s" not in table.header:
        raise InputError(
            f"missing column: no t_s (frame time in seconds) in the header "
            f"({','.join(table.header)})",
            file=table.file,
            line=1,
            field="t_s",
        )
    return table.numbers("t_s", what="frame time in seconds")


def _check_increasing(table: CsvTable, t: np.ndarray) -> None:
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        kind = "repeats" if t[i] == t[i - 1] else "goes backwards from"
        raise InputError(
            f"{t[i]:g} s {kind} the previous row's {t[i - 1]:g} s; frame times "
            "must be strictly increasing (sort the rows, drop duplicates)",
            file=table.file,
            line=table.lines[i],
            field="t_s",
        )


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
    _check_increasing(table, t)
    col = channel_column(table, channel, required=True)
    unit = col[len(channel.name) + 1 :]
    v = table.numbers(col, nonneg=True, what=f"{channel.description or channel.name} in {unit}")
    end = t[-1] + (float(np.median(np.diff(t))) if t.size > 1 else 0.0)
    wave = from_samples(t, channel.to_si(v, unit), end_s=end, name=col)
    return wave, f"logged trace {Path(path).name} ({t.size} samples, {unit})"


def _check_log_against_description(
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
      [camera] settings and the fixed [experiment] settings applied.
    - `camera`: the [camera] values given, in SI ({"fps", "exposure_s", "m_per_px"}, each
      optional); `fixed`: {path: SI value} applied to every run.
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
    """`device.default_model()` with the given camera settings and fixed values applied.

    `camera` may hold "m_per_px" and "exposure_s" (SI); absent ones keep the device default.
    """
    from greybox.parameters import set_values

    model = device.default_model()
    cam = model.camera
    if camera.get("m_per_px") is not None or camera.get("exposure_s") is not None:
        new_cam = type(cam)(
            m_per_px=float(camera.get("m_per_px") or cam.m_per_px),
            exposure_s=float(
                cam.exposure_s if camera.get("exposure_s") is None else camera["exposure_s"]
            ),
            offset_m=cam.offset_m,
            drift_m_per_s=cam.drift_m_per_s,
            n_quadrature=cam.n_quadrature,
        )
        model = eqx.tree_at(lambda m: m.camera, model, new_cam)
    return set_values(model, list(fixed), [float(v) for v in fixed.values()])


def _settings(doc: _Toml, table, model, *path) -> dict:
    """{dotted path: SI value} from a TOML table, each path checked against the model."""
    from greybox.parameters import get_value

    if not isinstance(table, dict):
        raise doc.error(
            "must be a table of path = value (SI units), e.g. { initial_rise_K = 0.0 }", *path
        )
    out = {}
    for key, value in table.items():
        flat = _flatten(value, key) if isinstance(value, dict) else {key: value}
        for k, v in flat.items():
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise doc.error(f"{v!r} must be a finite number (SI units)", *path, key)
            try:
                get_value(model, k)
            except ValueError:
                raise doc.error(
                    f"{k!r} is not a parameter of the device model; see its "
                    "parameter table (PARAMETERS in models/<device>.py)",
                    *path,
                    key,
                ) from None
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
    """[fit] free: paths picked from the device's standard free parameters, or tables that
    define a free parameter (bounds, prior) in full. Absent: the standard list."""
    from greybox.parameters import get_value

    defaults = {p.path: p for p in device.default_free_parameters()}
    if entries is None:
        return tuple(defaults.values())
    if not isinstance(entries, list) or not entries:
        raise doc.error(
            "must be a non-empty list of parameter paths (or tables); leave it "
            "out for the device's standard fit",
            "fit",
            "free",
        )
    units = {p.path: p.unit for p in getattr(device, "PARAMETERS", ())}
    out, seen = [], set()
    for i, e in enumerate(entries):
        where = ("fit", "free", i)
        if isinstance(e, str):
            if e not in defaults:
                raise doc.error(
                    f"{e!r} is not one of {device.NAME}'s standard free "
                    f"parameters ({', '.join(defaults)}); to fit another "
                    "parameter give a table { path = ..., lower = ..., ... }",
                    *where,
                )
            fp, path = defaults[e], e
        elif isinstance(e, dict):
            doc.check_keys(e, _FREE_KEYS, *where)
            path = doc.string(e, "path", *where, required=True)
            try:
                get_value(model, path)
            except ValueError:
                known = ", ".join(sorted(units)) or "see models/<device>.py"
                raise doc.error(
                    f"{path!r} is not a parameter of {device.NAME}; known: {known}", *where, "path"
                ) from None
            unit = doc.string(
                e,
                "unit",
                *where,
                default=units.get(path, getattr(defaults.get(path), "unit", None)),
            )
            if unit is None:
                raise doc.error(
                    "missing; this path is not in the device's parameter table, "
                    'so give its SI unit (e.g. unit = "s")',
                    *where,
                    "unit",
                )
            per_run = e.get("per_run", False)
            if not isinstance(per_run, bool):
                raise doc.error(f"{per_run!r} must be true or false", *where, "per_run")
            kw = {
                k: doc.number(e, k, *where)
                for k in ("lower", "upper", "prior_median", "prior_log_sd", "initial")
            }
            scale = doc.number(e, "scale", *where, default=1.0, positive=True)
            try:
                fp = FreeParameter(path, unit=unit, per_experiment=per_run, scale=scale, **kw)
                if kw["initial"] is not None:
                    fp.check_value(kw["initial"])
            except ValueError as err:
                raise doc.error(str(err).split(": ", 1)[-1], *where, "path") from None
        else:
            raise doc.error(f"{e!r}: give a quoted parameter path or a table", *where)
        if path in seen:
            raise doc.error(f"{path!r} is listed twice", *where)
        if path in fixed:
            raise doc.error(
                f"{path!r} is also fixed in [experiment] settings; fit it or fix it", *where
            )
        seen.add(path)
        out.append(fp)
    return tuple(out)


def _camera(doc: _Toml, data: dict) -> dict:
    cam = doc.table(data, "camera", required=False)
    doc.check_keys(cam, _CAMERA_KEYS, "camera")
    fps = doc.number(cam, "fps", "camera", positive=True, unit="frames/s")
    exposure_ms = doc.number(
        cam, "exposure_ms", "camera", nonneg=True, unit="ms (0 = instantaneous)"
    )
    um_per_px = doc.number(cam, "um_per_px", "camera", positive=True, unit="um per pixel")
    if fps is not None and exposure_ms is not None and exposure_ms > 1e3 / fps * 1.0001:
        raise doc.error(
            f"{exposure_ms:g} ms is longer than one frame interval (1/fps = "
            f"{1e3 / fps:g} ms); check fps and exposure_ms",
            "camera",
            "exposure_ms",
        )
    return {
        "fps": fps,
        "exposure_s": None if exposure_ms is None else exposure_ms * 1e-3,
        "m_per_px": None if um_per_px is None else um_per_px * 1e-6,
    }


def _read_outputs(doc: _Toml, table: CsvTable, outputs, camera: dict, y_choice, run: str):
    """(readings (N, n_y) in SI, column names); px columns need [camera] um_per_px."""
    ys, cols = [], []
    for ch in outputs:
        col = channel_column(
            table,
            ch,
            required=True,
            choose=y_choice if len(outputs) == 1 else None,
            choose_hint=f' with y_column = "..." in run {run!r} of {doc.file}',
        )
        unit = col[len(ch.name) + 1 :]
        v = table.numbers(col, allow_missing=True, what=f"{ch.name} reading in {unit}")
        if not np.isfinite(v).any():
            raise InputError(
                f"every reading is empty or NaN ({v.size} rows); a run needs at "
                "least one tracked frame (check the tracker output)",
                file=table.file,
                line=table.lines[0],
                field=col,
            )
        if unit == PIXELS and camera["m_per_px"] is None:
            raise InputError(
                f"pixel readings need the image scale: add um_per_px to [camera] "
                f"in {doc.file} (or give {ch.name}_um)",
                file=table.file,
                line=1,
                field=col,
            )
        ys.append(ch.to_si(v, unit, camera["m_per_px"]))
        cols.append(col)
    return np.column_stack(ys), cols


def _check_frame_rate(
    doc: _Toml, table: CsvTable, t: np.ndarray, valid: np.ndarray, fps: float | None
) -> None:
    """Frame intervals must match [camera] fps within 3x (catches t_s written in ms)."""
    if fps is None or valid.sum() < 3:
        return
    interval = float(np.median(np.diff(t[valid])))
    expected = 1.0 / fps
    if not expected / 3 <= interval <= 3 * expected:
        hint = (
            " (t_s looks like milliseconds: divide by 1000)"
            if 300 * expected <= interval <= 3000 * expected
            else ""
        )
        raise InputError(
            f"median frame interval {interval:g} s does not match 1/fps = "
            f"{expected:g} s from [camera] fps in {doc.file}{hint}; t_s must be "
            "seconds and fps the camera's frame rate",
            file=table.file,
            line=table.lines[0],
            field="t_s",
        )


def _read_inputs(
    doc: _Toml,
    table: CsvTable,
    entry: dict,
    t: np.ndarray,
    inputs,
    camera: dict,
    path: tuple,
    csv_name: str,
):
    """(waveform in SI, text, source) from the run's `waveform` and/or logged columns."""
    desc = entry.get("waveform")
    if desc is not None and not isinstance(desc, dict):
        raise doc.error(
            'must be a table such as { type = "pulse_train", power_mW = 20, '
            'period_ms = 500, duty = 0.5, n_pulses = 10 } or { type = "logged" }',
            *path,
            "waveform",
        )
    kind = None if desc is None else desc.get("type")
    if desc is not None and kind not in WAVEFORM_TYPES:
        raise doc.error(
            f"{kind!r} is not a waveform type; use one of "
            f"{', '.join(repr(k) for k in WAVEFORM_TYPES)}",
            *path,
            "waveform",
            "type",
        )
    if kind == "logged" and len(desc) > 1:
        extra = next(k for k in desc if k != "type")
        raise doc.error(
            "a logged waveform takes no other keys (the levels come from the CSV)",
            *path,
            "waveform",
            extra,
        )
    logged = {}
    for ch in inputs:
        col = channel_column(table, ch, required=kind == "logged")
        if col is not None:
            unit = col[len(ch.name) + 1 :]
            v = table.numbers(
                col, nonneg=True, what=f"logged {ch.description or ch.name} in {unit}"
            )
            logged[ch.name] = (col, unit, ch.to_si(v, unit))
    if desc is None and len(logged) < len(inputs):
        names = " and ".join(ch.column_names()[0] for ch in inputs)
        raise doc.error(
            f'no input waveform: describe it (waveform = {{ type = "pulse_train", '
            f"power_mW = ..., period_ms = ..., duty = 0.5, n_pulses = ... }}) or log "
            f'it in {csv_name} ({names}) with waveform = {{ type = "logged" }}',
            *path,
            "waveform",
        )
    end = t[-1] + (float(np.median(np.diff(t))) if t.size > 1 else 0.0)
    if kind is None or kind == "logged":
        waves = [
            from_samples(t, logged[ch.name][2], end_s=end, name=logged[ch.name][0]) for ch in inputs
        ]
        text = (
            f"logged in {', '.join(logged[ch.name][0] for ch in inputs)} "
            f"({t.size} samples, each held until the next)"
        )
        wave = waves[0] if len(waves) == 1 else stack_channels(waves)
        return wave, text, "logged"
    if len(inputs) != 1:
        raise doc.error(
            f"a {kind} waveform describes one input, but {inputs[0].name}.. has "
            f"{len(inputs)} ({', '.join(c.name for c in inputs)}); log them in the "
            'CSV and use type = "logged"',
            *path,
            "waveform",
            "type",
        )
    ch = inputs[0]
    wave, text = waveform_from_description(desc, ch, doc.error, (*path, "waveform"))
    if ch.name not in logged:
        return wave, text, "described"
    col, unit, values = logged[ch.name]
    slack = max(
        1.0 / camera["fps"] if camera["fps"] else 0.0,
        camera["exposure_s"] or 0.0,
        float(np.median(np.diff(t))) if t.size > 1 else 0.0,
    )
    ref = f"{doc.file}:{doc.where.line(*path, 'waveform')}"
    _check_log_against_description(table, col, values, t, wave, ch, unit, slack, ref)
    return wave, text, "described (log checked)"


def _load_run(
    doc: _Toml, i: int, entry: dict, directory: Path, device, model, camera: dict, known_names: set
):
    path = ("runs", i)
    if not isinstance(entry, dict):
        raise doc.error("each run is a [[runs]] table", *path)
    doc.check_keys(entry, _RUN_KEYS, *path)
    name = doc.string(entry, "name", *path, required=True)
    if name in known_names:
        raise doc.error(f"run name {name!r} is used twice; names must be unique", *path, "name")
    if not re.fullmatch(r"[A-Za-z0-9_.\-]+", name):
        raise doc.error(
            f"{name!r}: use letters, digits, '_', '-' or '.' only (it names figure files)",
            *path,
            "name",
        )
    role = doc.string(entry, "role", *path, required=True, choices=ROLES)
    rel = doc.string(entry, "file", *path, required=True)
    csv_path = directory / rel
    if not csv_path.is_file():
        raise doc.error(
            f"{csv_path} does not exist; put the run's CSV there or fix the "
            "file name (relative to the experiment folder)",
            *path,
            "file",
        )
    t_start = doc.number(entry, "t_start_s", *path, default=0.0)
    settings = _settings(doc, entry.get("settings", {}), model, *path, "settings")
    y_choice = doc.string(entry, "y_column", *path)

    table = read_csv(csv_path)
    t = time_column(table)
    _check_increasing(table, t)
    y, y_cols = _read_outputs(doc, table, device.OUTPUTS, camera, y_choice, name)
    valid = np.all(np.isfinite(y), axis=1)
    _check_frame_rate(doc, table, t, valid, camera["fps"])
    wave, text, source = _read_inputs(
        doc, table, entry, t, tuple(device.INPUTS), camera, path, csv_path.name
    )
    try:
        exp = Experiment(
            name,
            t,
            y if y.shape[1] > 1 else y[:, 0],
            wave,
            t_start_s=t_start,
            role=role,
            settings=settings,
        )
    except ValueError as err:
        raise InputError(str(err), file=table.file) from None
    info = RunInfo(
        name, role, str(csv_path), ",".join(y_cols), t.size, int(valid.sum()), text, source
    )
    return exp, info


def _initial_offset(free: tuple, estimation: tuple) -> tuple:
    """Start per-run camera offsets at the median rest reading of the estimation runs.

    The fitter starts every run's offset from one value; a camera reading is the image
    position (hundreds of um), so starting from 0 puts the fit far from the data (it then
    fails). A run's rest reading is `Experiment.rest_level` (the median before the input
    first switches on), or the median of all its frames if fewer than three come before.
    """
    if not any(
        p.path == "camera.offset_m" and p.per_experiment and p.initial is None for p in free
    ):
        return free
    rest = []
    for e in estimation:
        level = e.rest_level()[0]
        rest.append(level if np.isfinite(level) else np.nanmedian(e.y[:, 0]))
    start = float(np.median(rest))
    return tuple(
        dataclasses.replace(p, initial=start)
        if p.path == "camera.offset_m" and p.per_experiment and p.initial is None
        else p
        for p in free
    )


def load_experiment_set(directory) -> ExperimentSet:
    """Load and check an experiment folder (``experiment.toml`` + run CSVs).

    Raises `InputError` (``file:line: field: problem and fix``) for the first problem.
    """
    import models
    from greybox.fit import LOSSES
    from greybox.simulate import METHODS

    directory = Path(directory)
    if not directory.is_dir():
        raise InputError(
            f"{directory} is not a folder; give the experiment folder that holds {TOML_NAME}",
            file=str(directory),
            field="EXPERIMENT_DIR",
        )
    doc = _Toml(directory / TOML_NAME)
    data = doc.data
    doc.check_keys(data, _TOP_KEYS)
    exp = doc.table(data, "experiment")
    doc.check_keys(exp, _EXPERIMENT_KEYS, "experiment")
    device_name = doc.string(exp, "device", "experiment", required=True)
    try:
        device = models.load(device_name)
    except ValueError:
        raise doc.error(
            f"unknown device model {device_name!r}; known: "
            f"{', '.join(models.available())} (a module in models/)",
            "experiment",
            "device",
        ) from None
    description = doc.string(exp, "description", "experiment", default="")
    camera = _camera(doc, data)
    base = configure_model(device, camera, {})
    fixed = _settings(doc, exp.get("settings", {}), base, "experiment", "settings")
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
    if (
        fit_options["method"] == "zoh"
        and not model.is_linear
        and not isinstance(model, AbstractSteppedDevice)
    ):
        raise doc.error(
            "the exact 'zoh' path needs a linear device; use method = \"adaptive\"", "fit", "method"
        )
    free = _free_parameters(doc, fitopt.get("free"), device, model, fixed)

    runs = data.get("runs")
    if not isinstance(runs, list) or not runs:
        raise doc.error(
            "no runs; add one [[runs]] table per CSV (name, file, role, waveform)", "runs"
        )
    experiments, infos, names = [], [], set()
    for i, entry in enumerate(runs):
        e, info = _load_run(doc, i, entry, directory, device, model, camera, names)
        names.add(e.name)
        experiments.append(e)
        infos.append(info)
    estimation = tuple(e for e in experiments if e.role == "estimation")
    validation = tuple(e for e in experiments if e.role == "validation")
    if not estimation or sum(int(e.mask.all(axis=1).sum()) for e in estimation) == 0:
        raise doc.error(
            "the estimation set has zero frames: no run has role = "
            '"estimation" (with tracked frames); mark at least one run for '
            "estimation",
            "runs",
            0,
            "role",
        )
    free = _initial_offset(free, estimation)
    return ExperimentSet(
        name=directory.resolve().name,
        directory=directory,
        description=description,
        device_name=device_name,
        device=device,
        model=model,
        camera=camera,
        fixed=fixed,
        estimation=estimation,
        validation=validation,
        runs=tuple(infos),
        free=free,
        fit_options=fit_options,
    )
