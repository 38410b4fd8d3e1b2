"""Convert the EMPS benchmark .mat files into this greybox experiment folder (run once).

Reads `<source>/DATA_EMPS.mat` (estimation) and `<source>/DATA_EMPS_PULSES.mat` (validation)
and writes, next to this file, `estimation.csv` and `validation.csv` with columns

    t_s      sample time k * 1 ms [s] (the files' `t`, stored in single precision, is k * 1 ms
             to within 2e-8 s; the exact grid is written)
    qref_m   reference position `qg` [m]
    pulse_V  pulse added to the controller output [V] (`pulses_N`, which despite its name is
             0/5 V, DATA.md section 5; 0 for the estimation run)
    q_m      measured position `qm` [m]
    vir_V    recorded controller output `vir` [V] (not a device channel: the fit ignores it;
             study.py uses it for the force error)

All 24841 rows are kept: every row is one controller sample, and the closed-loop device
(`emps_device.py`) steps its digital controller once per row, so thinning the rows would change
the controller. With `--every N` only every N-th q_m is written (the others are left empty:
not fitted), which shortens the residual vector but not the simulation. With `--seconds S`
only the first S seconds are written (used for the quick test subset in `short/`).

Also writes `experiment.toml` (into OUT, default this folder) with the known initial state of
each run (first measured position and the central-difference velocity at the start).

Run: .venv/bin/python experiments/emps/convert.py SOURCE [--out DIR] [--seconds S]
where SOURCE is the folder holding the two .mat files (PROVENANCE.md says where it is from).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import scipy.io

HERE = Path(__file__).resolve().parent
TS = 1e-3
RUNS = (("estimation", "DATA_EMPS.mat"), ("validation", "DATA_EMPS_PULSES.mat"))


def load(path: Path) -> dict[str, np.ndarray]:
    d = scipy.io.loadmat(path)
    t = d["t"].ravel().astype(float)
    n = t.size
    k = np.arange(n)
    if np.max(np.abs(t - k * TS)) > 1e-6:
        raise ValueError(
            f"{path}: t is not the 1 ms grid (max deviation {np.max(np.abs(t - k * TS))})"
        )
    pulse = d["pulses_N"].ravel().astype(float) if "pulses_N" in d else np.zeros(n)
    return {
        "t_s": k * TS,
        "qref_m": d["qg"].ravel().astype(float),
        "pulse_V": pulse,
        "q_m": d["qm"].ravel().astype(float),
        "vir_V": d["vir"].ravel().astype(float),
    }


def write_csv(path: Path, cols: dict[str, np.ndarray], every: int) -> None:
    with open(path, "w") as f:
        f.write("t_s,qref_m,pulse_V,q_m,vir_V\n")
        for i in range(cols["t_s"].size):
            q = f"{cols['q_m'][i]:.9g}" if i % every == 0 else ""
            f.write(
                f"{cols['t_s'][i]:.3f},{cols['qref_m'][i]:.12g},{cols['pulse_V'][i]:g},{q},{cols['vir_V'][i]:.9g}\n"
            )


def toml(runs: dict[str, dict[str, np.ndarray]], description: str) -> str:
    lines = [
        "[experiment]",
        'device = "emps_device.py:SPEC"',
        f'description = "{description}"',
        "",
        "[model]",
        "v_eps_m_per_s = 0.001",
        "substeps = 2",
        "",
        "[fit]",
        'method = "zoh"   # a stepped device: one controller sample per CSV row',
        'loss = "l2"',
        "n_starts = 1",
        "max_steps = 100",
        'free = ["M_kg", "Fv_N_s_per_m", "Fc_N", "offset_N"]',
        "",
    ]
    for role, cols in runs.items():
        q = cols["q_m"]
        v0 = (q[2] - q[0]) / (2 * TS)
        lines += [
            "[[runs]]",
            f'name = "{role}"',
            f'file = "{role}.csv"',
            f'role = "{role}"',
            'waveform = { type = "logged" }',
            f"settings = {{ initial_q_m = {float(q[0])!r}, initial_v_m_per_s = {float(v0)!r} }}",
            "",
        ]
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("source", type=Path, help="folder with DATA_EMPS.mat, DATA_EMPS_PULSES.mat")
    parser.add_argument("--out", type=Path, default=HERE)
    parser.add_argument("--seconds", type=float, default=None, help="keep only the first S s")
    parser.add_argument("--every", type=int, default=1, help="write every N-th q_m only")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    runs = {}
    for role, name in RUNS:
        cols = load(args.source / name)
        if args.seconds is not None:
            keep = cols["t_s"] <= args.seconds + 1e-9
            cols = {k: v[keep] for k, v in cols.items()}
        write_csv(args.out / f"{role}.csv", cols, args.every)
        runs[role] = cols
    span = "full records" if args.seconds is None else f"first {args.seconds:g} s"
    description = (
        "EMPS benchmark (Janot, Gautier, Brunot 2019), closed loop qref -> q; "
        f"estimation DATA_EMPS, validation DATA_EMPS_PULSES; {span}"
    )
    (args.out / "experiment.toml").write_text(toml(runs, description))


if __name__ == "__main__":
    main()
