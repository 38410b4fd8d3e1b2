"""Make `experiments/chevron_compare/` (synthetic, fixed seed): the README's compare example.

A two-node + elongation-lag chevron under a pulsed laser, filmed at 250 fps, simulated by the
independent numpy/scipy reference of tests/test_chevron_structures.py (matrix-exponential ZOH
on a 0.1 ms grid, exact kinematics, trapezoid exposure averaging; not greybox), so the true
structure is known: `greybox compare` should prefer "two nodes + lag" and reject "one node".

Usage (from the repository root):
    .venv/bin/python experiments/chevron_compare/generate.py
"""

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
from tests.test_chevron_structures import simulate_run  # noqa: E402

SEED = 7
# (name, power mW, period ms, pulses, offset px); 50 % duty, 100 ms before, 200 ms after
RUNS = [
    ("a_20mW_160ms", 20, 160, 5, 300.0),
    ("b_30mW_60ms", 30, 60, 8, 302.0),
    ("v_25mW_100ms", 25, 100, 6, 301.0),
]


def main(out=Path(__file__).resolve().parent):
    rng = np.random.default_rng(SEED)
    for name, p, period, n, offset in RUNS:
        t, px, _ = simulate_run(p, period, n, offset, rng)
        rows = "".join(f"{a:.6f},{b:.5f}\n" for a, b in zip(t, px))
        (out / f"{name}.csv").write_text("t_s,y_px\n" + rows)


if __name__ == "__main__":
    main()
