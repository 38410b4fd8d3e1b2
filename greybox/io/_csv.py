"""Run CSVs: numeric columns with file line numbers, unit-suffixed columns, the time column.

The reader is vectorised: an all-numeric table (the usual run log) is parsed by numpy array
operations on its bytes (greybox/io/_csv_numbers.py; `np.loadtxt` when its cells are unusual,
e.g. many nan or 17-digit cells), with the file line of every row computed from the newline
positions, so 300,000 rows take a few times what pandas takes and the memory is linear in
the numbers. Anything else (quoted cells, a text column, a row with a cell too many) goes
through the `csv` module, which locates the problem; a column that is not all numbers is
kept as text and only raises (with its file line) when a signal is read from it.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import math
import re
import warnings
from pathlib import Path

import numpy as np

from greybox._model.channels import Channel
from greybox._model.errors import InputError
from greybox.io._csv_numbers import parse_cells
from greybox.io._toml import excerpt

MAX_CSV_BYTES = 256 * 2**20  # a run CSV larger than this is refused before it is read
MAX_LINE_CHARS = 10_000  # per line: a frame row is a few numbers
MAX_COLUMNS = 256
MAX_ROWS = 2_000_000  # frames per file

#: the cell separators a run CSV may use (European lab exports often use ';', loggers tab)
DELIMITERS = {",": "comma", ";": "semicolon", "\t": "tab"}
_MISSING = ("", "nan", "na")
# line breaks other than \n and \r\n (str.splitlines counts them): such a file is read by the
# csv module, so that line numbers stay those of an editor
_ODD_BREAKS = ("\x0b", "\x0c", "\x1c", "\x1d", "\x1e", "\x85", "\u2028", "\u2029")


def delimiter_name(delimiter: str) -> str:
    return f"{DELIMITERS.get(delimiter, 'custom')} ({delimiter!r})"


# --------------------------------------------------------------------------------------
# CSV tables


@dataclasses.dataclass(frozen=True, eq=False)
class CsvTable:
    """A CSV file as numbers: `header`, `values` (rows x columns, NaN for an empty or nan
    cell and for every cell of a text column), each row's file line (`lines`) and the
    `delimiter` it was split at. `text_columns` holds the cells of a column with a cell that
    is not a number: reading it as numbers raises at that cell's line."""

    file: str
    header: tuple
    values: np.ndarray
    lines: np.ndarray
    header_line: int = 1  # the header's file line (1 for a header-less file: names declared)
    delimiter: str = ","
    text_columns: dict = dataclasses.field(default_factory=dict)
    source: str = dataclasses.field(default="", repr=False)  # the text, to quote a cell

    @property
    def n_rows(self) -> int:
        return int(self.values.shape[0])

    def cell(self, i: int, name: str) -> str:
        """The text of row `i`'s cell in column `name` (for messages)."""
        if name in self.text_columns:
            return self.text_columns[name][i]
        if not self.source:  # a table built from arrays (a DataFrame): the number itself
            v = self.values[i, self.header.index(name)]
            return "" if np.isnan(v) else repr(float(v))
        line = self.source.splitlines()[int(self.lines[i]) - 1]
        cells = next(csv.reader([line], delimiter=self.delimiter, strict=False))
        j = self.header.index(name)
        return cells[j].strip() if j < len(cells) else ""

    def numbers(
        self, name: str, *, allow_missing: bool = False, nonneg: bool = False, what: str = ""
    ) -> np.ndarray:
        """Column `name` as floats; empty/nan cells are NaN only if `allow_missing`."""
        if name in self.text_columns:
            return self._text_numbers(name, allow_missing, nonneg, what)
        v = self.values[:, self.header.index(name)].copy()
        bad = np.isinf(v) | (np.isnan(v) if not allow_missing else False)
        if nonneg:
            bad |= v < 0
        if bad.any():
            i = int(np.argmax(bad))
            self._check_cell(name, i, self.cell(i, name), allow_missing, nonneg, what)
        return v

    def _text_numbers(self, name, allow_missing, nonneg, what) -> np.ndarray:
        cells = self.text_columns[name]
        out = np.empty(len(cells))
        for i, cell in enumerate(cells):
            out[i] = self._check_cell(name, i, cell, allow_missing, nonneg, what)
        return out

    def _check_cell(self, name, i, text, allow_missing, nonneg, what) -> float:
        """The number in one cell, or the located error that says why it is not one."""
        line = int(self.lines[i])
        text = text.strip()
        if text.lower() in _MISSING:
            if not allow_missing:
                raise InputError(
                    f"cell is {'empty' if not text else excerpt(text)}; every row "
                    f"needs a {what or 'number'}",
                    file=self.file,
                    line=line,
                    field=name,
                )
            return np.nan
        try:
            v = float(text)
        except ValueError:
            comma = (
                " (a decimal comma? then the cells must be split at ';': declare "
                '[csv] delimiter = ";")'
                if "," in text and self.delimiter != ","
                else ""
            )
            raise InputError(
                f"{excerpt(text)} is not a number; use a plain decimal number "
                f"(point as decimal separator){comma}"
                + (
                    " or leave the cell empty / write nan for a dropped frame"
                    if allow_missing
                    else ""
                ),
                file=self.file,
                line=line,
                field=name,
            ) from None
        if not math.isfinite(v):
            raise InputError(
                f"{excerpt(text)} is infinite; give a finite number"
                + (" or nan for a dropped frame" if allow_missing else ""),
                file=self.file,
                line=line,
                field=name,
            )
        if nonneg and v < 0:
            raise InputError(
                f"{v:g} is negative; {what or 'the value'} must be >= 0",
                file=self.file,
                line=line,
                field=name,
            )
        return v


