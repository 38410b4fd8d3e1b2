"""Regenerate the executed notebooks (`notebooks/*.ipynb`, with outputs) from their sources.

The sources are the jupytext percent-format scripts `notebooks/*.py` (diffable, no outputs).
The committed `.ipynb` files exist so that a reader on the web sees the figures; the test
suite checks that their code cells equal the sources, so outputs are never stale.

Run: .venv/bin/python notebooks/build.py            (all notebooks, full problem sizes)
     .venv/bin/python notebooks/build.py NAME ...   (only these, e.g. new_waveforms)
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
SKIP = {"build.py"}


def sources(names=()) -> list[Path]:
    found = sorted(p for p in HERE.glob("*.py") if p.name not in SKIP)
    if names:
        found = [p for p in found if p.stem in names]
    return found


def execute(source: Path, timeout_s: int = 1800):
    """The notebook built from `source`, executed headless in its own folder."""
    import jupytext
    import nbclient

    nb = jupytext.read(source)
    nb.metadata["kernelspec"] = {
        "name": "python3",
        "display_name": "Python 3",
        "language": "python",
    }
    client = nbclient.NotebookClient(
        nb, timeout=timeout_s, kernel_name="python3", resources={"metadata": {"path": str(HERE)}}
    )
    # The kernel must use its own inline backend (headless, figures become PNG outputs); a
    # MPLBACKEND=Agg inherited from a test run would silently swallow every plt.show().
    env = {k: v for k, v in os.environ.items() if k != "MPLBACKEND"}
    client.execute(env=env)
    return nb


def main(argv: list[str]) -> int:
    import nbformat

    for source in sources(argv):
        print(f"executing {source.name} ...", flush=True)
        nb = execute(source)
        nbformat.write(nb, source.with_suffix(".ipynb"))
        print(f"wrote {source.with_suffix('.ipynb').name}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
