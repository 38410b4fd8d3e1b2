"""A command run again: `greybox fit` of a folder in a fresh process, with and without the
compiled programs that an earlier run kept on disk (`greybox/io/_jax_setup.py`).

The identification loop runs the same commands over and over (fit, read the report, change
the folder, fit again; compare, then fit and simulate the preferred structure), each in a
new process that used to compile every program again. For each folder this script runs
`greybox fit FOLDER --quiet` in fresh processes: once with an empty cache folder (`cold_s`:
it compiles and writes), then `--repeats` times each, alternating, without a cache
(`GREYBOX_COMPILE_CACHE=off`, `off_s`) and with the filled one (`warm_s`); medians. It
checks that the warm run's params.json holds the same numbers, to the bit, as the run
without a cache (`same_result`: estimates, standard errors, covariance, noise, convergence
and cost, log-likelihood, fit %). Reported per folder, and over all folders `warm_speedup`
= off / warm (the median of their ratios), `cold_overhead` likewise (cold / off) and
`cache_mb` (the filled folders).

Run: .venv/bin/python benchmarks/rerun.py [--folders chevron_laser chevron_process microrobot]
[--repeats 2]; --smoke fits a one-run copy of the demo folder cold, then warm (the cold run
stands for the run without a cache).
Last line: one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = ("chevron_laser", "chevron_process", "microrobot")
SMOKE_HELP = "smallest setting (a one-run folder, fitted cold then warm): checks the script runs"
# what must not change when the programs come from the cache
SAME = (
    "parameters", "raw", "covariance_raw", "standard_errors", "sigma", "convergence",
    "log_likelihood", "fit_percent",
)  # fmt: skip


def fit_once(folder: Path, out: Path, cache: str) -> tuple[float, dict]:
    """(wall seconds, params.json) of `greybox fit folder` in a fresh process."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_COMPILATION_CACHE")}
    env["GREYBOX_COMPILE_CACHE"] = cache
    shutil.rmtree(out, ignore_errors=True)
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "greybox", "fit", str(folder), "--out", str(out), "--quiet"],
        env=env,
        capture_output=True,
        text=True,
        timeout=1800,
    )
    wall = time.perf_counter() - t0
    if proc.returncode not in (0, 1):  # 1: written, not trustworthy (still a result)
        raise SystemExit(f"greybox fit {folder} failed ({proc.returncode}):\n{proc.stderr}")
    return wall, json.loads((out / "params.json").read_text())


def one_run_copy(tmp: Path) -> Path:
    """The demo folder with its first estimation run only (the smoke run's folder)."""
    src, dst = ROOT / "experiments" / "chevron_laser", tmp / "chevron_one_run"
    shutil.copytree(src, dst)
    toml = (dst / "experiment.toml").read_text()
    head, first, *_ = toml.split("\n[[runs]]\n")  # the first run is an estimation run
    (dst / "experiment.toml").write_text(head + "\n[[runs]]\n" + first)
    return dst


def measure(folder: Path, repeats: int, tmp: Path) -> dict:
    cache = tmp / f"cache-{folder.name}"
    out = tmp / "out"
    cold_s, doc_cold = fit_once(folder, out, str(cache))
    off, warm, same = [], [], True
    for _ in range(max(repeats, 1)):
        # --smoke (repeats 0): the cold run, which compiled everything, stands for "off"
        t_off, doc_off = fit_once(folder, out, "off") if repeats else (cold_s, doc_cold)
        t_warm, doc_warm = fit_once(folder, out, str(cache))
        off.append(t_off)
        warm.append(t_warm)
        same &= all(doc_off.get(k) == doc_warm.get(k) for k in SAME)
    size = sum(p.stat().st_size for p in cache.rglob("*") if p.is_file())
    row = {
        "off_s": round(statistics.median(off), 2),
        "cold_s": round(cold_s, 2),
        "warm_s": round(statistics.median(warm), 2),
        "cache_mb": round(size / 1e6, 2),
        "same_result": bool(same),
    }
    row["speedup"] = round(row["off_s"] / row["warm_s"], 2)
    print(f"{folder.name}: {row}", file=sys.stderr, flush=True)
    return row


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--folders", nargs="+", default=list(FOLDERS))
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--smoke", action="store_true", help=SMOKE_HELP)
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="greybox-rerun-") as tmp:
        tmp = Path(tmp)
        if args.smoke:
            folders, args.repeats = [one_run_copy(tmp)], 0
        else:
            folders = [ROOT / "experiments" / name for name in args.folders]
        rows = {f.name: measure(f, args.repeats, tmp) for f in folders}
    cold = [r["cold_s"] / r["off_s"] for r in rows.values()]
    out = {
        "warm_speedup": statistics.median(r["speedup"] for r in rows.values()),
        "cold_overhead": round(statistics.median(cold), 2),
        "same_result": all(r["same_result"] for r in rows.values()),
        "cache_mb": round(sum(r["cache_mb"] for r in rows.values()), 2),
        "folders": rows,
        "load_average_1min": round(os.getloadavg()[0], 2),
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
