"""The run-CSV reader's memory is linear in the file and holds numbers, not strings (issue 27).

A 221-255 MB file once needed 5.6-6.8 GB: every cell was kept as a Python string (about 58
bytes for a 9-character cell, 6x the text). Measured with tracemalloc (which counts numpy's
buffers too) for two sizes of one table: what the table keeps is the text (quoted in
messages) plus 8 bytes per cell -- about 2x the file, far below a string per cell -- and the
peak while parsing grows by under 10x each added byte of file (measured 7.9x; the csv-module
reader, which holds every cell as a string at once, peaks at 12x): a fixed ~12 MB of chunk
buffers (`greybox.io._csv_numbers.CHUNK` cells at a time) plus a slope linear in the file.
The values equal numpy's independent `loadtxt` parse.
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
    for n in (60_000, 120_000):
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


def test_memory_grows_linearly_with_the_file(measured):
    (path1, _, kept1, peak1), (path2, _, kept2, peak2) = measured[60_000], measured[120_000]
    size1, size2 = path1.stat().st_size, path2.stat().st_size
    assert abs(kept2 / kept1 - 1) < 0.1, (kept1, kept2)  # kept: the same per byte
    slope = (peak2 * size2 - peak1 * size1) / (size2 - size1)  # peak bytes per added byte
    assert slope < 10.0, slope
    assert peak2 < peak1, (peak1, peak2)  # per byte: the fixed buffers weigh less
