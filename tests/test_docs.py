"""Every fenced shell command and Python snippet of README.md, experiments/README.md and
DEVELOPING.md runs (in a temporary folder) with the exit status it implies, and every
documented error example is reproduced verbatim.

Convention (DEVELOPING.md, "Docs test"): a comment on the line before a fence says how the
test treats a block that cannot run as written in the time a test has:

    <!-- docs-test: skip: REASON -->      not run (e.g. creates a venv; CI runs it)
    <!-- docs-test: short: COMMAND -->    COMMAND is run instead (same program and
                                           subcommand: a short version of a long run)

Any other ``sh``/``python`` block is run as written; ``.venv/bin/greybox`` and
``.venv/bin/python`` mean this interpreter. Error examples (text blocks whose lines start
with ``greybox fit: error:``) are produced from the folders built below; ``...`` in a
documented line stands for text left out, the rest must match character for character.
"""

import re
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.helpers import GOOD_TOML

ROOT = Path(__file__).resolve().parents[1]
DOCS = ("README.md", "experiments/README.md", "DEVELOPING.md")
FENCE = re.compile(r"(?:<!-- docs-test: (skip|short): (.*?) -->\n)?```(\w*)\n(.*?)```", re.S)


def _blocks(kinds):
    out = []
    for doc in DOCS:
        text = (ROOT / doc).read_text()
        for m in FENCE.finditer(text):
            marker, arg, lang, body = m.groups()
            if lang in kinds:
                line = text[: m.start(3)].count("\n") + 1
                out.append(pytest.param(marker, arg, lang, body, id=f"{doc}:{line}"))
    return out


def _argv(command: str) -> list:
    words = shlex.split(command)
    if words[0] in (".venv/bin/greybox", "greybox"):
        return [sys.executable, "-m", "greybox", *words[1:]]
    if words[0] in (".venv/bin/python", "python"):
        return [sys.executable, *words[1:]]
    return words


@pytest.mark.parametrize("marker, arg, lang, body", _blocks({"sh", "bash"}))
def test_shell_block_runs(marker, arg, lang, body, tmp_path, monkeypatch):
    if marker == "skip":
        assert arg.strip(), "a skipped block must say why"
        pytest.skip(arg)
    commands = [ln.strip() for ln in body.splitlines() if ln.strip()]
    if marker == "short":
        short = _argv(arg)
        for c in commands:  # the short version runs the same program and subcommand
            assert _argv(c)[:4] == short[:4] or _argv(c)[:3] == short[:3], (c, arg)
        commands = [arg]
    for c in commands:
        argv = _argv(c)
        if argv[:3] == [sys.executable, "-m", "greybox"]:  # in this process: one import
            assert _greybox(argv[3:], tmp_path, monkeypatch) == 0, c
            continue
        done = subprocess.run(argv, cwd=tmp_path, capture_output=True, text=True, timeout=120)
        assert done.returncode == 0, (c, done.stderr[-2000:])


def _greybox(args, folder, monkeypatch) -> int:
    """`greybox ARGS` run in `folder` in this process (exit status; --help exits 0)."""
    from greybox.cli import main

    monkeypatch.chdir(folder)
    try:
        return main(list(args))
    except SystemExit as exit_:
        return int(exit_.code or 0)


@pytest.mark.parametrize("marker, arg, lang, body", _blocks({"python"}))
def test_python_block_runs(marker, arg, lang, body, tmp_path, monkeypatch):
    if marker == "skip":
        pytest.skip(arg)
    monkeypatch.chdir(tmp_path)  # in this process (one import of greybox for every snippet)
    code = compile(arg if marker == "short" else body, "snippet.py", "exec")
    exec(code, {"__name__": "snippet"})


# --------------------------------------------------------------------------------------
# the documented error messages


T = (np.arange(42) + 0.5) / 30.0
Y = 312.0 + 1.5 * (np.sin(2 * np.pi * T / 0.4) > 0) * (T > 0.2)
LASER = 20.0 * ((T - 0.2) % 0.4 < 0.2) * (T > 0.2) * (T < 1.4)


def _csv(path, rows, header="t_s,y_px"):
    path.write_text(header + "\n" + "".join(",".join(r) + "\n" for r in rows))


def _rows(y=Y, t=T, extra=None):
    rows = [[f"{a:.6f}", f"{b:.4f}"] for a, b in zip(t, y)]
    if extra is not None:
        rows = [r + [f"{v:g}"] for r, v in zip(rows, extra)]
    return rows


def _chevron(tmp_path, toml=GOOD_TOML, est=None, header="t_s,y_px", folder="exp", name="est"):
    exp = tmp_path / folder
    exp.mkdir()
    (exp / "experiment.toml").write_text(toml.replace('file = "est.csv"', f'file = "{name}.csv"'))
    _csv(exp / f"{name}.csv", est if est is not None else _rows(), header)
    _csv(exp / "val.csv", _rows(Y - 2.0))
    return exp


def _exposure(tmp_path):
    _chevron(tmp_path, GOOD_TOML.replace("exposure_ms = 10", "exposure_ms = -10"))


def _missing_val(tmp_path):
    (_chevron(tmp_path) / "val.csv").unlink()


def _unit(tmp_path):
    _chevron(tmp_path, header="t_s,y_degC")


def _repeat(tmp_path):
    rows = _rows()
    rows[10][0] = rows[9][0]
    _chevron(tmp_path, est=rows)


def _repeat_readme(tmp_path):
    """README.md's example: its folder my_experiment and run file run1.csv."""
    rows = _rows()
    rows[10][0] = rows[9][0]
    _chevron(tmp_path, est=rows, folder="my_experiment", name="run1")


