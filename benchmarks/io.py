"""What a user waits for outside the fit itself: reading a large run CSV, `greybox --help`,
and the longest silence of `greybox demo` (seconds between two lines it prints).

- CSV: 300,000 rows x 5 columns (a TCLab-style log at 6 significant digits, some empty
  cells), read by greybox's run-CSV reader (values and line numbers) and by pandas.read_csv
  (the reference), best of 5 each in the same process; the ratio is greybox / pandas.
- `greybox --help`: wall time of a fresh `python -m greybox --help` process, best of 3.
- `greybox demo`: the whole command in a subprocess; every stdout/stderr line is time-stamped
  on arrival, and the longest gap (start to first line, between lines, last line to exit)
  is reported. Skip it with --no-demo (it fits the demo data: a minute or more).
- process-noise `greybox fit`: the same measurement on the three-state stochastic RC building
  folder of the tests (tests/rc_folder.py, 300 frames of tests/rc3_reference.py; maximum
  likelihood through the Kalman filter, BFGS + Newton, 12 parameters): a few minutes on a
  loaded machine. `process_fit_longest_silence_s` is its longest gap after the first line
  (Python's start-up and `import greybox` before it are `first_line_s`), and the lines
  around the gap name the silent phase. Skip it with --no-process.

Run: .venv/bin/python benchmarks/io.py [--no-demo] [--no-process]   (needs pandas: the
dataframe extra); --smoke reads 3,000 rows and runs neither command.
Last line: one JSON object.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
# the script's own folder would put this file first as `io`: the repository root instead
sys.path[0] = str(ROOT)

N_ROWS = 300_000


def write_log(path: Path) -> None:
    rng = np.random.default_rng(0)
    t = np.arange(N_ROWS) * 1.0
    cols = [t, 21 + rng.standard_normal(N_ROWS), 22 + rng.standard_normal(N_ROWS)]
    cols += [rng.uniform(0, 100, N_ROWS), rng.uniform(0, 100, N_ROWS)]
    lines = ["t_s,T1_degC,T2_degC,H1_pct,H2_pct"]
    for k, row in enumerate(zip(*cols)):
        cells = [f"{v:.6g}" for v in row]
        if k % 997 == 5:
            cells[1] = ""  # a dropped reading
        lines.append(",".join(cells))
    path.write_text("\n".join(lines) + "\n")


def best_of(fn, n: int) -> float:
    best = np.inf
    for _ in range(n):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return float(best)


def csv_read(folder: Path) -> dict:
    import pandas as pd

    from greybox.io import read_csv  # the run-CSV reader `greybox fit` uses

    path = folder / "log.csv"
    write_log(path)
    table = read_csv(path)
    ref = pd.read_csv(path).to_numpy(dtype=float)
    assert np.array_equal(table.values, ref, equal_nan=True), "greybox and pandas disagree"
    g = best_of(lambda: read_csv(path), 5)
    p = best_of(lambda: pd.read_csv(path), 5)
    print(f"CSV {N_ROWS} rows: greybox {g * 1e3:.0f} ms, pandas {p * 1e3:.0f} ms, {g / p:.1f}x")
    return {"rows": N_ROWS, "greybox_s": g, "pandas_s": p, "ratio": g / p}


def help_time() -> float:
    cmd = [sys.executable, "-m", "greybox", "--help"]
    t = best_of(lambda: subprocess.run(cmd, cwd=ROOT, capture_output=True, check=True), 3)
    print(f"greybox --help: {t:.2f} s")
    return t


def longest_silence(cmd, cwd) -> dict:
    """Run `cmd`; the longest time [s] without a line on stdout or stderr."""
    stamps = []  # (seconds since the start, the line)
    lock = threading.Lock()
    t0 = time.perf_counter()
    env = dict(os.environ, GREYBOX_COMPILE_CACHE="off")  # a first run's silences: it compiles
    proc = subprocess.Popen(
        cmd, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env
    )

    def pump(stream):
        for line in stream:
            with lock:
                stamps.append((time.perf_counter() - t0, line.rstrip()[:160]))

    threads = [threading.Thread(target=pump, args=(s,)) for s in (proc.stdout, proc.stderr)]
    for th in threads:
        th.start()
    rc = proc.wait()
    for th in threads:
        th.join()
    end = time.perf_counter() - t0
    stamps.sort()
    times = np.array([0.0, *(t for t, _ in stamps), end])
    texts = ["(start)", *(line for _, line in stamps), "(exit)"]
    gaps = np.diff(times)
    k = int(np.argmax(gaps))
    after = 1 + int(np.argmax(gaps[1:])) if gaps.size > 1 else 0
    return {
        "exit_status": rc,
        "total_s": end,
        "lines": len(stamps),
        "longest_gap_s": float(gaps[k]),
        "gap_ends_at_s": float(times[k + 1]),
        # the start-up (Python, `import greybox`) before the first line, and the rest
        "first_line_s": float(times[1]),
        "longest_gap_after_first_line_s": float(gaps[after]) if gaps.size > 1 else 0.0,
        # the silent phase: the line before the longest gap after the first line, and after
        "silent_after": texts[after],
        "silent_until": texts[after + 1],
    }


def process_fit_silence(folder: Path) -> dict:
    """The longest silence of a process-noise `greybox fit` (see the module docstring)."""
    from tests import rc3_reference
    from tests.rc_folder import write_folder

    runs = write_folder(folder, rc3_reference.simulate(seed=0, n=300))
    cmd = [sys.executable, "-m", "greybox", "fit", str(runs), "--out", str(folder / "result")]
    d = longest_silence(cmd, ROOT)
    print(
        f"process-noise fit: {d['total_s']:.0f} s, first line after {d['first_line_s']:.1f} s, "
        f"longest silence after it {d['longest_gap_after_first_line_s']:.1f} s "
        f"(after {d['silent_after']!r})"
    )
    return d


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--no-demo", action="store_true", help="skip the demo's silence")
    parser.add_argument(
        "--no-process", action="store_true", help="skip the process-noise fit's silence"
    )
    parser.add_argument(
        "--smoke",
        action="store_true",
        help="3,000 rows, no demo and no process-noise fit: checks the script runs",
    )
    args = parser.parse_args()
    if args.smoke:
        global N_ROWS
        N_ROWS, args.no_demo, args.no_process = 3_000, True, True
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        out["csv_read"] = csv_read(Path(tmp))
        out["help_s"] = help_time()
        if args.no_demo:
            out["demo_silence"] = None
        else:
            cmd = [sys.executable, "-m", "greybox", "demo", "--out", str(Path(tmp) / "demo")]
            out["demo_silence"] = longest_silence(cmd, ROOT)
            d = out["demo_silence"]
            print(
                f"greybox demo: longest silence {d['longest_gap_s']:.1f} s (first line after "
                f"{d['first_line_s']:.1f} s; longest after it "
                f"{d['longest_gap_after_first_line_s']:.1f} s)"
            )
        out["process_fit_silence"] = None if args.no_process else process_fit_silence(Path(tmp))
    pf = out["process_fit_silence"]
    out["process_fit_longest_silence_s"] = pf and pf["longest_gap_after_first_line_s"]
    print(json.dumps(out))


if __name__ == "__main__":
    main()
