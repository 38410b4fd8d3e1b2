"""The run-CSV reader's memory is linear in the file and holds numbers, not strings (issue 27).

A 221-255 MB file once needed 5.6-6.8 GB: every cell was kept as a Python string (about 58
bytes for a 9-character cell, 6x the text). Measured with tracemalloc (which counts numpy's
buffers too) for two sizes of one table: what the table keeps is the text (quoted in
messages) plus 8 bytes per cell -- about 2x the file, far below a string per cell -- the
peak while parsing stays under 10x the file (9x measured; the csv-module reader, which holds
every cell as a string at once, peaks at 12x), and both per byte of file are the same at
both sizes (linear). The values equal numpy's independent `loadtxt` parse.
"""

import tracemalloc

import numpy as np
import pytest

from greybox.io._csv import read_csv


def _measure(path):
    tracemalloc.start()
    try:
        table = read_csv(path)
        kept, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    return table, kept / path.stat().st_size, peak / path.stat().st_size


@pytest.fixture(scope="module")
def measured(tmp_path_factory):
    folder = tmp_path_factory.mktemp("csvmem")
    rng = np.random.default_rng(0)
    out = {}
    for n in (15_000, 30_000):
        path = folder / f"run{n}.csv"
        rows = rng.normal(size=(n, 5))
        body = "\n".join(",".join(f"{v:.6g}" for v in r) for r in rows)
        path.write_text("t_s,a_um,b_um,c_mW,d_K\n" + body + "\n")
        out[n] = (path, *_measure(path))
    return out


def test_the_values_are_numpys_parse(measured):
    for path, table, _, _ in measured.values():
        assert np.array_equal(table.values, np.loadtxt(path, delimiter=",", skiprows=1))


def test_the_table_keeps_numbers_not_strings(measured):
    for path, table, kept, peak in measured.values():
        cells_per_byte = table.values.size / path.stat().st_size
        # the text itself, and 8 bytes per cell (+ the line numbers), a little slack
        assert kept < 1.0 + 8 * cells_per_byte + 0.3, kept
        assert kept < 58 * cells_per_byte / 2  # far below one str object per cell
        assert peak < 10.0, peak


def test_memory_per_byte_does_not_grow_with_the_file(measured):
    (_, _, kept1, peak1), (_, _, kept2, peak2) = measured[15_000], measured[30_000]
    assert abs(kept2 / kept1 - 1) < 0.1, (kept1, kept2)
    assert abs(peak2 / peak1 - 1) < 0.1, (peak1, peak2)
