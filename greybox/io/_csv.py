"""Run CSVs: text cells with file line numbers, unit-suffixed columns, the time column."""

from __future__ import annotations

import csv
import dataclasses
import math
import re
from pathlib import Path

import numpy as np

from greybox._channels import Channel
from greybox._errors import InputError

MAX_CSV_BYTES = 256 * 2**20  # a run CSV larger than this is refused before it is read
MAX_LINE_CHARS = 10_000  # per line: a frame row is a few numbers
MAX_COLUMNS = 256
MAX_ROWS = 2_000_000  # frames per file


def excerpt(text: str, limit: int = 40) -> str:
    """A short, escaped quotation of file content for an error message (never the whole)."""
    text = str(text)
    short = text[:limit]
    return repr(short) + (f"... ({len(text)} characters)" if len(text) > limit else "")


# --------------------------------------------------------------------------------------
# CSV tables


@dataclasses.dataclass(frozen=True)
class CsvTable:
    """A CSV file as text cells: `header`, `rows` (lists of str) and each row's file line."""

    file: str
    header: tuple
    rows: tuple
    lines: tuple
    header_line: int = 1  # the header's file line (1 for a header-less file: names declared)

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
                        f"cell is {'empty' if not text else excerpt(text)}; every row "
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
                    f"{excerpt(text)} is not a number; use a plain decimal number "
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
                    f"{excerpt(text)} is infinite; give a finite number"
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


def read_csv(path, *, example: str = "t_s,y_px", names=None) -> CsvTable:
    """Read a CSV with a header row (line 1, or the first line not starting with '#').

    Lines starting with '#' and blank lines are skipped; every row must have as many cells as
    the header. `names`: the column names of a header-less file (every line is a row; a
    MATLAB ``csvwrite`` log). Cells stay text; convert with `CsvTable.numbers`.
    """
    path = Path(path)
    file = str(path)
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
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(
            f"cannot be read as UTF-8 text ({err}); export the table as CSV",
            file=file,
            line=1,
            field="header",
        ) from None
    header, rows, lines = None, [], []
    header_line = 1
    if names is not None:
        header = [str(n).strip() for n in names]
    physical = text.splitlines()
    for lineno, raw in enumerate(physical, 1):
        if len(raw) > MAX_LINE_CHARS:
            raise InputError(
                f"is {len(raw)} characters long (at most {MAX_LINE_CHARS}; it starts "
                f"{excerpt(raw)}); a row holds one frame's numbers: check the delimiter "
                "and the line endings",
                file=file,
                line=lineno,
                field="row",
            )
    reader = csv.reader(physical, strict=False)
    previous = 0
    while True:
        try:
            cells = next(reader)
        except StopIteration:
            break
        except csv.Error as err:
            raise InputError(
                f"is not a well-formed CSV row ({excerpt(str(err), 80)}); check quotes and "
                "delimiters (plain comma-separated numbers)",
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
                f"({_header_text(header)}); every row needs one cell per column"
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
    return CsvTable(file, tuple(header), tuple(rows), tuple(lines), header_line)


def _numeric_row(cells) -> bool:
    for c in cells:
        try:
            float(c)
        except ValueError:
            if c.strip().lower() not in ("", "nan", "na"):
                return False
    return True


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

    names = ", ".join(f"{channel.name}_{u}" for u in unit_examples(channel))
    fix = (
        f"give a unit of {channel.si_unit} in the mapping ({mapped})"
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


def check_increasing(table: CsvTable, t: np.ndarray) -> None:
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
