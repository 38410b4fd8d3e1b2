"""The README's two commands: the test command is exactly what CI runs, the demo command runs
the demo, both are on the first screen, and every greybox command line it shows parses."""

import re
import shlex
from pathlib import Path

import pytest

from greybox.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
FIRST_SCREEN = "\n".join(README.splitlines()[:30])


def _commands(text: str) -> list[str]:
    blocks = re.findall(r"```sh\n(.*?)```", text, flags=re.S)
    return [line.strip() for block in blocks for line in block.splitlines() if line.strip()]


def _ci_command() -> str:
    lines = [
        line
        for line in (ROOT / ".ci" / "run").read_text().splitlines()
        if line.strip() and not line.startswith("#") and not line.startswith(("set ", "cd "))
    ]
    assert len(lines) == 1, lines
    return lines[0]


def test_readme_test_command_is_the_ci_command():
    setup = [c for c in _commands(FIRST_SCREEN) if c.startswith("python3.11 -m venv .venv")]
    assert len(setup) == 2, setup
    assert setup[1] == _ci_command()
    assert "pytest" in setup[1] and ".[test]" in setup[1]


def test_readme_demo_command_runs_the_demo():
    demo = [c for c in _commands(FIRST_SCREEN) if c.startswith("python3.11 -m venv .venv")][0]
    assert (
        demo == "python3.11 -m venv .venv && .venv/bin/pip install -q -e . && "
        ".venv/bin/greybox demo"
    )
    assert demo.split("&&")[-1].split() == [".venv/bin/greybox", "demo"]


@pytest.mark.parametrize(
    "command", [c for c in _commands(README) if c.startswith(".venv/bin/greybox ")]
)
def test_readme_greybox_commands_parse(command):
    args = build_parser().parse_args(shlex.split(command)[1:])
    assert args.func is not None


@pytest.mark.parametrize(
    "argv, words",
    [
        ([], ["t_s", "um", "mW", "simulation"]),
        (
            ["fit"],
            [
                "t_s [s]",
                "y_um [um]",
                "y_px [pixels",
                "laser_mW [mW]",
                "exposure_ms [ms]",
                "um_per_px",
                "simulation",
                "Exit status",
            ],
        ),
        (["simulate"], ["power_mW", "period_ms", "t_s [s]", "y_um", "laser_mW", "H1_pct", "95 %"]),
        (["demo"], ["ms", "um", "mW", "SI", "simulation"]),
    ],
)
def test_help_explains_the_units(argv, words):
    parser = build_parser()
    if argv:
        sub = next(a for a in parser._subparsers._group_actions if a.choices)
        parser = sub.choices[argv[0]]
    text = parser.format_help()
    for word in words:
        assert word in text, (argv, word)
