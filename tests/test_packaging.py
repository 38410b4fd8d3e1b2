"""Packaging facts a user relies on: the license file, declared dependencies (every module
greybox imports is declared, in the base install or an extra), the typing marker, the
editable-install mode, and greybox's logger (Dask's records go through it)."""

import ast
import io
import logging
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
# import name -> distribution name, where they differ
DISTRIBUTION = {
    "skimage": "scikit-image",
    "imageio_ffmpeg": "imageio-ffmpeg",
    "distributed": "dask",  # dask[distributed]
    "cloudpickle": "dask",  # a dependency of dask itself
}


def _requirement_names(reqs) -> set:
    out = set()
    for r in reqs:
        name = r.split(";")[0].split("[")[0]
        for sep in "<>=!~ ":
            name = name.split(sep)[0]
        out.add(name.strip().lower())
    return out


def test_license_file_and_typing_marker():
    assert PYPROJECT["project"]["license"] == "MIT"
    text = (ROOT / "LICENSE").read_text()
    assert text.startswith("MIT License") and "WITHOUT WARRANTY" in text
    assert (ROOT / "greybox" / "py.typed").is_file()


def test_every_imported_module_is_declared():
    declared = _requirement_names(PYPROJECT["project"]["dependencies"])
    for extra in PYPROJECT["project"]["optional-dependencies"].values():
        declared |= _requirement_names(extra)
    stdlib = set(sys.stdlib_module_names)
    missing = set()
    for path in (ROOT / "greybox").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            for n in names:
                top = n.split(".")[0]
                if top in stdlib or top in ("greybox", "__future__"):
                    continue
                if DISTRIBUTION.get(top, top).lower().replace("_", "-") not in {
                    d.replace("_", "-") for d in declared
                }:
                    missing.add((top, path.name))
    assert not missing, f"imported but not declared in pyproject.toml: {sorted(missing)}"


def test_editable_install_exposes_only_greybox():
    wheel = PYPROJECT["tool"]["hatch"]["build"]["targets"]["wheel"]
    assert wheel["packages"] == ["greybox"] and wheel["dev-mode-exact"] is True
    assert "force-include" not in wheel  # the packed folders: regular wheels only (hook)
    assert "models" in (ROOT / "hatch_build.py").read_text()


def test_dask_records_go_through_the_greybox_logger():
    from greybox._log import route_dask_logs

    dask_logger = logging.getLogger("distributed.core")
    route_dask_logs()
    buf = io.StringIO()
    handler = logging.StreamHandler(buf)
    logging.getLogger("greybox").addHandler(handler)
    try:
        dask_logger.warning("heartbeat to the scheduler failed")
    finally:
        logging.getLogger("greybox").removeHandler(handler)
    assert buf.getvalue().strip() == "heartbeat to the scheduler failed"
    assert logging.getLogger("distributed").propagate is False
