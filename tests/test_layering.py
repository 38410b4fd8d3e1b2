"""The layering, read from the imports: the core never reaches the edges, io never names a
device, and notebooks, experiments and models use the public API only (benchmarks may time
private parts)."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
EDGE = {"greybox.io", "greybox.cli", "greybox._plots", "greybox._report", "greybox._registry",
        "greybox._usercode", "greybox.video"}  # fmt: skip
EDGE_MODULES = {"_plots.py", "_report.py", "_registry.py", "_usercode.py", "video.py", "__init__.py", "__main__.py"}


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


def _core_files():
    lib = ROOT / "greybox"
    files = [p for p in lib.glob("_*.py") if p.name not in EDGE_MODULES]
    files += list((lib / "blocks").glob("*.py")) + list((lib / "blackbox").glob("*.py"))
    return files


def test_there_is_a_core_to_check():
    names = {p.name for p in _core_files()}
    assert {"_fit.py", "_simulate.py", "_spec.py", "_device.py", "_thermal.py"} <= names


@pytest.mark.parametrize("path", _core_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_core_never_imports_edges_or_devices(path):
    bad = {
        m
        for m in _imports(path)
        if any(m == e or m.startswith(e + ".") for e in EDGE) or m.split(".")[0] == "models"
    }
    assert not bad, f"{path.name} imports {sorted(bad)}"


@pytest.mark.parametrize(
    "path", sorted((ROOT / "greybox" / "io").glob("*.py")), ids=lambda p: p.name
)
def test_io_never_imports_a_specific_device(path):
    text = path.read_text()
    bad = {m for m in _imports(path) if m.split(".")[0] in ("models", "greybox_builtin_devices")}
    assert not bad and "chevron_laser" not in text and "tclab" not in text, path.name


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
