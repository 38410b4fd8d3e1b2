"""Writing a fit's result folder: its share of `greybox fit` and the compilations it triggers
(issue 24: "writing the result takes under 15 % of the wall time and triggers no compilation
after the fit").

Runs the work of `greybox fit experiments/tclab/two_heaters` in this process
(`greybox.cli._common.fit_experiment_dir`: load, fit, validate, write params.json, report.md,
figures, predictions/, metrics.csv) into a temporary folder, timing each phase off the
command's own progress lines, and counts XLA compilations (JAX's monitoring event of each
backend compile) before and after the "writing" line. `write_share` = write time / (load +
fit + write) time (Python start-up and imports left out, so the share is, if anything, an
overestimate of the command's); `compiles_after_fit` should be 0.

Measured (2-core CPU, quiet): 0.407 -> 0.111 when the writer stopped re-simulating (the fit
then took ~60 s). Since, the fit got ~8x faster (7.5 s, compiling included) while writing stayed
the figures' matplotlib work, so the share rose to 0.183 (writing 1.87 s, no compilation).
Drawing the residual tests' correlations as line collections instead of bars and PNGs at zlib
level 1 (2026-11-27): writing 1.87 -> 1.68 s, write_share 0.183 -> 0.167 (three alternating
runs each). PNGs compressed and written by a thread while the next figure is drawn (the same
bytes): writing 1.76 -> 1.45 s, write_share 0.173 -> 0.145 (three alternating runs each,
total 10.2 -> 10.0 s). What is left is matplotlib: its import (~0.3 s), the constrained layout
and tick text of six figures (~1 s), and 200 dpi rasters.
Then (2026-11-27, two alternating runs of f64b357 and 75f843b): the fit got faster (`_solve`
traces the model once: fit 7.97-8.21 -> 7.16-7.31 s, total 10.2-10.6 -> 9.5-9.7 s) while
writing stayed 1.44-1.55 s, so write_share rose from 0.141 to 0.160-0.163. Importing
matplotlib in a thread during the fit moved ~0.2 s from the writing to the fit (write_share
0.135-0.144) but the total did not fall (9.17-9.60 against 9.31-9.40 s: the import holds the
interpreter while the fit traces), so it was not kept.
Then (2026-11-27, three alternating runs of 2c36d26 and cf18462, load 1.2-1.5): a process
started before the fit (its imports on the idle core while the fit runs) draws half of the six
figures while this process draws the other half (`greybox.io._drawing.drawing_process`, the
same bytes): writing 1.53-1.57 -> 0.92-1.00 s, total 9.75-10.30 -> 9.09-9.26 s, fit unchanged
(7.34-7.84 and 7.35-7.41 s), write_share 0.150-0.158 -> 0.102-0.108. On a busy machine (the
1-minute load leaving under half a core idle) no process is started and the share is as before
(`drawing_process` in the JSON line says which). With the figures shared as they go and a
drawing process that imports no JAX (d98fa04 against 2c36d26, two alternating runs, the
machine slower that hour: totals 11.3-11.6 and 11.9-12.2 s): writing 1.86-1.92 -> 1.11-1.14
s, write_share 0.156-0.157 -> 0.099.
Then (2026-11-29, four alternating runs of 6177155 and this change, load under 0.6, a drawing
process each time): the fit had become faster again (5.6-6.0 s with its validation) and
writing was 1.16-1.28 s, write_share 0.163-0.176. The drawing process now draws the
estimation's figures (the estimation run's, the residual tests, the correlation: those the
validation cannot change) while the validation runs, into a folder of their own, and the
writer moves them in (`greybox.io._drawing.drawing_ahead`; a job whose data differs from the
writer's own is drawn again; the same bytes in every file): writing 0.62-0.68 s,
write_share 0.094-0.099, total 6.93-7.43 -> 6.57-6.82 s (the validation takes ~0.2 s longer
beside the drawing).

Run: .venv/bin/python benchmarks/write_share.py [--smoke] [--folder DIR]

`--smoke`: the same command on the demo's folder, experiments/chevron_laser (checks that the
script still runs; the share is not meaningful there). `drawing_process`: whether the load left
a core idle for the process that draws half the figures. Last line: one JSON object.
"""

import jax

jax.config.update("jax_enable_x64", True)

import argparse  # noqa: E402
import json  # noqa: E402
import shutil  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from greybox.cli._common import fit_experiment_dir  # noqa: E402
from greybox.io._drawing import spare_core  # noqa: E402

FOLDER = ROOT / "experiments" / "tclab" / "two_heaters"
# the smoke run's folder: the demo's (a ZOH model that compiles in about a second, and the
# folder the test suite fits most, so its compiled programs are often in the suite's cache)
SMOKE_FOLDER = ROOT / "experiments" / "chevron_laser"
SMOKE_HELP = "smallest setting (a few seconds): checks that the script still runs"
COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"


class Clock:
    """The progress callback of the command: records when each phase starts and how many
    compilations had happened by then."""

    def __init__(self, compiles):
        self.compiles = compiles
        self.marks = []

    def __call__(self, message: str) -> None:
        self.marks.append((message, time.perf_counter(), self.compiles[0]))

    def first(self, prefix: str):
        return next((t, n) for m, t, n in self.marks if m.startswith(prefix))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--smoke", action="store_true", help=SMOKE_HELP)
    ap.add_argument("--folder", default=str(FOLDER), help="experiment folder to fit")
    args = ap.parse_args(argv)
    compiles = [0]

    def count(event, _secs, **_kw):
        if event == COMPILE_EVENT:
            compiles[0] += 1

    jax.monitoring.register_event_duration_secs_listener(count)
    with tempfile.TemporaryDirectory() as tmp:
        folder = SMOKE_FOLDER if args.smoke else Path(args.folder)
        drawing_process = spare_core()  # what `fit_experiment_dir` decides, at the same load
        clock = Clock(compiles)
        t0 = time.perf_counter()
        fit_experiment_dir(folder, Path(tmp) / "result", clock)
        t_end = time.perf_counter()
        n_end = compiles[0]
        t_fit, _ = clock.first("fitting")
        t_write, n_write = clock.first("writing")
        written = sorted(p.name for p in (Path(tmp) / "result").iterdir())
        shutil.rmtree(Path(tmp) / "result")
    total = t_end - t0
    out = {
        "write_share": round((t_end - t_write) / total, 4),
        "write_s": round(t_end - t_write, 3),
        "fit_s": round(t_write - t_fit, 3),
        "load_s": round(t_fit - t0, 3),
        "total_s": round(total, 3),
        "compiles_during_fit": n_write,
        "compiles_after_fit": n_end - n_write,
        "folder": str(folder.relative_to(ROOT)) if folder.is_relative_to(ROOT) else folder.name,
        "written": written,
        "drawing_process": drawing_process,
        "smoke": bool(args.smoke),
    }
    print(
        f"load {out['load_s']} s, fit + validation {out['fit_s']} s ({n_write} compilations), "
        f"writing {out['write_s']} s ({out['compiles_after_fit']} compilations): write share "
        f"{out['write_share']:.1%}"
    )
    print(json.dumps(out))


if __name__ == "__main__":
    main()
