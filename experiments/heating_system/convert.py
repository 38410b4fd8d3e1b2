"""Convert the DaISy heating-system record into this greybox experiment folder (run once).

Reads SOURCE (`heating_system.dat`: whitespace-separated time [s], lamp drive [V], plate
temperature [degC], 801 rows at 2 s) and writes, next to this file,

    estimation.csv   rows with t < 800 s (400 rows: the lamp at 9 and 4 V)
    validation.csv   rows with t >= 800 s (401 rows: 8, 3, 7 and 6 V; 3 V is below every
                     estimation level, so the validation run also tests extrapolation)

with columns `t_s, u_V, T_C` (values unchanged, written at full precision). The validation
run's clock starts at 0 (its first row is t = 800 s of the record); its lamp level before
that row, 4 V, is not in the file and does not matter: the run starts from its first reading.

Run: .venv/bin/python experiments/heating_system/convert.py SOURCE
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
SPLIT_S = 800.0
TS = 2.0


def load(path: Path) -> np.ndarray:
    d = np.loadtxt(path)
    if d.ndim != 2 or d.shape[1] != 3:
        raise ValueError(f"{path}: expected 3 columns (t, u, y), got shape {d.shape}")
    t = d[:, 0]
    if np.max(np.abs(np.diff(t) - TS)) > 1e-9:
        raise ValueError(f"{path}: the rows are not {TS} s apart")
    return d


def write(path: Path, rows: np.ndarray, t0: float) -> None:
    lines = ["t_s,u_V,T_C"]
    lines += [f"{t - t0:.1f},{float(u)!r},{float(y)!r}" for t, u, y in rows]
    path.write_text("\n".join(lines) + "\n")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("source", type=Path, help="heating_system.dat")
    args = ap.parse_args(argv)
    d = load(args.source)
    est = d[:, 0] < SPLIT_S
    write(HERE / "estimation.csv", d[est], 0.0)
    write(HERE / "validation.csv", d[~est], SPLIT_S)
    print(f"wrote {est.sum()} + {(~est).sum()} rows")


if __name__ == "__main__":
    main()
