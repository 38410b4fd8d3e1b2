"""experiments/README.md documents every table and key the loader accepts, and README.md's
exit-status table is the code's (`greybox._estimate.verdict.EXIT_STATUS`)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from greybox._estimate.verdict import EXIT_STATUS
from greybox.io._experiment_set import accepted_keys

ROOT = Path(__file__).resolve().parents[1]
FORMAT_DOC = (ROOT / "experiments" / "README.md").read_text(encoding="utf-8")


def _documented(key: str) -> bool:
    """A key is documented where it appears in backticks or as `key =` in a TOML example."""
    return f"`{key}`" in FORMAT_DOC or re.search(rf"^\s*{re.escape(key)}\s*=", FORMAT_DOC, re.M)


def _loader_keys():
    keys = dict(accepted_keys())
    from greybox.io._noise_table import NOISE_KEYS  # [noise] is read in io

    keys["noise"] = set(NOISE_KEYS)
    return keys


def test_every_top_level_table_is_documented():
    tables = accepted_keys()[""]
    missing = [t for t in tables if f"[{t}]" not in FORMAT_DOC and f"[[{t}]]" not in FORMAT_DOC]
    assert not missing, f"experiments/README.md does not document the tables {missing}"


@pytest.mark.parametrize("table", sorted(k for k in _loader_keys() if k))
def test_every_key_of_a_table_is_documented(table):
    missing = sorted(k for k in _loader_keys()[table] if not _documented(k))
    assert not missing, f"experiments/README.md does not document [{table}] keys {missing}"


def test_an_undocumented_key_is_caught():
    # the check itself can fail: a key the document never names is reported
    assert not _documented("no_such_key_anywhere")


def test_readme_exit_status_table_is_the_codes():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    rows = dict(re.findall(r"^\| (\d+) \| (.+) \|$", text, re.M))
    assert {int(k): v for k, v in rows.items()} == EXIT_STATUS
