"""`greybox describe DEVICE --option k=v` shows the parameters of the structure asked for."""

import re

import pytest

import greybox
from greybox.cli import main
from greybox.cli._describe import parse_options


def _describe(capsys, *argv) -> str:
    assert main(["describe", *argv]) == 0
    return capsys.readouterr().out


def test_options_change_the_parameter_table(capsys):
    default = _describe(capsys, "chevron_laser")
    chain = _describe(capsys, "chevron_laser", "--option", "thermal_nodes=3", "--option",
                      "elongation_lag=true")  # fmt: skip
    assert "thermal.tau_s" in default and "thermal.resistance_K_per_W[2]" not in default
    assert "thermal.tau_s" not in chain and "thermal.lag_s" in chain
    # the table printed is the spec's for those options, row for row
    table = greybox.get_device("chevron_laser").parameter_table(
        {"thermal_nodes": 3, "elongation_lag": True}
    )
    rows = re.findall(r"^ [ *](\S+) ", chain.split("parameters (")[1], flags=re.M)
    assert rows[: len(table)] == [p.path for p in table]
    # physical range beside the optimiser's bounds: chain resistances x10 vs x30 (freed)
    r0 = table[[p.path for p in table].index("thermal.resistance_K_per_W[0]")]
    line = next(s for s in chain.splitlines() if "thermal.resistance_K_per_W[0]" in s)
    lo, hi = r0.physical_range
    assert f"physical {lo:g}..{hi:g}" in line
    assert f"bounds {r0.nominal / 30:g}..{r0.nominal * 30:g}" in line


def test_bad_option_exits_2(capsys):
    assert main(["describe", "chevron_laser", "--option", "thermal_nodes=0"]) == 2
    assert "thermal_nodes" in capsys.readouterr().err
    assert main(["describe", "chevron_laser", "--option", "thermal_nodes"]) == 2


@pytest.mark.parametrize(
    "text, value",
    [("2", 2), ("true", True), ("1.5", 1.5), ('"linear"', "linear"), ("linear", "linear")],
)
def test_option_values_read_as_toml(text, value):
    got = parse_options([f"k={text}"])["k"]
    assert got == value and type(got) is type(value)
