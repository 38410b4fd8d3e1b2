"""Black-box baselines for results.md: ARX [na nb nk] with an offset on this folder's runs.

Estimated by least squares on estimation.csv (lamp drive in V, plate temperature in degC, the
2 s samples as they are), scored on validation.csv, every order na = nb = 1..3 with
nk = 1; printed per order: the number of coefficients and the simulation and one-step fit %
(MATLAB `compare`) on both runs. The offset carries the ambient and the mean lamp heat, so
the runs are not detrended (a validation run's own mean would be information from its
outputs).

Run: .venv/bin/python experiments/heating_system/arx.py
"""

from pathlib import Path

import numpy as np

from greybox import blackbox as bb

HERE = Path(__file__).resolve().parent


def load(name: str) -> bb.UniformData:
    d = np.loadtxt(HERE / f"{name}.csv", delimiter=",", skiprows=1)
    return bb.UniformData(d[:, 1], d[:, 2], float(d[1, 0] - d[0, 0]), name=name)


def main() -> None:
    est, val = load("estimation"), load("validation")
    print(
        "| ARX [na nb nk] + offset | coefficients | estimation fit %: simulation, one-step "
        "| validation fit %: simulation, one-step |"
    )
    print("|---|---|---|---|")
    for n in (1, 2, 3):
        m = bb.fit_arx(est, n, n, 1, offset=True)
        fits = [
            (bb.compare(m, d).fit_percent[0], bb.compare(m, d, k=1).fit_percent[0])
            for d in (est, val)
        ]
        print(
            f"| [{n} {n} 1] | {m.parameters.size} | {fits[0][0]:.1f}, {fits[0][1]:.1f} | "
            f"{fits[1][0]:.1f}, {fits[1][1]:.1f} |"
        )


if __name__ == "__main__":
    main()
