"""The run-CSV reader as users' files come: delimiters, gaps, comments, header-less logs,
mapped time columns, one-sensor logs of a two-sensor board, and the located errors.

Every value is checked against Python's own `float` of the cell text (read with the `csv`
module), an independent parse of the same file."""

import csv
import io

import numpy as np
import pytest

from greybox._model.errors import InputError
from greybox.io import load_experiment_set
from greybox.io._csv import read_csv


def _reference(text: str, delimiter: str):
    """(header, values, file lines) by the csv module and float(), cell by cell."""
    header, rows, lines = None, [], []
    for lineno, cells in enumerate(csv.reader(io.StringIO(text), delimiter=delimiter), 1):
        if not cells or not "".join(cells).strip() or cells[0].startswith("#"):
            continue
        if header is None:
            header = [c.strip() for c in cells]
            continue
        rows.append([np.nan if c.strip().lower() in ("", "nan") else float(c) for c in cells])
        lines.append(lineno)
    return header, np.array(rows), np.array(lines)


def _table_text(delimiter=",", newline="\n", quote_header=False, seed=0):
    rng = np.random.default_rng(seed)
    names = ["t_s", "T1_degC", "T2_degC", "H1_pct"]
    head = delimiter.join(f'"{n}"' if quote_header else n for n in names)
    out = ["# logger v2", head]
    for k in range(400):
        cells = [f"{0.5 * k:.6g}", f"{rng.normal(21, 3):.17g}", f"{rng.normal(30, 1):.4e}"]
        cells.append(str(int(rng.integers(0, 100))))
        if k % 37 == 5:
            cells[1] = ""  # a dropped reading
        if k % 53 == 7:
            cells[2] = "nan"
        out.append(delimiter.join(cells))
        if k % 101 == 50:
            out += ["", "# a pause in the log"]
    return newline.join(out) + newline


@pytest.mark.parametrize("delimiter", [",", ";", "\t"])
@pytest.mark.parametrize("newline", ["\n", "\r\n"])
def test_values_and_lines_match_an_independent_parse(tmp_path, delimiter, newline):
    text = _table_text(delimiter, newline)
    p = tmp_path / "run.csv"
    p.write_bytes(text.encode())
    table = read_csv(p)  # the delimiter detected from the header line
    header, values, lines = _reference(text.replace("\r\n", "\n"), delimiter)
    assert table.delimiter == delimiter
    assert list(table.header) == header
    np.testing.assert_array_equal(table.values, values)  # bit for bit, NaN where empty
    np.testing.assert_array_equal(table.lines, lines)


def test_csv_module_path_gives_the_same_table(tmp_path):
    """A quoted header goes through the csv module: the same numbers and lines."""
    fast, slow = tmp_path / "fast.csv", tmp_path / "slow.csv"
    fast.write_text(_table_text(","))
    slow.write_text(_table_text(",").replace("\n0,", '\n"0",', 1))  # one quoted cell
    a, b = read_csv(fast), read_csv(slow)
    np.testing.assert_array_equal(a.values, b.values)
    np.testing.assert_array_equal(a.lines, b.lines)


def test_errors_keep_the_file_line_and_column(tmp_path):
    text = _table_text(",").splitlines()
    text[300] = text[300].replace(",", ",oops", 1)  # a text cell deep in the file
    p = tmp_path / "run.csv"
    p.write_text("\n".join(text) + "\n")
    table = read_csv(p)
    with pytest.raises(InputError) as err:
        table.numbers("T1_degC", allow_missing=True)
    assert err.value.line == 301 and err.value.field == "T1_degC"
    assert "'oops" in err.value.message
    good = _table_text(",")
    p.write_text(good)
    with pytest.raises(InputError) as err:  # an empty reading where one is required
        read_csv(p).numbers("T1_degC")
    assert "cell is empty" in err.value.message
    first_gap = next(i for i, ln in enumerate(good.splitlines(), 1) if ",," in ln)
    assert err.value.line == first_gap


def test_ragged_row_names_the_delimiter(tmp_path):
    p = tmp_path / "run.csv"
    p.write_text("t_s;T1_degC\n0;21\n1;21;5\n")
    with pytest.raises(InputError) as err:
        read_csv(p)
    assert err.value.line == 3
    assert "semicolon (';')" in err.value.message


def test_header_less_file_gets_a_hint(tmp_path):
    p = tmp_path / "run.csv"
    p.write_text("0,21.0,21.0,0,0\n1,21.0,21.0,0,0\n")
    with pytest.raises(InputError) as err:
        read_csv(p)
    assert "header = false" in err.value.message and err.value.line == 1


