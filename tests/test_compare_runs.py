"""`greybox compare` across runs and with --strict, on the small mass-spring-damper of
DEVELOPING.md (a user's file device; data made with numpy, not greybox).

- Cross-run scoring: the sensor offset fitted per run is tested for equality between the two
  estimation runs. Where the true offsets are equal the test agrees (p above 0.01); where they
  differ by 50 noise standard deviations it flags the offset "run-specific". The statistic is
  checked against the closed form from the reported values and standard errors.
- --strict: data with two time constants and a zero (the sum of two first-order lags), which
  no mass-spring-damper can produce: the residual test
  rejects the preferred candidate's structure, so `compare --strict` exits 1 and plain
  `compare` exits 0, both writing the result.
"""

import json
import re
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import chi2

ROOT = Path(__file__).resolve().parents[1]
T = np.arange(0, 2, 0.01)
NOISE_M = 1e-4


def _device() -> str:
    text = (ROOT / "DEVELOPING.md").read_text()
    return re.search(r"<!-- device example: msd.py -->\n```python\n(.*?)```", text, re.S).group(1)


def msd_step(k=50.0, c=15.0, m=1.0, force=1.0):
    """Closed-form step response of m x'' + c x' + k x = F (overdamped), from rest."""
    r = np.roots([m, c, k]).real  # two negative real poles
    a, b = r
    return force / k * (1 + (b * np.exp(a * T) - a * np.exp(b * T)) / (a - b))


ONE = '[[candidates]]\nname = "light"\nmodel = { mass_kg = 1.0 }\n'


def write_folder(folder: Path, runs: dict, free: str, candidates: str = ONE) -> Path:
    """`runs`: name -> (step force [N] at t = 0, readings [m]); estimation runs, but a name
    starting with "v" is a validation run."""
    folder.mkdir()
    if not (folder.parent / "msd.py").exists():  # one device file: its code compiles once
        (folder.parent / "msd.py").write_text(_device())
    tables = []
    for name, (force, y) in runs.items():
        rows = "".join(f"{a:.3f},{b:.8g}\n" for a, b in zip(T, y))
        (folder / f"{name}.csv").write_text("t_s,x_m\n" + rows)
        tables.append(
            f'[[runs]]\nname = "{name}"\nfile = "{name}.csv"\n'
            f'role = "{"validation" if name.startswith("v") else "estimation"}"\n'
            f'waveform = {{ type = "steps", times_s = [0.0], F_N = [{force}], end_s = 2.0 }}\n'
        )
    (folder / "experiment.toml").write_text(
        '[experiment]\ndevice = "../msd.py:SPEC"\n\n[fit]\nloss = "l2"\n'
        f"free = {free}\n\n" + "\n".join(tables) + "\n" + candidates
    )
    return folder


PER_RUN_FREE = (
    '["stiffness_N_per_m", "damping_N_s_per_m", '
    '{ path = "readout.offset", per_run = true, unit = "m" }]'
)


def compare(folder, out, *extra):
    from greybox.cli import main

    rc = main(["compare", str(folder), "--out", str(out), "--quiet", *extra])
    return rc, json.loads((out / "compare.json").read_text())


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    return tmp_path_factory.mktemp("msd")


@pytest.fixture(scope="module")
def offsets(root):
    """compare.json of two folders: offsets (1 mm, 1 mm) and (1 mm, 6 mm), same noise."""
    rng = np.random.default_rng(3)
    x = msd_step()
    docs = {}
    for label, (o1, o2) in {"equal": (1e-3, 1e-3), "different": (1e-3, 6e-3)}.items():
        runs = {  # the same device under 1 N and 0.5 N steps
            "r1": (1.0, x + o1 + NOISE_M * rng.standard_normal(T.size)),
            "r2": (0.5, 0.5 * x + o2 + NOISE_M * rng.standard_normal(T.size)),
        }
        if label == "equal":  # and a validation run with the same offset
            runs["v3"] = (1.0, x + o1 + NOISE_M * rng.standard_normal(T.size))
        folder = write_folder(root / label, runs, PER_RUN_FREE)
        docs[label] = compare(folder, root / f"out-{label}")
    return docs


def _agreement(doc, name="light"):
    cand = next(c for c in doc["candidates"] if c["name"] == name)
    (a,) = cand["per_run_agreement"]
    return cand, a


def test_equal_per_run_offsets_agree_across_runs(offsets):
    rc, doc = offsets["equal"]
    assert rc == 0
    cand, a = _agreement(doc)
    assert a["path"] == "readout.offset" and a["runs"] == ["r1", "r2", "v3"] and a["dof"] == 2
    assert a["validation_runs"] == ["v3"]
    assert not a["run_specific"] and a["p_value"] > 0.01, a
    assert a["mean"] == pytest.approx(1e-3, abs=5 * max(a["se"]))


