"""The layering, read from the imports, as package rules.

greybox is built in rings: `_model` (devices, specs, parameters, data, waveforms; with `blocks`)
<- `_simulate` <- `stochastic` (filters) <- `_estimate` (problem, back ends, results, verdicts)
<- `design` <- the edges (`io`, `report`, `video`, `_registry`) <- `cli`; `blackbox` sits beside
`_estimate`. A module may import its own ring and the rings inside it, never one outside, and
only modules that exist. The core never
imports a device; io never names one; cli commands do not import each other; notebooks,
experiments and models use the public API only (benchmarks may time private parts)."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LIB = ROOT / "greybox"
RING = {
    "greybox._model": 0,
    "greybox._log": 0,  # the library's logger
    "greybox._lazy": 0,  # names imported on first use
    "greybox._extras": 0,  # the message naming a missing optional extra
    "greybox._platform": 0,  # the processor a trace will run on (algorithm choices)
    "greybox._compile": 0,  # how the library compiles (jit with its XLA options)
    "greybox._collector": 0,  # the cyclic garbage collector paused around a batch
    "greybox.blocks": 0,
    "greybox._simulate": 1,
    "greybox.stochastic": 2,
    "greybox._estimate": 3,
    "greybox.blackbox": 3,  # black-box estimators share the metrics and residual tests
    "greybox.design": 4,
    "greybox.io": 5,
    "greybox.report": 5,
    "greybox.video": 5,
    "greybox._registry": 5,
    "greybox._usercode": 5,  # imports a user's device code, with consent
    "greybox.plots": 5,
    # public re-exports by job (no code of their own): each at the ring of what it re-exports
    "greybox.waveforms": 1,
    "greybox.metrics": 3,
    "greybox.uncertainty": 3,
    "greybox.population": 3,
    "greybox.parameters": 5,  # parameter_table comes from greybox.report
    "greybox.devices": 5,  # the registry of installed devices
    "greybox.cli": 6,
    "greybox.__main__": 6,
}
# what every command may import: the package and its helpers (no command)
CLI_SHARED = {"greybox.cli"} | {
    f"greybox.cli.{m}" for m in ("_common", "_ticker", "_trust", "_figures")
}


def _imports(path: Path) -> set[str]:
    """Absolute module names imported by `path` (relative imports resolved)."""
    tree = ast.parse(path.read_text())
    package = ".".join(path.relative_to(ROOT).with_suffix("").parts[:-1])
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(parts + ([base] if base else []))
            out.add(base)
            out |= {f"{base}.{a.name}" for a in node.names}
    return out


def _module(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _ring(module: str) -> int | None:
    for name, ring in sorted(RING.items(), key=lambda kv: -len(kv[0])):
        if module == name or module.startswith(name + "."):
            return ring
    return None


LIB_FILES = sorted(p for p in LIB.rglob("*.py") if p != LIB / "__init__.py")


def test_every_library_module_has_a_ring():
    assert [str(p.relative_to(ROOT)) for p in LIB_FILES if _ring(_module(p)) is None] == []


def test_the_rings_are_populated():
    modules = {_module(p) for p in LIB_FILES}
    packages = ("greybox._model", "greybox._simulate", "greybox._estimate", "greybox.stochastic")
    for package in packages:
        assert any(m.startswith(package + ".") for m in modules), package


@pytest.mark.parametrize("path", LIB_FILES, ids=lambda p: str(p.relative_to(ROOT)))
def test_no_import_reaches_outward(path):
    own = _ring(_module(path))
    greybox_imports = [
        m for m in _imports(path) if m.startswith("greybox.") and m != "greybox.__version__"
    ]
    bad = sorted(m for m in greybox_imports if _ring(m) is None or _ring(m) > own)
    homes = ("models", "greybox_builtin_devices")
    devices = sorted(m for m in _imports(path) if m.split(".")[0] in homes)
    if own < RING["greybox.io"]:
        bad += devices
    assert not bad, f"{path.relative_to(ROOT)} (ring {own}) imports {bad}"


@pytest.mark.parametrize("path", sorted((LIB / "io").glob("*.py")), ids=lambda p: p.name)
def test_io_never_names_a_specific_device(path):
    text = path.read_text()
    bad = {m for m in _imports(path) if m.split(".")[0] in ("models", "greybox_builtin_devices")}
    assert not bad and "chevron_laser" not in text and "tclab" not in text, path.name


@pytest.mark.parametrize("path", sorted((LIB / "cli").glob("_*.py")), ids=lambda p: p.name)
def test_cli_commands_do_not_import_each_other(path):
    me = _module(path)
    others = sorted(
        m
        for m in _imports(path)
        if m.startswith("greybox.cli.")
        and m not in CLI_SHARED
        and not any(m.startswith(s + ".") for s in CLI_SHARED - {"greybox.cli"})
        and not m.startswith(me)
    )
    assert not others, f"{path.name} imports {others}"


def _outer_files():
    # benchmarks may time private parts (the compiled solve alone); users' code may not
    for folder in ("notebooks", "experiments", "models"):
        yield from sorted((ROOT / folder).rglob("*.py"))


@pytest.mark.parametrize("path", list(_outer_files()), ids=lambda p: str(p.relative_to(ROOT)))
def test_outer_ring_uses_public_names_only(path):
    private = {
        m
        for m in _imports(path)
        if m.startswith("greybox") and any(part.startswith("_") for part in m.split(".")[1:])
    }
    assert not private, f"{path.relative_to(ROOT)} imports private {sorted(private)}"
