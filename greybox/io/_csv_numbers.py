"""Decimal numbers parsed from a CSV body's bytes by numpy array operations (no Python loop
per cell), the fast path of the run-CSV reader (greybox/io/_csv.py).

Each cell's bytes are copied, right-aligned, into a row of 8 or 16 bytes (one 16-byte copy
per cell), and the rows transposed so that every numpy operation works on one character
position of every cell at once. A fixed-point cell (``-12.345``, at most 15 digits) is read
by combining neighbouring digit positions pairwise (uint8 -> uint16 -> uint32 -> uint64):
its digits as one integer, divided by a power of ten, one correctly rounded operation
(Clinger's fast path), so the value is bit for bit what `float()` gives. Cells with an
exponent (``1.5e-3``) go through a general per-position pass; an empty cell is NaN; any
other cell (nan, inf, 17 digits, a space) is handed to `float()` one at a time while they
are few. A cell that `float()` refuses, or a row with the wrong number of cells, returns
None: the caller then takes the slow path, which says where the problem is. Temporaries are
bounded by working in chunks of cells.
"""

from __future__ import annotations

import numpy as np

CHUNK = 1 << 16  # cells per block: the byte matrix and its masks stay a few MB
WIDTH = 16  # characters of a fixed-point cell read by the pairwise pass
MAX_WIDTH = 24  # characters of a cell with an exponent; longer ones go to float()
MAX_DIGITS = 15  # significant digits that an int64 -> float64 keeps exactly
MAX_ODD = 1000  # cells for float(); more, and the caller's general parser is faster
_POW10 = 10.0 ** np.arange(23)  # exact doubles
_POW10_INT = 10 ** np.arange(WIDTH + 1, dtype=np.uint64)
_MISSING = ("", "nan", "na")


def parse_cells(b: np.ndarray, delimiter: str, n_columns: int) -> np.ndarray | None:
    """(rows, n_columns) floats from `b`: UTF-8 bytes of rows separated by b"\\n" (no
    "\\r", blank or comment lines), cells by `delimiter`; None when the caller must parse."""
    if b.size == 0 or len(delimiter.encode()) != 1:
        return None
    # WIDTH zero bytes on each side: every cell's WIDTH-byte window lies inside
    pad = np.zeros(WIDTH, np.uint8)
    b = np.concatenate((pad, b, pad[:0] if b[-1] == 10 else np.full(1, 10, np.uint8), pad))
    d = ord(delimiter)
    ends = np.flatnonzero((b == d) | (b == 10))  # where each cell ends
    row_ends = np.flatnonzero(b[ends] == 10)
    if np.any(np.diff(row_ends, prepend=-1) != n_columns):
        return None  # a row with a cell too many or too few
    rows = np.ndarray(buffer=b, dtype=f"V{WIDTH}", shape=(b.size - WIDTH + 1,), strides=(1,))
    out = np.empty(ends.size)
    rest = []
    for k in range(0, ends.size, CHUNK):
        cells = np.arange(k, min(k + CHUNK, ends.size))
        values, other = _fixed_point(rows, _starts(ends, cells), ends[cells])
        out[cells] = values
        rest.append(other + k)
    rest = np.concatenate(rest)
    if rest.size > MAX_ODD:  # scientific notation: the general pass, on those cells only
        values, odd = _plain(b, _starts(ends, rest), ends[rest])
        out[rest] = values
        rest = rest[odd]
        if rest.size > MAX_ODD:
            return None
    for k in rest.tolist():
        v = _one(bytes(b[_starts(ends, k) : ends[k]]))
        if v is None:
            return None
        out[k] = v
    return out.reshape(-1, n_columns)


def _count_rows(mask):
    """Per cell (column), the marked positions: a uint8 sum (a bool sum is 10x slower)."""
    return np.add.reduce(mask.view(np.uint8), axis=0, dtype=np.uint8).astype(np.int64)