def test_different_per_run_offsets_are_run_specific(offsets):
    rc, doc = offsets["different"]
    cand, a = _agreement(doc)
    assert a["run_specific"] and a["p_value"] < 1e-10, a
    assert a["values"] == pytest.approx([1e-3, 6e-3], abs=5e-5)
    # the joint-covariance statistic against the closed form with independent errors: the
    # same order (the shared stiffness correlates the two offsets a little)
    independent = (a["values"][0] - a["values"][1]) ** 2 / (a["se"][0] ** 2 + a["se"][1] ** 2)
    assert 0.25 * independent < a["statistic"] < 4 * independent
    assert chi2.sf(a["statistic"], 1) == pytest.approx(a["p_value"], rel=1e-6)


def test_compare_md_reports_the_run_specific_parameter(offsets, root):
    md = (root / "out-different" / "compare.md").read_text()
    assert "## Per-run parameters across runs" in md
    row = next(ln for ln in md.splitlines() if ln.startswith("| light | `readout.offset`"))
    assert "run-specific" in row
    md_equal = (root / "out-equal" / "compare.md").read_text()
    row = next(ln for ln in md_equal.splitlines() if ln.startswith("| light | `readout.offset`"))
    assert "agrees across runs" in row


def test_strict_exits_1_when_the_preferred_structure_is_rejected(root, tmp_path):
    rng = np.random.default_rng(5)
    # two first-order lags in parallel (time constants 0.05 s and 1 s): a zero no
    # mass-spring-damper has, so the residuals of every candidate are far from white
    y = 0.01 * (1 - np.exp(-T / 0.05)) + 0.01 * (1 - np.exp(-T / 1.0))
    y = y + NOISE_M * rng.standard_normal(T.size)
    free = '["stiffness_N_per_m", "damping_N_s_per_m"]'
    folder = write_folder(root / "rejected", {"r1": (1.0, y)}, free)
    rc, doc = compare(folder, tmp_path / "plain")
    assert rc == 0, doc
    best = next(c for c in doc["candidates"] if c["name"] == doc["preferred"])
    assert best["headline"]["verdict"] == "structure rejected", best["headline"]
    assert "misses dynamics" in best["residuals"]
    rc_strict, doc_strict = compare(folder, tmp_path / "strict", "--strict")
    assert rc_strict == 1
    assert doc_strict["preferred"] == doc["preferred"]  # the same result, written either way


def _est(path, run, value, se):
    from types import SimpleNamespace

    return SimpleNamespace(path=path, experiment=run, value=value, se=se, unit="m")


def test_the_wald_statistic_matches_its_closed_form():
    """Two correlated estimation values and one independent validation value: the statistic
    equals the closed form of the Wald test (raw coordinates = values, so no delta method)."""
    from greybox._estimate.compare import run_agreement

    # estimation runs: values 1.0, 1.3, sd 0.1, 0.2, correlation 0.5; a shared parameter too
    est = [_est("k", None, 5.0, 1.0), _est("off", "a", 1.0, 0.1), _est("off", "b", 1.3, 0.2)]
    cov = np.array([[1.0, 0.0, 0.0], [0.0, 0.01, 0.01], [0.0, 0.01, 0.04]])
    (a,) = run_agreement(est, cov)
    assert a["statistic"] == pytest.approx(0.3**2 / (0.01 + 0.04 - 2 * 0.01))
    assert a["p_value"] == pytest.approx(chi2.sf(3.0, 1)) and not a["run_specific"]
    # one estimation run and a validation run: independent, X^2 = d^2 / (s1^2 + s2^2)
    (b,) = run_agreement(est[:2], cov[:2, :2], validation=[_est("off", "v", 1.5, 0.1)])
    assert b["statistic"] == pytest.approx(0.25 / 0.02) and b["run_specific"]
    assert b["runs"] == ["a", "v"] and b["validation_runs"] == ["v"]
    # three runs, independent errors: X^2 = sum (v_i - weighted mean)^2 / se_i^2
    v, se = np.array([1.0, 1.3, 0.8]), np.array([0.1, 0.2, 0.15])
    three = [_est("off", r, x, s) for r, x, s in zip("abc", v, se)]
    (c,) = run_agreement(three)
    mean = np.sum(v / se**2) / np.sum(1 / se**2)
    assert c["statistic"] == pytest.approx(np.sum((v - mean) ** 2 / se**2))
    assert c["mean"] == pytest.approx(mean) and c["dof"] == 2
