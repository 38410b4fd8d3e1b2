"""Every benchmark script still runs (issue 24, item 6): each one with `--smoke` (its smallest
setting) in a subprocess, its last line one JSON object with the keys its full run reports.

The scripts run in two processes side by side (the machine has two cores), several scripts
one after another in each (tests/bench_smoke_runner.py: each script as `__main__` with its own
argv, as the command line runs it), so Python and JAX start twice instead of once per script
and a compiled function two scripts share is compiled once. A script that is not listed here
fails the test, so a new benchmark cannot be added without a smoke run.
"""

import json
import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks"

# keys each script's last JSON line must carry (present in the full run's line as well)
KEYS = {
    "batch_independence.py": {"max_rel", "steps_differ", "ok_differ", "backend"},
    "blackbox.py": {"arx_speedup_vs_sippy", "armax_speedup_vs_sippy", "armax_fit_pct"},
    "compare.py": {"compare_4_candidates_s", "candidates", "target_s", "per_candidate_s"},
    "design.py": {"det_gain", "predicted_se_ratio", "measured_se_ratio", "replicates"},
    "fit_chevron.py": {"compile_s", "zoh_fit_s", "adaptive_fit_s", "ratio_vs_scipy"},
    "gpu_many_devices.py": {
        "backend",
        "solve_fits_per_min",
        "batch_fits_per_min",
        "cpu_agreement_max_rel",
        "batch_independence_max_rel",
        "shuffle_pass",
    },
    "io.py": {
        "csv_read",
        "help_s",
        "demo_silence",
        "process_fit_silence",
        "process_fit_longest_silence_s",
    },
    "kalman.py": {
        "loglik_grad_s",
        "numpy_loglik_s",
        "speedup",
        "loglik_rel_diff",
        "ekf_grad_over_value",
    },
    "many_devices.py": {
        "loop_fits_per_s",
        "batch_fits_per_min",
        "solve_share",
        "backend",
        "own_numbers_fits_per_s",
        "loop_with_bands_per_s",
        "loop_first_fit_s",
        "result_kb_per_device",
    },
    "memory.py": {"sizes", "within_30_percent", "worst_ratio"},
    "microrobot.py": {"detailed_1000_cycles_s", "play_1000_cycles_s"},
    "rerun.py": {"warm_speedup", "cold_overhead", "same_result", "cache_mb", "folders"},
    "shuffle_pass.py": {"numpy_s", "compiled_s", "compiled_speedup", "max_abs_diff", "backend"},
    "tclab.py": {"greybox_sae_val", "arx_sae_val", "greybox_structure", "horizon"},
    "track.py": {"frames_per_s", "baseline_frames_per_s", "speedup"},
    "whiteness.py": {"replicates"},
    "write_share.py": {"write_share", "compiles_after_fit", "write_s", "total_s"},
}
# the first process's scripts: the three that share gpu_many_devices.py's batch solve,
# write_share.py and memory.py (about 20 s unloaded, as the other ten together); the rest run
# in the second
FIRST = (
    "gpu_many_devices.py",
    "batch_independence.py",
    "many_devices.py",
    "write_share.py",
    "memory.py",
)
TIMEOUT_S = 600  # per process (about 20 s unloaded), on a loaded machine
RUNNER = ROOT / "tests" / "bench_smoke_runner.py"


def run_smoke(names):
    """{name: (exit status, stdout, stderr)} of each script; a script whose record is missing
    (the runner itself died) gets the runner's status and stderr."""
    env = dict(os.environ, PYTHONPATH=str(ROOT), JAX_PLATFORMS="cpu")
    proc = subprocess.run(
        [sys.executable, str(RUNNER), *names],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=TIMEOUT_S,
    )
    done = {}
    for line in proc.stdout.splitlines():
        if not line.startswith('{"name"'):  # anything else a script wrote to the real stdout
            continue
        rec = json.loads(line)
        done[rec["name"]] = (rec["returncode"], rec["stdout"], rec["stderr"])
    lost = (proc.returncode or 1, "", f"runner exit {proc.returncode}:\n{proc.stderr[-3000:]}")
    return {name: done.get(name, lost) for name in names}


@pytest.fixture(scope="module")
def smoke_runs():
    groups = [[n for n in sorted(KEYS) if n in FIRST], [n for n in sorted(KEYS) if n not in FIRST]]
    with ThreadPoolExecutor(max_workers=2) as pool:
        return {k: v for part in pool.map(run_smoke, groups) for k, v in part.items()}


def test_every_script_has_a_smoke_run():
    scripts = {p.name for p in BENCH.glob("*.py") if not p.name.startswith("_")}
    assert scripts == set(KEYS)
    for p in BENCH.glob("*.py"):
        assert "--smoke" in p.read_text(), f"{p.name}: no --smoke flag"


@pytest.mark.parametrize("name", sorted(KEYS))
def test_smoke_run_ends_with_its_json_line(smoke_runs, name):
    code, stdout, stderr = smoke_runs[name]
    assert code == 0, f"{name} failed:\n{stderr[-3000:]}"
    last = stdout.strip().splitlines()[-1]
    out = json.loads(last)
    assert isinstance(out, dict)
    missing = KEYS[name] - set(out)
    assert not missing, f"{name}: JSON line lacks {sorted(missing)}"
    if name == "rerun.py":  # the reference is the same fit compiled in its own process
        assert out["same_result"], "a fit loaded from the compile cache changed its numbers"
        assert out["cache_mb"] > 0, "the command kept no compiled program"