def _fixed_point(rows, starts, ends):
    """(values, indices of the other cells) for the cells [starts, ends) of the bytes that
    `rows` views as WIDTH-byte windows: the cells ``[-]digits[.digits]``."""
    lens = ends - starts
    n = lens.size
    width = 8 if lens.max(initial=0) <= 8 else WIDTH
    c = rows[ends - width].view(np.uint8).reshape(n, WIDTH)[:, :width].T.copy()
    r = np.arange(width - 1, -1, -1, dtype=np.uint8)[:, None]  # position from the right
    c *= r < lens  # bytes before the cell
    digit = c - np.uint8(48)  # wraps below '0': one compare finds the digits
    isdig = digit < 10
    digit *= isdig
    dot = c == 46
    n_digits = _count_rows(isdig)
    n_dot = _count_rows(dot)
    first = c[np.clip(width - lens, 0, width - 1), np.arange(n)]
    minus = first == 45
    plain = (
        (n_digits + n_dot + minus == lens)
        & (n_dot <= 1)
        & (n_digits >= 1)
        & (n_digits <= MAX_DIGITS)
        & (lens <= width)
    )
    # the digits as one integer (a dot counts as a 0 digit): pairs of positions combined
    x = digit
    for factor, kind in ((10, np.uint8), (100, np.uint16), (10_000, np.uint32), (10**8, np.uint64)):
        if x.shape[0] == 1:
            break
        x = x[0::2].astype(kind) * kind(factor) + x[1::2]
    s = x[0].astype(np.uint64)
    rdot = np.add.reduce(dot * r, axis=0, dtype=np.uint8).astype(np.int64)  # after the dot
    has_dot = n_dot == 1
    low = s % _POW10_INT[np.where(has_dot, rdot, 0)]
    m = np.where(has_dot, (s - low) // np.uint64(10) + low, s)  # the dot's 0 removed
    v = m.astype(float) / _POW10[np.where(has_dot, rdot, 0)]
    v = np.where(minus, -v, v)
    v[lens == 0] = np.nan
    return v, np.flatnonzero(~plain & (lens > 0))


def _starts(ends, cells):
    """Where cells `cells` begin: after the previous cell's end (the first after the pad)."""
    return np.where(cells > 0, ends[np.maximum(cells, 1) - 1] + 1, WIDTH)


def _one(cell: bytes) -> float | None:
    """A cell that is not plain: NaN if marked missing, float() if it reads, else None."""
    text = cell.decode("utf-8", "replace").strip()
    if text.lower() in _MISSING:
        return np.nan
    if "_" in text:  # float() reads 1_000; numpy and the csv path do not
        return None
    try:
        return float(text)
    except ValueError:
        return None


def _classes() -> np.ndarray:
    """Per byte value, its class as a count in its own bit field (a sum over a cell's bytes
    counts every class at once): digit, dot, e/E, sign, anything else; 0 stays 0."""
    lut = np.full(256, 1 << _OTHER, np.uint32)
    lut[0] = 0
    lut[48:58] = 1 << _DIGIT
    lut[ord(".")] = 1 << _DOT
    lut[[ord("e"), ord("E")]] = 1 << _E
    lut[[ord("+"), ord("-")]] = 1 << _SIGN
    return lut


_DIGIT, _DOT, _E, _SIGN, _OTHER = 0, 6, 12, 18, 24  # 6-bit fields: counts up to MAX_WIDTH
_CLASSES = _classes()


def _count(packed, field):
    return ((packed >> field) & 63).astype(np.int64)


def _first(mask, cols, default):
    """Per cell, the column of its one marked byte (a plain cell has at most one), else
    `default` (a weighted sum: argmax along the short axis is many times slower)."""
    return np.where(mask.any(axis=0), (mask * cols).sum(axis=0, dtype=np.int64), default)


def _plain(b, starts, ends):
    """(values, indices of the cells that are not plain) for the cells [starts, ends)."""
    lens = ends - starts
    width = int(min(lens.max(initial=0), MAX_WIDTH))
    n = lens.size
    if width == 0:
        return np.full(n, np.nan), np.empty(0, np.int64)
    cols = np.arange(width, dtype=np.uint8)[:, None]
    c = np.empty((width, n), np.uint8)  # row j: character j of every cell (0 past its end)
    last = b.size - 1
    for j in range(width):
        np.multiply(b[np.minimum(starts + j, last)], lens > j, out=c[j])
    packed = _CLASSES[c].sum(axis=0, dtype=np.uint32)
    n_digits, n_dot, n_e = _count(packed, _DIGIT), _count(packed, _DOT), _count(packed, _E)
    n_sign, n_other = _count(packed, _SIGN), _count(packed, _OTHER)
    has_e = n_e > 0
    epos = np.where(has_e, ((c | 32) == 101).argmax(axis=0), lens) if has_e.any() else lens
    dotpos = _first(c == 46, cols, -1)
    e_sign = c[np.minimum(epos + 1, width - 1), np.arange(n)]
    exp_sign = has_e & ((e_sign == 43) | (e_sign == 45))
    n_exp = np.where(has_e, lens - epos - 1 - exp_sign, 0)
    n_mant = n_digits - n_exp
    lead_sign = (c[0] == 43) | (c[0] == 45)
    plain = (
        (n_other == 0)
        & (n_dot <= 1)
        & (n_e <= 1)
        & (n_sign == lead_sign.astype(np.int64) + exp_sign)
        & (dotpos < epos)
        & (n_mant >= 1)
        & (n_mant <= MAX_DIGITS)
        & (~has_e | ((n_exp >= 1) & (n_exp <= 3)))
        & (lens <= MAX_WIDTH)
    )
    total = np.zeros(n, np.int64)  # all digits of the cell as one integer: mantissa, exponent
    for j in range(width):
        digit = c[j] - np.uint8(48)  # wraps below '0': one compare finds the digits
        total = np.where(digit < 10, total * 10 + digit, total)
    p_exp = (10 ** np.minimum(n_exp, 3)).astype(np.int64)
    m, e = np.divmod(total, p_exp)
    e10 = np.where(e_sign == 45, -e, e) * has_e - np.where(dotpos >= 0, epos - 1 - dotpos, 0)
    plain &= np.abs(e10) <= 22
    v = m.astype(float)
    p = _POW10[np.minimum(np.abs(e10), 22)]
    v = np.where(e10 >= 0, v * p, v / p)
    v = np.where(c[0] == 45, -v, v)
    v[lens == 0] = np.nan
    return v, np.flatnonzero(~plain & (lens > 0))