def _not_a_number(tmp_path):
    rows = _rows()
    rows[6][1] = "31x.2"
    _chevron(tmp_path, est=rows)


def _contradiction(tmp_path):
    laser = LASER.copy()
    laser[27] = 20.0
    _chevron(tmp_path, est=_rows(extra=laser), header="t_s,y_px,laser_mW")


TCLAB_TOML = """\
[experiment]
device = "tclab"

[experiment.settings]
ambient_K = 294.15

[[runs]]
name = "a"
file = "a.csv"
role = "estimation"
columns = { time = "Time", T1 = { column = "T1", unit = "degC" }, \
T2 = { column = "T2", unit = "degC" }, H1 = "Q1", H2 = "Q2" }

[[runs]]
name = "b"
file = "b.csv"
role = "estimation"
columns = { time = "Time", T1 = { column = "T1", unit = "degC" }, \
T2 = { column = "T2", unit = "degC" }, H1 = "Q1", H2 = "Q2" }

[[runs]]
name = "c"
file = "c.csv"
role = "estimation"
"""


def _three(tmp_path):
    exp = tmp_path / "exp"
    exp.mkdir()
    (exp / "experiment.toml").write_text(TCLAB_TOML)
    t = np.arange(200) * 3.0
    temp = 21.0 + 0.01 * t
    q1 = np.where(t > 30, 50.0, 0.0)
    q1_bad = q1.copy()
    q1_bad[12] = 150.0
    (exp / "a.csv").write_text(
        "Time,T1,T2,Q1,Q2\n"
        + "".join(f"{a:g},{b:g},{b:g},{c:g},0\n" for a, b, c in zip(t, temp, q1_bad))
    )
    (exp / "b.csv").write_text(
        "Time,T1,T2,Q1,Q2\n"
        + "".join(f"{a + 1000:g},{b:g},{b:g},{c:g},0\n" for a, b, c in zip(t, temp, q1))
    )
    (exp / "c.csv").write_text(
        "t_s,T1_degC,T2_degC,H1_pct\n"
        + "".join(f"{a:g},{b:g},{b:g},{c:g}\n" for a, b, c in zip(t, temp, q1))
    )


SCENARIOS = {
    "my_experiment/run1.csv": _repeat_readme,
    "camera.exposure_ms": _exposure,
    "runs[1].file": _missing_val,
    "y_degC": _unit,
    "repeats the previous row": _repeat,
    "is not a number": _not_a_number,
    "contradicts the waveform": _contradiction,
    "problems in exp": _three,
}


def _documented_errors():
    out = []
    for doc in DOCS:
        text = (ROOT / doc).read_text()
        for m in FENCE.finditer(text):
            body = m.group(4)
            lines = [ln for ln in body.splitlines() if ln.startswith("greybox fit: error:")]
            if not lines or "FILE:LINE" in body:
                continue
            if lines[0].endswith("problems in exp:"):
                out.append(pytest.param(lines, id=f"{doc}:problems"))
            else:
                out += [pytest.param([ln], id=f"{doc}:{ln[20:60]}") for ln in lines]
    return out


def _matches(documented: str, actual: str) -> bool:
    """`documented` equals `actual`, where '...' may stand for any text."""
    pattern = ".*?".join(re.escape(part.strip()) for part in documented.split("..."))
    return re.fullmatch(pattern, actual) is not None


@pytest.mark.parametrize("lines", _documented_errors())
def test_documented_error_is_reproduced_verbatim(lines, tmp_path, monkeypatch, capsys):
    key = next(k for k in SCENARIOS if k in " ".join(lines))
    SCENARIOS[key](tmp_path)
    folder = next(p.name for p in tmp_path.iterdir() if p.is_dir())
    rc = _greybox(["fit", folder, "--out", "out", "--quiet"], tmp_path, monkeypatch)
    stderr = capsys.readouterr().err
    assert rc == 2, stderr[-2000:]
    assert not (tmp_path / "out").exists()  # nothing written
    actual = stderr.strip().splitlines()
    assert len(actual) == len(lines), actual
    for doc, got in zip(lines, actual):
        assert _matches(doc, got), f"\ndocumented: {doc}\nactual:     {got}"


def test_every_repository_path_the_docs_name_exists():
    """A file or folder of the repository the docs name (`greybox/...`, `benchmarks/...`,
    `tests/...`, `experiments/...`, in backticks) is where they say: a module renamed or
    moved must take its mention along (DEVELOPING.md's layout table had kept fourteen old
    module names and one old path). A bare module name (`verdict.py`) must be some file's
    name. Built artefacts (`greybox/_builtin_models`, packed into wheels) are exempt."""
    built = {"greybox/_builtin_models"}
    named = re.compile(r"`((?:greybox|benchmarks|tests|experiments|models)/[\w./-]*)`")
    module = re.compile(r"`(\w+\.py)`")  # a bare module name: some file of the repository
    tops = ("greybox", "tests", "benchmarks", "experiments", "models", "notebooks", ".ci")
    basenames = {f.name for top in tops for f in (ROOT / top).rglob("*.py")}
    basenames |= {f.name for f in ROOT.glob("*.py")}
    missing = []
    for doc in DOCS:
        text = (ROOT / doc).read_text()
        for path in named.findall(text):
            path = path.rstrip("/.")
            if path in built or any(c in path for c in "{*"):
                continue
            if not (ROOT / path).exists():
                missing.append(f"{doc}: {path}")
        missing += [f"{doc}: {name}" for name in module.findall(text) if name not in basenames]
    assert not missing, "\n".join(missing)