def _read_text(path: Path, file: str) -> str:
    if not path.is_file():
        raise InputError("no such file", file=file)
    try:
        size = path.stat().st_size
        if size > MAX_CSV_BYTES:
            raise InputError(
                f"{size / 2**20:.0f} MB is more than the {MAX_CSV_BYTES / 2**20:.0f} MB a run "
                "CSV may hold; decimate the frames or split the run into several files",
                file=file,
                field="file",
            )
        return path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(
            f"cannot be read as UTF-8 text ({err}); export the table as CSV",
            file=file,
            line=1,
            field="header",
        ) from None


def _check_line_lengths(text: str, file: str) -> tuple:
    """(the text's UTF-8 bytes, the positions of its newlines), once no line is too long."""
    raw = np.frombuffer(text.encode("utf-8", "surrogatepass"), np.uint8)
    breaks = np.flatnonzero(raw == 10)
    if np.diff(np.r_[-1, breaks, raw.size]).max(initial=0) - 1 <= MAX_LINE_CHARS:
        return raw, breaks  # bytes >= characters: no line is too long
    for lineno, line in enumerate(text.splitlines(), 1):
        if len(line) > MAX_LINE_CHARS:
            raise InputError(
                f"is {len(line)} characters long (at most {MAX_LINE_CHARS}; it starts "
                f"{excerpt(line)}); a row holds one frame's numbers: check the delimiter "
                "and the line endings",
                file=file,
                line=lineno,
                field="row",
            )


def _first_line(text: str) -> tuple:
    """(line number, text) of the first line that is neither blank nor a '#' comment."""
    start = 0
    for lineno in range(1, MAX_ROWS + 1):  # line by line: never the whole file split
        end = text.find("\n", start)
        line = (text[start:] if end < 0 else text[start:end]).splitlines()
        if line and line[0].strip() and not line[0].lstrip().startswith("#"):
            return lineno, line[0]
        if end < 0:
            break
        start = end + 1
    return 0, ""


def choose_delimiter(line: str, declared: str | None, file: str, lineno: int) -> str:
    """The delimiter `declared` (checked against the first line) or the one seen there."""
    counts = {d: line.count(d) for d in DELIMITERS}
    seen = max(DELIMITERS, key=lambda d: counts[d])  # ties: the first (comma)
    if declared is not None:
        if counts.get(declared, line.count(declared)) == 0 and counts[seen] > 0:
            raise InputError(
                f"the declared delimiter {delimiter_name(declared)} does not occur in "
                f"this line, which is split by {delimiter_name(seen)} ({excerpt(line, 60)}); "
                f'declare [csv] delimiter = "{seen}" in experiment.toml, or drop the '
                "declaration (the delimiter is then detected)",
                file=file,
                line=lineno,
                field="delimiter",
            )
        return declared
    return seen if counts[seen] else ","


def _header_cells(line: str, delimiter: str) -> list:
    return [c.strip() for c in next(csv.reader([line], delimiter=delimiter, strict=False))]


