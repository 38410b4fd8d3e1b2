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