# --------------------------------------------------------------------------------------
# experiment folders (the tclab board: two temperatures, two heaters)

TOML = """\
[experiment]
device = "tclab"

[model]
radiation = false

[experiment.settings]
ambient_K = 294.15

[fit]
free = ["U_W_per_m2K"]
{extra}
[[runs]]
name = "a"
file = "a.csv"
role = "estimation"
{run}
"""


def _folder(tmp_path, csv_text, extra="", run=""):
    folder = tmp_path / "exp"
    folder.mkdir(exist_ok=True)
    (folder / "experiment.toml").write_text(TOML.format(extra=extra, run=run))
    (folder / "a.csv").write_text(csv_text)
    return folder


def _log(delimiter=","):
    rows = [delimiter.join(["t_s", "T1_degC", "T2_degC", "H1_pct", "H2_pct"])]
    rows += [
        delimiter.join(f"{v:g}" for v in (k, 21 + 0.1 * k, 21 + 0.05 * k, 50, 0)) for k in range(20)
    ]
    return "\n".join(rows) + "\n"


def test_semicolon_file_loads_like_the_comma_file(tmp_path):
    (tmp_path / "c").mkdir()
    (tmp_path / "s").mkdir()
    a = load_experiment_set(_folder(tmp_path / "c", _log(",")))
    b = load_experiment_set(_folder(tmp_path / "s", _log(";")))
    np.testing.assert_array_equal(a.estimation[0].y, b.estimation[0].y)
    assert a.estimation[0].y[3, 0] == pytest.approx(21.3 + 273.15, abs=1e-12)


def test_declared_delimiter_that_is_not_in_the_file(tmp_path):
    folder = _folder(tmp_path, _log(";"), extra='[csv]\ndelimiter = ","\n')
    with pytest.raises(InputError) as err:
        load_experiment_set(folder)
    assert "semicolon (';')" in str(err.value) and 'delimiter = ";"' in str(err.value)
    tab = _folder(tmp_path, _log("\t"), extra='[csv]\ndelimiter = "tab"\n')
    assert load_experiment_set(tab).estimation[0].y.shape == (20, 2)


def test_unit_message_asks_for_the_files_unit_not_kelvin(tmp_path):
    text = "Time,T1,H1\n" + "".join(f"{k},21.5,50\n" for k in range(10))
    run = 'columns = { time = "Time", T1 = "T1", H1 = "H1" }\nconstant_inputs = { H2 = 0 }'
    with pytest.raises(InputError) as err:
        load_experiment_set(_folder(tmp_path, text, run=run))
    message = str(err.value)
    assert 'e.g. unit = "C"' in message and "the unit of the numbers as logged" in message
    assert "a unit of K" not in message


def test_repeated_first_time_names_the_users_column(tmp_path):
    text = "Time,T1,H1\n0,21.5,50\n0,21.5,50\n" + "".join(
        f"{k},21.5,50\n" for k in range(1, 10)
    )
    run = (
        'columns = { time = "Time", T1 = { column = "T1", unit = "degC" }, H1 = "H1" }\n'
        "constant_inputs = { H2 = 0 }"
    )
    with pytest.raises(InputError) as err:
        load_experiment_set(_folder(tmp_path, text, run=run))
    assert err.value.field == "Time" and err.value.line == 3
    assert "'Time'" in err.value.message and "first time stamp twice" in err.value.message


def test_one_sensor_log_is_an_estimation_run(tmp_path):
    """The board has T1 and T2; the only estimation run logged T1: its frames count."""
    text = "t_s,T1_degC,H1_pct,H2_pct\n" + "".join(
        f"{k},{21 + 0.1 * k:g},50,0\n" for k in range(20)
    )
    fs = load_experiment_set(_folder(tmp_path, text))
    e = fs.estimation[0]
    assert e.y.shape == (20, 2) and np.isnan(e.y[:, 1]).all()
    assert fs.runs[0].n_valid == 20


def test_outside_folder_message_is_whole(tmp_path):
    name = "../" + "a_long_folder_name_of_the_lab_share/" * 3 + "run_0001.csv"
    folder = _folder(tmp_path, _log(), run="")
    (folder / "experiment.toml").write_text(
        TOML.format(extra="", run="").replace('file = "a.csv"', f'file = "{name}"')
    )
    with pytest.raises(InputError) as err:
        load_experiment_set(folder)
    assert repr(name) in str(err.value) and "outside the experiment folder" in str(err.value)