def _fast_values(body: str, raw, breaks, delimiter: str, n_columns: int, first_line: int):
    """(values, lines) of an all-numeric body (its text, UTF-8 bytes and newline positions)
    parsed by numpy, or None when the body needs the csv module (quotes, text cells, ragged
    rows)."""
    if '"' in body or raw.size == 0:
        return None
    starts = np.r_[0, breaks + 1]
    ends = np.r_[breaks, raw.size]
    ends = np.where((ends > starts) & (raw[np.maximum(ends - 1, 0)] == 13), ends - 1, ends)
    nonblank = ends > starts
    first = np.where(nonblank, raw[np.minimum(starts, max(raw.size - 1, 0))], 0)
    if np.isin(first[nonblank], (32, 9)).any():
        return None  # an indented line (blank or not): the csv module decides
    comment = first == 35
    if np.count_nonzero(raw == 35) != np.count_nonzero(comment):
        return None  # a '#' inside a row
    rows = nonblank & ~comment
    n = int(np.count_nonzero(rows))
    if n == 0 or n > MAX_ROWS or n_columns > MAX_COLUMNS:
        return None
    lines = np.flatnonzero(rows) + first_line
    # the rows' bytes only (no blank or comment line, no "\r"), parsed by array operations
    keep = np.repeat(rows, np.diff(starts, append=raw.size))
    if ends.size and (raw[ends[ends < raw.size]] == 13).any():
        keep &= raw != 13
    values = parse_cells(raw if keep.all() else raw[keep], delimiter, n_columns)
    if values is not None and values.shape == (n, n_columns):
        return values, lines
    # cells numpy's own parser reads (many nan or inf, 17 digits, spaces)
    empty = (delimiter * 2, delimiter + "\n", delimiter + "\r", "\n" + delimiter)
    if any(e in body for e in empty) or body.startswith(delimiter) or body.endswith(delimiter):
        body = _fill_empty_cells(body, delimiter)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            values = np.loadtxt(
                io.StringIO(body),
                delimiter=delimiter,
                comments="#",
                ndmin=2,
                dtype=float,
                quotechar=None,
                encoding=None,
            )
    except (ValueError, UserWarning):
        return None
    if values.shape != (n, n_columns):
        return None
    return values, lines


def _fill_empty_cells(body: str, d: str) -> str:
    """`body` with every empty cell written as nan (numpy reads it as NaN); plain string
    replacements (C speed), twice for runs of empty cells."""
    for _ in range(2):  # ",,," -> ",nan,," -> ",nan,nan,"
        body = body.replace(d + d, d + "nan" + d)
    body = body.replace(d + "\r\n", d + "nan\r\n").replace(d + "\n", d + "nan\n")
    body = body.replace("\n" + d, "\nnan" + d)
    if body.startswith(d):
        body = "nan" + body
    if body.endswith(d):
        body += "nan"
    return body


def read_csv(
    path, *, example: str = "t_s,y_px", names=None, delimiter: str | None = None
) -> CsvTable:
    """Read a CSV with a header row (line 1, or the first line not starting with '#').

    Lines starting with '#' and blank lines are skipped; every row must have as many cells as
    the header. `names`: the column names of a header-less file (every line is a row; a
    MATLAB ``csvwrite`` log). `delimiter`: ',', ';' or tab as declared (``[csv] delimiter``);
    None detects it from the first line (the one of the three it holds most of).
    """
    path = Path(path)
    file = str(path)
    text = _read_text(path, file)
    raw, breaks = _check_line_lengths(text, file)
    lineno, line = _first_line(text)
    delimiter = choose_delimiter(line, delimiter, file, lineno or 1)
    fast = None
    # every "\r" part of a "\r\n" ("in" first: a scan, where counting takes ten times as long)
    crlf_only = "\r" not in text or text.count("\r") == text.count("\r\n")
    plain_breaks = crlf_only and not any(
        b in text for b in _ODD_BREAKS
    )
    if names is None and lineno > 0 and plain_breaks:
        header = _header_cells(line, delimiter)
        body_start = 0
        for _ in range(lineno):  # the offset of the line after the header
            body_start = text.find("\n", body_start) + 1
        if body_start > 0 and len(set(header)) == len(header) and not _numeric_row(header):
            skip = int(breaks[lineno - 1]) + 1  # the body's first byte
            fast = _fast_values(
                text[body_start:], raw[skip:], breaks[lineno:] - skip, delimiter,
                len(header), lineno + 1,
            )
    if fast is not None:
        return CsvTable(
            file, tuple(header), fast[0], fast[1], lineno, delimiter, {}, source=text
        )
    return _read_with_csv_module(text, file, example, names, delimiter)


