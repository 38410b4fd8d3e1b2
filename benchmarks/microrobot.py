"""Speed of 1,000 laser cycles of the micro-robot: detailed friction balance vs play surrogate.

Pulse train at the optimum period (16 ms, 50 % duty, 20 mW), 16 steps of 1 ms per cycle
(16,000 steps), nominal model (PHYSICS.md §14), timed after compilation (best of 5 wall-clock
runs; the process CPU time of the best run is printed too, since on a shared machine the wall
clock includes waiting for a core). Targets (2-core CPU): detailed < 1 s, play < 50 ms.
Ends with one JSON line.
Run: .venv/bin/python benchmarks/microrobot.py [--smoke]
"""

import argparse
import json
import os
import sys
import time

import jax

import greybox

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

mr = greybox.device_module("microrobot")  # noqa: E402

CYCLES, STEPS_PER_CYCLE, PERIOD_S, POWER_W = 1000, 16, 0.016, 0.02


SMOKE_HELP = "smallest setting (a few seconds): checks that the script still runs"

def timed(model, cycles=CYCLES, repeats=5) -> tuple[float, float, float]:
    """(best wall time [s], its process CPU time [s], final X [m])."""
    run = jax.jit(lambda m: mr.pose_history(m, PERIOD_S, 0.5, POWER_W, cycles, STEPS_PER_CYCLE))
    states = run(model).block_until_ready()  # compile
    best, cpu = float("inf"), float("inf")
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        states = run(model).block_until_ready()
        wall = time.perf_counter() - t0
        if wall < best:
            best, cpu = wall, time.process_time() - c0
    return best, cpu, float(states[-1, 4])


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--smoke", action="store_true", help=SMOKE_HELP)
    args = ap.parse_args(argv)
    cycles, repeats = (10, 1) if args.smoke else (CYCLES, 5)
    load_before = os.getloadavg()[0]
    play_s, play_cpu, play_x = timed(mr.SPEC.model(substeps=1), cycles, repeats)
    det_s, det_cpu, det_x = timed(mr.SPEC.model(substeps=1, contacts="friction"), cycles, repeats)
    load = max(load_before, os.getloadavg()[0])
    print(
        f"{cycles} cycles x {STEPS_PER_CYCLE} steps, period {PERIOD_S * 1e3:.0f} ms; "
        f"{os.cpu_count()} cores, 1-min load average {load:.2f}"
    )
    print(
        f"play operator  : {play_s * 1e3:8.2f} ms wall, {play_cpu * 1e3:8.2f} ms CPU  "
        f"(X = {play_x * 1e6:.3f} um)"
    )
    print(
        f"detailed (5x5) : {det_s * 1e3:8.2f} ms wall, {det_cpu * 1e3:8.2f} ms CPU  "
        f"(X = {det_x * 1e6:.3f} um)"
    )
    print(f"ratio detailed/play: {det_s / play_s:.1f}")
    print(
        json.dumps(
            {
                "detailed_1000_cycles_s": det_s,
                "play_1000_cycles_s": play_s,
                "ratio_detailed_over_play": det_s / play_s,
                "detailed_cpu_s": det_cpu,
                "play_cpu_s": play_cpu,
                "load_average_1min": load,
                "cycles": cycles,
            }
        )
    )


if __name__ == "__main__":
    main()
