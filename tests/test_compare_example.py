"""README.md's compare example runs as written: its command, on the shipped folder whose
candidates are the README's TOML block, and its stated outcome (the folder's data come from an
independent two-node + lag simulator, experiments/chevron_compare/generate.py)."""

import json
import re
import shlex
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SECTION = "## Is the structure right? Comparing candidates"


def _readme_example():
    text = (ROOT / "README.md").read_text()
    section = text[text.index(SECTION) :].split("\n## ", 1)[0]
    command = re.search(r"```sh\n(.*?)\n```", section, re.S).group(1).strip()
    toml = re.search(r"```toml\n(.*?)```", section, re.S).group(1)
    return command, toml


def test_the_readme_toml_is_the_candidates_of_the_folder_the_command_compares():
    command, toml = _readme_example()
    folder = ROOT / shlex.split(command)[2]
    assert toml in (folder / "experiment.toml").read_text()
    shipped = tomllib.loads((folder / "experiment.toml").read_text())["candidates"]
    assert shipped == tomllib.loads(toml)["candidates"]


def test_the_readme_compare_command_runs_as_written(tmp_path, monkeypatch):
    from greybox.cli import main

    command, _ = _readme_example()
    words = shlex.split(command)
    assert words[:2] == [".venv/bin/greybox", "compare"]
    (tmp_path / "experiments").symlink_to(ROOT / "experiments")  # the repository's paths
    monkeypatch.chdir(tmp_path)
    assert main([*words[1:], "--quiet"]) == 0
    out = tmp_path / words[words.index("--out") + 1]
    doc = json.loads((out / "compare.json").read_text())
    # what the README says it shows: the true structure preferred, by a wide AIC margin
    assert doc["preferred"] == "two nodes + lag"
    aic = {c["name"]: c["aic"] for c in doc["candidates"]}
    assert aic["one node"] - aic["two nodes + lag"] > 1000
    heads = {c["name"]: c["headline"]["verdict"] for c in doc["candidates"]}
    assert heads == {"one node": "structure rejected", "two nodes + lag": "valid"}
    # the estimates of the true structure cover the simulator's values
    truth = {"absorptance": 0.55, "thermal.resistance_K_per_W[0]": 4400.0,
             "thermal.resistance_K_per_W[1]": 2100.0, "thermal.lag_s": 0.004}  # fmt: skip
    best = next(c for c in doc["candidates"] if c["name"] == "two nodes + lag")
    for e in best["estimates"]:
        if e["path"] in truth:
            lo, hi = e["ci95"]
            assert lo <= truth[e["path"]] <= hi, e
