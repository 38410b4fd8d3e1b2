"""Convert the Park et al. (2020) TCLab runs into greybox experiment folders (run once).

Reads `<source>/1_Model/{2_Heaters,1_Heater}/{initial_models,validation}.csv` (columns Time,
H1, H2, T1, T2 in s, %, %, degC) and writes, next to this file, `two_heaters/` and
`one_heater/`, each with `estimation.csv`, `validation.csv` (columns t_s,H1_pct,H2_pct,T1_C,
T2_C; values unchanged, only renamed) and `experiment.toml` (known initial temperatures =
first measurement, in K).

Run: .venv/bin/python experiments/tclab/convert.py SOURCE
where SOURCE is the unpacked `CACE_2020_source` folder (see PROVENANCE.md for where it is from).
"""

import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
HEADER = "t_s,H1_pct,H2_pct,T1_C,T2_C"
SETS = {
    "two_heaters": ("2_Heaters", "both heaters stepped; paper's MIMO benchmark (T1 + T2)"),
    "one_heater": ("1_Heater", "heater 1 only (Q2 = 0); paper's SISO benchmark (T1)"),
}
ROLES = (("estimation", "initial_models.csv"), ("validation", "validation.csv"))


def _toml(device_set: str, description: str, runs: list[tuple[str, np.ndarray]]) -> str:
    lines = [
        "[experiment]",
        'device = "tclab"',
        f'description = "TCLab, Park et al. (2020) {device_set}: {description}"',
        "",
        "[fit]",
        'method = "adaptive"',
        'loss = "l2"',
        "n_starts = 1",
        "",
    ]
    for role, data in runs:
        t1_k, t2_k = data[0, 3] + 273.15, data[0, 4] + 273.15
        lines += [
            "[[runs]]",
            f'name = "{role}"',
            f'file = "{role}.csv"',
            f'role = "{role}"',
            'waveform = { type = "logged" }',
            f"settings = {{ initial_T1_K = {t1_k:.2f}, initial_T2_K = {t2_k:.2f} }}",
            "",
        ]
    return "\n".join(lines)


def main(source: Path) -> None:
    for folder, (sub, description) in SETS.items():
        out = HERE / folder
        out.mkdir(exist_ok=True)
        runs = []
        for role, name in ROLES:
            data = np.loadtxt(source / "1_Model" / sub / name, delimiter=",", skiprows=1)
            if data.shape[1] != 5 or not np.all(np.isfinite(data)):
                raise ValueError(f"{source / sub / name}: expected 5 finite columns")
            with open(out / f"{role}.csv", "w") as f:
                f.write(HEADER + "\n")
                for row in data:
                    f.write(",".join(repr(float(v)) for v in row) + "\n")
            runs.append((role, data))
        (out / "experiment.toml").write_text(_toml(sub, description, runs))


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit("usage: convert.py SOURCE  (the unpacked CACE_2020_source folder, PROVENANCE.md)")
    main(Path(sys.argv[1]))
