"""Every notebook executes headless, and committed outputs are never stale.

Notebooks are jupytext percent scripts (`notebooks/*.py`): reviewable diffs, no outputs in
the source. Executing them through nbclient (a real kernel with the inline backend, which
is headless) is what a user running them top to bottom does. Under CI=true the notebooks
shrink their problem sizes.
"""

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "notebooks"))
import build  # noqa: E402

NOTEBOOKS = build.sources()


@pytest.mark.slow
@pytest.mark.parametrize("source", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_executes_headless(source, monkeypatch):
    monkeypatch.setenv("CI", "true")  # small problem sizes, as in CI
    nb = build.execute(source, timeout_s=600)
    errors = [
        o
        for c in nb.cells
        if c.cell_type == "code"
        for o in c.get("outputs", [])
        if o.get("output_type") == "error"
    ]
    assert not errors
    images = [
        o
        for c in nb.cells
        if c.cell_type == "code"
        for o in c.get("outputs", [])
        if "image/png" in o.get("data", {})
    ]
    assert images, "a notebook with no figure is not doing its job"


@pytest.mark.parametrize("source", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_committed_notebook_matches_its_source(source):
    import jupytext
    import nbformat

    committed = source.with_suffix(".ipynb")
    assert committed.exists(), f"run `.venv/bin/python notebooks/build.py {source.stem}`"
    expected = [c.source for c in jupytext.read(source).cells if c.cell_type == "code"]
    actual = [
        c.source for c in nbformat.read(committed, as_version=4).cells if c.cell_type == "code"
    ]
    assert actual == expected, f"stale: rerun `.venv/bin/python notebooks/build.py {source.stem}`"
    assert any(
        o
        for c in nbformat.read(committed, as_version=4).cells
        if c.cell_type == "code"
        for o in c.get("outputs", [])
    ), "committed without outputs"
