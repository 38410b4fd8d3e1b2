"""The vectorised number parser of the run-CSV reader (greybox/io/_csv_numbers.py) against
Python's own `float()` of every cell, bit for bit (sign of zero included): fixed-point cells
(the pairwise digit pass), scientific notation (the general pass), and the cells it hands to
`float()`; refusals return None so that the reader's located slow path takes over."""

import numpy as np
import pytest

import greybox.io._csv_numbers as numbers
from greybox._model.errors import InputError
from greybox.io._csv import read_csv


def _cells(rng, n, formats, decades):
    out = []
    for _ in range(n):
        x = float(rng.standard_normal() * 10.0 ** rng.integers(-decades, decades + 1))
        f = str(rng.choice(formats))
        out.append(f"{int(x):d}" if f == "%d" else f % x)
    return out


def _parse(cells, n_columns=3, delimiter=","):
    n = len(cells) // n_columns * n_columns
    rows = [delimiter.join(cells[i : i + n_columns]) for i in range(0, n, n_columns)]
    raw = np.frombuffer("\n".join(rows).encode(), np.uint8)
    ref = [np.nan if c.strip().lower() in ("", "nan", "na") else float(c) for c in cells[:n]]
    return numbers.parse_cells(raw, delimiter, n_columns), np.array(ref).reshape(-1, n_columns)


def _same(got, ref):
    assert got is not None
    np.testing.assert_array_equal(got, ref)
    np.testing.assert_array_equal(np.signbit(got), np.signbit(ref))


EDGES = ["", "1.", ".5", "-.5", "-0", "0", "-0.0", "007", "1e-22", "1e22", "1E+05", "+2E+2",
         "1e0", "9" * 15, "9" * 15 + "e-22", "1.5e-021", "0.1e-21", "-1.5e-3", "+3"]


def test_fixed_point_and_exponent_cells_without_float(monkeypatch):
    """Every cell is read by the array passes (float() may take none of them)."""
    monkeypatch.setattr(numbers, "MAX_ODD", 0)
    rng = np.random.default_rng(0)
    formats = ["%.6g", "%e", "%.10E", "%+.4g", "%.3f", "%.6f", "%d", "%.9g"]
    cells = _cells(rng, 30_000, formats, 8) + EDGES
    for delimiter in (",", ";", "\t"):
        _same(*_parse(cells, 3, delimiter))


def test_other_cells_are_read_by_float():
    rng = np.random.default_rng(1)
    cells = _cells(rng, 30_000, ["%.6g", "%.3f"], 5)
    cells[::50] = _cells(rng, 600, ["%.17g", "%r"], 30)  # 17 digits, 1e-30: float()
    cells[7::1000] = ["nan", "NaN", "inf", "-inf", "na", " 1.5", "2.5 ", "1e-400", "1e400",
                      "1.5e-022", "1" * 20, "-0e5", "0.000000000000000000001", "1.5e+3", "5",
                      "-7", "8", "9", "10", "11", "12", "13", "14", "15", "16", "17", "18",
                      "19", "20", "21", "22"][: len(cells[7::1000])]
    _same(*_parse(cells))


@pytest.mark.parametrize(
    "text",
    ["1,2\n3\n", "1,2,3\n", "1,x\n", "1,-\n", "1,1e\n", "1,1.2.3\n", "1,1_0\n", "1,e5\n",
     "1,1e5.5\n", "1,1-5\n", "1,.\n", "1,1e+\n", "1,--1\n", "1,1e1e1\n", "1,2\n\n"],
)
def test_what_float_refuses_goes_back_to_the_reader(text):
    assert numbers.parse_cells(np.frombuffer(text.encode(), np.uint8), ",", 2) is None


def test_a_bad_cell_deep_in_a_large_file_keeps_its_line(tmp_path):
    rows = [f"{0.1 * k:.6g},{np.sin(k):.6g}" for k in range(50_000)]
    rows[41_234] = "4123.4,1.2.3"
    p = tmp_path / "run.csv"
    p.write_text("t_s,y_um\n" + "\n".join(rows) + "\n")
    with pytest.raises(InputError) as err:
        read_csv(p).numbers("y_um")
    assert (err.value.line, err.value.field) == (41_236, "y_um")
