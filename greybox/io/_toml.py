"""TOML descriptions with located errors: ``file:line: field: what is wrong and how to fix it``.

tomllib returns values only; `TomlLines` maps key paths back to the lines that define them so
every message about a description can point at its line.
"""

from __future__ import annotations

import math
import re
import tomllib
from pathlib import Path

from greybox._model.errors import InputError


def excerpt(value, limit: int = 40) -> str:
    """A short, escaped quotation of file content for an error message (never the whole)."""
    text = value if isinstance(value, str) else repr(value)
    out = repr(text[:limit]) if isinstance(value, str) else text[:limit]
    return out + (f"... ({len(text)} characters)" if len(text) > limit else "")


TOML_NAME = "experiment.toml"
MAX_TOML_BYTES = 4 * 2**20  # an experiment description is a few kB


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
        if isinstance(p, str) and (len(p) > 60 or not p.isprintable()):
            p = excerpt(p, 40)  # a key from the file: quote it short and escaped
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out


MAX_ABS_NUMBER = 1e300  # larger values overflow as soon as they are squared or summed


def non_finite(value) -> str | None:
    """What is wrong with a number that is NaN, infinite or beyond `MAX_ABS_NUMBER` (named
    as what it is: "nan is not finite", not "inf"), or None for a usable number."""
    if isinstance(value, int) and not isinstance(value, bool):
        if abs(value) < MAX_ABS_NUMBER:
            return None
        return f"{excerpt(value)} is too large (|value| >= {MAX_ABS_NUMBER:g}); give a smaller one"
    value = float(value)
    if math.isnan(value):
        return "nan is not finite; give a number"
    if math.isinf(value):
        return f"{'-' if value < 0 else ''}inf is not finite; give a finite number"
    if abs(value) >= MAX_ABS_NUMBER:
        return f"{value:g} is too large (|value| >= {MAX_ABS_NUMBER:g}); give a finite number"
    return None


class TomlDocument:
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
            size = path.stat().st_size
            if size > MAX_TOML_BYTES:
                raise InputError(
                    f"{size / 2**20:.1f} MB; an experiment description is a few kB "
                    "(the data belong in the run CSVs)",
                    file=self.file,
                    field=TOML_NAME,
                )
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
        except RecursionError:
            raise InputError(
                "nested too deeply (arrays or inline tables inside each other); an "
                "experiment description nests a few levels at most",
                file=self.file,
                field="TOML syntax",
            ) from None
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
            what = excerpt(re.sub(r"\s*\(at line \d+, column \d+\)", "", msg), 100)
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
            raise self.error(
                f"{excerpt(value)} is not a number; write it without quotes", *path, key
            )
        problem = non_finite(value)
        if problem:
            raise self.error(problem, *path, key)
        value = float(value)
        if positive and not value > 0:
            raise self.error(f"{value:g} must be > 0{f' {unit}' if unit else ''}", *path, key)
        if nonneg and not value >= 0:
            raise self.error(f"{value:g} must be >= 0{f' {unit}' if unit else ''}", *path, key)
        return value

    def integer(
        self, table: dict, key: str, *path, default=None, minimum: int = 1, maximum=None
    ):
        if key not in table:
            return default
        value = table[key]
        if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
            raise self.error(f"{excerpt(value)} must be a whole number >= {minimum}", *path, key)
        if maximum is not None and value > maximum:
            raise self.error(f"{excerpt(value)} is above the largest allowed, {maximum}", *path,
                             key)  # fmt: skip
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
            raise self.error(f"{excerpt(value)} must be a non-empty quoted string", *path, key)
        if choices is not None and value not in choices:
            raise self.error(
                f"{excerpt(value)} is not one of {', '.join(map(repr, choices))}", *path, key
            )
        return value