def _read_with_csv_module(text, file, example, names, delimiter) -> CsvTable:
    header, rows, lines = None, [], []
    header_line = 1
    if names is not None:
        header = [str(n).strip() for n in names]
    reader = csv.reader(text.splitlines(), strict=False, delimiter=delimiter)
    previous = 0
    while True:
        try:
            cells = next(reader)
        except StopIteration:
            break
        except csv.Error as err:
            raise InputError(
                f"is not a well-formed CSV row ({excerpt(str(err), 80)}); check quotes and "
                f"delimiters (numbers split at {delimiter_name(delimiter)})",
                file=file,
                line=reader.line_num,
                field="row",
            ) from None
        lineno = reader.line_num
        if lineno != previous + 1:
            raise InputError(
                f"a quoted cell runs over lines {previous + 1}-{lineno}; each row must be "
                "one line (check the quotes)",
                file=file,
                line=previous + 1,
                field="row",
            )
        previous = lineno
        if not cells or all(not c.strip() for c in cells) or cells[0].lstrip().startswith("#"):
            continue
        if len(cells) > MAX_COLUMNS:
            raise InputError(
                f"has {len(cells)} columns; at most {MAX_COLUMNS} (a run CSV holds t_s, the "
                "readings and optionally the logged input)",
                file=file,
                line=lineno,
                field="row",
            )
        cells = [c.strip() for c in cells]
        if header is None:
            header = cells
            header_line = lineno
            continue
        if len(rows) >= MAX_ROWS:
            raise InputError(
                f"more than {MAX_ROWS} frames; decimate (keep every k-th frame) or split "
                "the run into several files",
                file=file,
                line=lineno,
                field="rows",
            )
        if len(cells) != len(header):
            raise InputError(
                f"has {len(cells)} cells but the header has {len(header)} "
                f"({_header_text(header)}; cells split at {delimiter_name(delimiter)}); "
                "every row needs one cell per column"
                + (" (the header-less file's names come from experiment.toml)" if names else ""),
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
    if names is None and _numeric_row(header):
        raise InputError(
            f"the first line holds numbers ({_header_text(header)}), not column names: the "
            f"file has no header row. Add one (e.g. {example}) or, for a run CSV, declare "
            '[data] header = false and columns = ["t_s", ...] (in file order) in '
            "experiment.toml",
            file=file,
            line=header_line,
            field="header",
        )
    seen: set = set()
    for h in header:  # linear: a set, not header.count per column
        if h in seen:
            raise InputError(
                f"column {excerpt(h)} appears twice; rename or remove one",
                file=file,
                line=header_line,
                field=h if len(h) <= 40 and h.isprintable() else excerpt(h, 40),
            )
        seen.add(h)
    if not rows:
        raise InputError(
            f"has a header ({_header_text(header)}) but no data rows; one row per frame is needed",
            file=file,
            line=header_line + 1,
            field="rows",
        )
    if names is not None and rows and not _numeric_row(rows[0]):
        raise InputError(
            f"starts with a non-numeric row ({_header_text(rows[0])}) but experiment.toml "
            "declares the file header-less (header = false); drop header = false and "
            "columns = [...], or remove the header line",
            file=file,
            line=lines[0],
            field="header",
        )
    values = np.full((len(rows), len(header)), np.nan)
    text_columns = {}
    for j, name in enumerate(header):
        cells = [r[j] for r in rows]
        try:
            values[:, j] = np.array(
                ["nan" if c.lower() in _MISSING else c for c in cells], dtype=float
            )
        except ValueError:
            text_columns[name] = tuple(cells)
    return CsvTable(
        file,
        tuple(header),
        values,
        np.asarray(lines),
        header_line,
        delimiter,
        text_columns,
        source=text,
    )


def _numeric_row(cells) -> bool:
    for c in cells:
        try:
            float(c)
        except ValueError:
            if c.strip().lower() not in _MISSING:
                return False
    return any(c.strip().lower() not in _MISSING for c in cells)


def _header_text(header) -> str:
    text = ",".join(header)
    return text if len(text) <= 120 else excerpt(text, 120)


@dataclasses.dataclass(frozen=True)
class ColumnRef:
    """Where one signal is in a run's table: the header `column`, its `unit` as written and
    the conversion to SI (`conv`: (scale, offset), None for pixels); `mapped` names the TOML
    mapping that chose it (for messages), or is empty when the column name said it."""

    column: str
    unit: str
    conv: tuple | None
    mapped: str = ""


_BRACKET_UNIT = re.compile(r"^(.*?)\s*[\[(]\s*([^\])]+?)\s*[\])]\s*$")


def unit_in_name(col: str) -> str | None:
    """The unit written in a column name: ``T1 [degC]``, ``Time (sec)``; None if none."""
    m = _BRACKET_UNIT.match(col)
    return m.group(2) if m else None


def _field(col: str) -> str:
    return col if len(col) <= 40 and col.isprintable() else excerpt(col, 40)


def _unit_error(table, channel, col, unit, problem, mapped):
    from greybox.io._units import unit_examples

    examples = unit_examples(channel)
    names = ", ".join(f"{channel.name}_{u}" for u in examples)
    quoted = ", ".join('"' + u + '"' for u in examples)
    # the unit the file's numbers are in (degC for Celsius readings), never simply the SI
    # unit: `unit = "K"` on Celsius data would load 21 degC as 21 K
    fix = (
        f"give the unit the column's numbers are in, in the mapping ({mapped}), e.g. "
        f'unit = "{examples[0]}" (one of {quoted}: the unit '
        f"of the numbers as logged; greybox converts them to {channel.si_unit or 'a level'})"
        if mapped
        else f"{channel.description or channel.name} columns must be named one of {names} "
        f"(or map the column in experiment.toml: [columns] {channel.name} = "
        f'{{ column = "...", unit = "..." }})'
    )
    return InputError(
        f"{'no unit' if not unit else problem}; {fix}",
        file=table.file,
        line=table.header_line,
        field=_field(col),
    )


def _mapped_column(table: CsvTable, mapped: tuple, target: str) -> tuple:
    """(column, unit or None) of an experiment.toml mapping to `target` (a channel or time),
    the column checked against the header; the unit defaults to one in brackets in its name."""
    col, unit, where = mapped
    if col not in table.header:
        raise InputError(
            f"column {excerpt(col)} (mapped to {target} in {where}) is not in the header "
            f"({_header_text(table.header)}); fix the mapping or the header",
            file=table.file,
            line=table.header_line,
            field=target,
        )
    return col, unit if unit is not None else unit_in_name(col)


def find_column(
    table: CsvTable,
    channel: Channel,
    *,
    required: bool,
    mapped: tuple | None = None,
    choose: str | None = None,
    choose_hint: str = "",
) -> ColumnRef | None:
    """The one column of `table` holding `channel`, with its unit checked (pint).

    `mapped`: (column, unit or None, where) from an experiment.toml ``columns`` mapping; the
    unit defaults to one written in the name (``T1 [degC]``). Otherwise the column is
    ``<name>_<unit>``: a column named after the channel with an unknown unit suffix is an
    error (it is surely meant for this channel); several valid columns need `choose`.
    """
    from greybox.io._units import channel_conversion

    if mapped is not None:
        col, unit = _mapped_column(table, mapped, channel.name)
        where = mapped[2]
        if unit is None and col.startswith(channel.name + "_"):
            unit = col[len(channel.name) + 1 :]
        if unit is None and channel.si_unit in ("%", "1", ""):
            unit = next(iter(channel.units), channel.si_unit)  # a level: no unit to guess
        if unit is None:
            raise _unit_error(table, channel, col, None, "", where)
        try:
            conv = channel_conversion(channel, unit)
        except ValueError as err:
            raise _unit_error(table, channel, col, unit, str(err), where) from None
        return ColumnRef(col, unit, conv, where)
    found = []
    for col in table.header:
        if col == channel.name or col.startswith(channel.name + "_"):
            unit = col[len(channel.name) + 1 :]
            if not unit:
                raise _unit_error(table, channel, col, unit, "", "")
            try:
                conv = channel_conversion(channel, unit)
            except ValueError as err:
                raise _unit_error(
                    table, channel, col, unit, f"unknown unit suffix {unit!r} ({err})", ""
                ) from None
            found.append(ColumnRef(col, unit, conv))
    if choose is not None:
        hit = next((r for r in found if r.column == choose), None)
        if hit is None:
            raise InputError(
                f"column {choose!r} (chosen by y_column) is not a {channel.name} column of "
                f"the header ({_header_text(table.header)})",
                file=table.file,
                line=table.header_line,
                field=_field(choose),
            )
        return hit
    if len(found) > 1:
        raise InputError(
            f"several {channel.name} columns ({', '.join(r.column for r in found)}); say "
            f"which to use{choose_hint}",
            file=table.file,
            line=table.header_line,
            field=found[0].column,
        )
    if not found:
        if required:
            raise InputError(
                f"missing column: no {channel.description or channel.name} column "
                f"in the header ({_header_text(table.header)}); name it one of "
                f"{', '.join(channel.column_names())} or map a column to {channel.name} "
                "in experiment.toml ([columns], see experiments/README.md)",
                file=table.file,
                line=table.header_line,
                field=channel.column_names()[0],
            )
        return None
    return found[0]


def time_column(table: CsvTable, mapped: tuple | None = None) -> tuple:
    """(times in s, ColumnRef): ``t_<unit>`` (``t_s``, ``t_ms``) or the mapped time column."""
    from greybox.io._units import time_conversion

    ref = None
    if mapped is not None:
        col, unit = _mapped_column(table, mapped, "time")
        where = mapped[2]
        if unit is None and re.fullmatch(r"(t|time)_\w+", col):
            unit = col.split("_", 1)[1]
        if unit is None:
            unit = "s"  # a mapped time column without a unit is in seconds (documented)
        if unit is None:
            raise InputError(
                f"no time unit; give it in the mapping ({where}), e.g. time = "
                f'{{ column = {col!r}, unit = "s" }}',
                file=table.file,
                line=table.header_line,
                field=_field(col),
            )
        ref = ColumnRef(col, unit, None, where)
    else:
        for col in table.header:
            m = re.fullmatch(r"(?:t|time)(?:_(\w+))?", col)
            if m:
                if ref is not None:
                    raise InputError(
                        f"several time columns ({ref.column}, {col}); keep one or map one "
                        'with [columns] time = "..."',
                        file=table.file,
                        line=table.header_line,
                        field=col,
                    )
                ref = ColumnRef(col, m.group(1) or "", None)
        if ref is None:
            raise InputError(
                f"missing column: no t_s (frame time in seconds) in the header "
                f"({_header_text(table.header)}); name it t_s (or t_ms) or map the time "
                'column in experiment.toml: [columns] time = { column = "Time", unit = "s" }',
                file=table.file,
                line=table.header_line,
                field="t_s",
            )
    try:
        if not ref.unit:
            raise ValueError("no unit")
        scale = time_conversion(ref.unit)
    except ValueError as err:
        raise InputError(
            f"wrong unit suffix ({err}): frame times must be in a unit of time, e.g. a "
            "column named t_s (seconds) or t_ms, or map it with a unit in experiment.toml",
            file=table.file,
            line=table.header_line,
            field=_field(ref.column),
        ) from None
    t = table.numbers(ref.column, what="frame time") * scale
    return t, dataclasses.replace(ref, conv=(scale, 0.0))


def check_increasing(table: CsvTable, t: np.ndarray, column: str = "t_s") -> None:
    """Frame times strictly increasing; the error names the file's own time `column`."""
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        kind = "repeats" if t[i] == t[i - 1] else "goes backwards from"
        hint = (
            " (a logger that writes its first time stamp twice: delete line "
            f"{int(table.lines[0])}, the first reading, or give it its own time)"
            if i == 1 and t[1] == t[0]
            else " (sort the rows, drop duplicates)"
        )
        raise InputError(
            f"{t[i]:g} s {kind} the previous row's {t[i - 1]:g} s; the times in column "
            f"{column!r} must be strictly increasing{hint}",
            file=table.file,
            line=int(table.lines[i]),
            field=_field(column),
        )


def channel_numbers(
    table: CsvTable,
    channel: Channel,
    ref: ColumnRef,
    *,
    what: str,
    allow_missing: bool = False,
    m_per_px: float | None = None,
) -> np.ndarray:
    """Column `ref` in SI, checked against the channel's range (a laser power is >= 0, a
    heater level 0-100 %); the error points at the first offending line."""
    from greybox.io._units import to_si

    values = to_si(
        table.numbers(ref.column, what=what, allow_missing=allow_missing), ref.conv, m_per_px
    )
    if channel.check_range(values) is not None:
        lo = -np.inf if channel.minimum is None else channel.minimum
        hi = np.inf if channel.maximum is None else channel.maximum
        i = int(np.argmax((values < lo) | (values > hi)))
        raise InputError(
            f"{channel.check_range(values[i : i + 1])}: {what} must lie within the "
            f"{channel.name} channel's range",
            file=table.file,
            line=table.lines[i],
            field=_field(ref.column),
        )
    return values
