"""Run several benchmark scripts with `--smoke` in this one process, one after another, as
`python benchmarks/NAME --smoke` would (run as `__main__`, the script's folder first on
sys.path, its own argv), and print one JSON line per script: its name, exit status, seconds, stdout
and stderr.

Used by tests/test_benchmarks_smoke.py: one Python + JAX start-up for several scripts instead
of one each, and compiled functions that two scripts share (the same batch solve in
batch_independence.py and gpu_many_devices.py) compiled once.

Usage: python tests/bench_smoke_runner.py NAME [NAME ...]
"""

import contextlib
import io
import json
import runpy
import sys
import time
import traceback
from pathlib import Path

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"


def run_one(name: str) -> dict:
    out, err = io.StringIO(), io.StringIO()
    argv, path = sys.argv[:], sys.path[:]
    sys.argv, sys.path = [str(BENCH / name), "--smoke"], [str(BENCH), *path]
    code, t0 = 0, time.perf_counter()
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            runpy.run_path(str(BENCH / name), run_name="__main__")
    except SystemExit as e:  # sys.exit(): None/0 is success, a string is a failure message
        if e.code not in (None, 0):
            code = e.code if isinstance(e.code, int) else 1
            if not isinstance(e.code, int):
                err.write(f"{e.code}\n")
    except BaseException:  # noqa: BLE001 (a crash of one script is its result, not ours)
        code = 1
        err.write(traceback.format_exc())
    finally:
        sys.argv, sys.path = argv, path
    return {"name": name, "returncode": code, "seconds": round(time.perf_counter() - t0, 2),
            "stdout": out.getvalue(), "stderr": err.getvalue()}  # fmt: skip


if __name__ == "__main__":
    real = sys.stdout
    for name in sys.argv[1:]:
        print(json.dumps(run_one(name)), file=real, flush=True)
