"""TCLab: stochastic grey-box (process noise + random-walk ambient per sensor, Kalman-filter
maximum likelihood) beside the deterministic grey-box and ARX [2 2 1], each horizon labelled.

For each folder (two_heaters, one_heater), read with greybox.io's experiment loader (the
folder's [model] options, per-run settings and [fit] free list):

- stochastic grey-box: the linear TCLab (the folder's structure without radiation, so the
  exact Kalman filter applies), process noise on the two heater nodes (one intensity), one
  random-walk ambient/offset state per sensor, measurement noise per sensor; fitted by
  `greybox.fit(..., noise=greybox.ProcessNoise(...))` on the estimation run, validated on the
  validation run with the parameters fixed (`greybox.validate`);
- deterministic grey-box: `greybox.fit` (free-run least squares) with the same model and free
  list, validated by `greybox.validate`;
- ARX [2 2 1] with offset (the paper's structure, `study.fit_arx22`, as compare.py fits it),
  one-step prediction (`blackbox.predict`) and simulation (`blackbox.simulate`).

Scores: SAE [degC] on the validation run, summed over the paper's scored sensors (both for
two_heaters, T1 for one_heater), in SIMULATION (the model driven by the heaters alone, from the
initial state) and in ONE-STEP prediction (each reading predicted from the readings before it).
A deterministic grey-box has no one-step predictor of its own (no noise model): n/a.

Run: .venv/bin/python experiments/tclab/stochastic.py   (writes stochastic.md next to it)
"""

import dataclasses
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE), str(HERE.parents[1])]

import numpy as np  # noqa: E402
import study  # noqa: E402
from tclab_data import uniform  # noqa: E402

import greybox  # noqa: E402
from greybox import blackbox as bb  # noqa: E402
from greybox.io import atomic_output_file, load_experiment_set  # noqa: E402

STRUCTURE = greybox.NoiseStructure(
    process_groups=(("heaters", (0, 1)),), disturbances=("ambient_random_walk",)
)
# The TMP36 readings are quantised in steps of 3.3 V / 1024 -> 0.322 K, a noise of at least
# 0.322 / sqrt(12) = 0.093 K: a log-normal prior (median 0.093 K, log-sd 0.5) on each sensor's
# measurement sd. Without it the one_heater fit drove sensor 2's sd to 1e-154 K (T2 barely
# moves and repeats the same quantised reading: a degenerate likelihood spike).
QUANTUM_SD_K = 3.3 / 1024 * 100 / np.sqrt(12)
NOISE_PRIORS = {
    f"measurement.{c}": {"prior_median": QUANTUM_SD_K, "prior_log_sd": 0.5} for c in ("T1", "T2")
}
UNITS = {
    "process.heaters": "K^2/s",
    "measurement.T1": "K",
    "measurement.T2": "K",
    "output_walk.T1": "K^2/s",
    "output_walk.T2": "K^2/s",
}


def sae(y, z, outputs) -> float:
    r = (np.asarray(y) - np.asarray(z))[:, list(outputs)]
    return float(np.nansum(np.abs(r)))


def analyse(folder: str, say=print) -> dict:
    fs = load_experiment_set(HERE / folder)
    one = folder == "one_heater"
    outputs = (0,) if one else (0, 1)
    spec = fs.spec
    options = {**fs.options, "radiation": False}
    model = spec.model(options)
    (est,), (val,) = fs.estimation, fs.validation
    out = {"folder": folder, "outputs": outputs, "options": options, "free": fs.free}

    t0 = time.perf_counter()
    sdev = greybox.stochastic.stochastic_device(
        model, STRUCTURE, outputs=spec.outputs, inputs=spec.inputs
    )
    free = list(fs.free) + [
        dataclasses.replace(p, **NOISE_PRIORS.get(p.path, {}))
        for p in greybox.stochastic.noise_parameters(sdev, UNITS)
    ]
    res = greybox.fit(
        sdev,
        [est],
        free,
        noise=greybox.ProcessNoise(STRUCTURE),
        n_starts=1,
        progress=lambda m: say(f"[{folder}] {m}"),
    )
    (vd,) = greybox.validate(res, [val]).runs
    out["stochastic"] = res
    out["stochastic_val"] = vd
    out["t_stochastic"] = time.perf_counter() - t0
    say(f"[{folder}] stochastic fit {out['t_stochastic']:.1f} s, status {res.status}")

    # the folder's own (nonlinear, radiating) board: extended Kalman filter, and its
    # deterministic fit with the folder's [fit] settings, as `greybox fit` makes it
    t0 = time.perf_counter()
    sdev_nl = greybox.stochastic.stochastic_device(
        fs.model, STRUCTURE, outputs=spec.outputs, inputs=spec.inputs
    )
    free_nl = list(fs.free) + [
        dataclasses.replace(p, **NOISE_PRIORS.get(p.path, {}))
        for p in greybox.stochastic.noise_parameters(sdev_nl, UNITS)
    ]
    res_nl = greybox.fit(
        sdev_nl,
        [est],
        free_nl,
        noise=greybox.ProcessNoise(STRUCTURE),
        n_starts=1,
        progress=lambda m: say(f"[{folder}] EKF: {m}"),
    )
    (vd_nl,) = greybox.validate(res_nl, [val]).runs
    out["ekf"], out["ekf_val"] = res_nl, vd_nl
    out["t_ekf"] = time.perf_counter() - t0
    det_nl = greybox.fit(fs.model, [est], fs.free, **fs.fit_options)
    dval_nl = greybox.validate(det_nl, [val])
    z_det_nl = np.asarray(dval_nl.predictions[0]).reshape(val.n_frames, -1)
    say(f"[{folder}] EKF fit {out['t_ekf']:.1f} s, status {res_nl.status}")

    t0 = time.perf_counter()
    det = greybox.fit(model, [est], fs.free, method="zoh", loss="l2", n_starts=1)
    dval = greybox.validate(det, [val])
    out["det"] = det
    out["t_det"] = time.perf_counter() - t0
    z_det_est = det.predict(0)
    z_det_val = np.asarray(dval.predictions[0]).reshape(val.n_frames, -1)
    r = est.y - z_det_est
    out["det_whiteness"] = [greybox_ljung_box(r[:, j]) for j in range(r.shape[1])]
    say(f"[{folder}] deterministic fit {out['t_det']:.1f} s, status {det.status}")

    u_est, u_val = uniform(est), uniform(val)
    if one:  # SISO on T1 with heater 1, as compare.py and the paper
        u_est, u_val = (
            bb.UniformData(d.u[:, :1], d.y[:, :1], d.dt, name=d.name) for d in (u_est, u_val)
        )
    arx = study.fit_arx22(u_est)
    arx_sim = bb.simulate(arx, u_val)
    arx_one = bb.predict(arx, u_val, 1)
    yv = u_val.y
    arx_outputs = tuple(range(yv.shape[1]))

    rows = []
    yval = val.y - 273.15
    rows.append(
        (
            "stochastic grey-box (linear TCLab + heater process noise + ambient random walk "
            "per sensor; Kalman filter ML)",
            sae(yval, vd.y_simulation - 273.15, outputs),
            sae(yval, vd.y_one_step - 273.15, outputs),
        )
    )
    rows.append(
        (
            "deterministic grey-box (same linear TCLab and free list; free-run least squares)",
            sae(yval, z_det_val - 273.15, outputs),
            None,
        )
    )
    rows.append(
        (
            "stochastic grey-box, the folder's board with radiation (same noise structure; "
            f"extended Kalman filter ML; status {res_nl.status})",
            sae(yval, vd_nl.y_simulation - 273.15, outputs),
            sae(yval, vd_nl.y_one_step - 273.15, outputs),
        )
    )
    rows.append(
        (
            "deterministic grey-box, the folder's board with radiation (as `greybox fit`; "
            "results.md)",
            sae(yval, z_det_nl - 273.15, outputs),
            None,
        )
    )
    rows.append(
        (
            "ARX [2 2 1] + offset (least squares)" + (" SISO H1 -> T1" if one else ""),
            sae(yv, arx_sim, arx_outputs),
            sae(yv, arx_one, arx_outputs),
        )
    )
    out["rows"] = rows
    out["arx_whiteness"] = [greybox_ljung_box((yv - arx_one)[:, j]) for j in range(yv.shape[1])]
    return out


def greybox_ljung_box(x):
    return greybox.metrics.ljung_box(x, 20)


def _f(x, digits=2) -> str:
    return "n/a" if x is None or not np.isfinite(x) else f"{x:.{digits}f}"


def _g(x) -> str:
    return "n/a" if x is None or not np.isfinite(x) else f"{x:.3g}"


def report(results) -> str:
    lines = [
        "# TCLab: stochastic grey-box beside the deterministic grey-box and ARX",
        "",
        "Written by `experiments/tclab/stochastic.py` (run it to regenerate). Estimation on each "
        "folder's estimation run, scores on its validation run with every parameter fixed.",
        "",
        "- **Stochastic grey-box**: the linear TCLab (the folder's [model] options without "
        "radiation, so the exact continuous-discrete Kalman filter applies), process noise on "
        "the two heater nodes (one intensity q_heaters), one random-walk ambient/offset state per "
        "sensor (intensities q_T1, q_T2), measurement noise per sensor; likelihood: "
        f"{results[0]['stochastic'].likelihood} (`greybox.fit` with `ProcessNoise`).",
        "- **Deterministic grey-box**: `greybox.fit` with the same linear model and free list "
        "(free-run least squares).",
        "- **The folder's board with radiation** (the structure of results.md): the same noise "
        "structure through the extended Kalman filter, and its deterministic `greybox fit`.",
        "- **ARX [2 2 1]** with offset, least squares (the paper's structure; `study.fit_arx22`, "
        "as in compare.py).",
        "",
        "SAE in degC on the validation run, summed over the paper's scored sensors (T1 + T2 for "
        "two_heaters, T1 for one_heater). SIMULATION: the model driven by the heaters alone from "
        "the initial state (for the stochastic model: its deterministic mean, no reading used). "
        "ONE-STEP: each reading predicted from the readings before it (the Kalman filter's "
        "prediction; ARX's natural predictor). A deterministic grey-box has no noise model and "
        "so no one-step predictor of its own: n/a. Compare rows within one column only.",
        "",
    ]
    for r in results:
        res, vd = r["stochastic"], r["stochastic_val"]
        lines += [
            f"## {r['folder']}",
            "",
            "| model | validation SAE, simulation [degC] | validation SAE, one-step [degC] |",
            "|---|---|---|",
        ]
        for name, s_sim, s_one in r["rows"]:
            lines.append(f"| {name} | {_f(s_sim)} | {_f(s_one)} |")
        lines += [
            "",
            f"Stochastic fit: status **{res.status}** ({res.n_steps} BFGS steps, "
            f"{r['t_stochastic']:.0f} s), -log L = {res.neg_log_likelihood:.1f} over "
            f"{res.n_observations} readings, AIC {res.aic:.1f}. Deterministic fit: status "
            f"{r['det'].status} ({r['t_det']:.0f} s).",
            "",
            "| parameter | stochastic: value | 95 % interval | verdict | deterministic: value | "
            "95 % interval | verdict |",
            "|---|---|---|---|---|---|---|",
        ]
        det = {p.path: p for p in r["det"].parameters}
        for p in res.parameters:
            d = det.get(p.path)
            lines.append(
                f"| {p.name} [{p.unit}] | {_g(p.value)} | [{_g(p.ci95[0])}, {_g(p.ci95[1])}] | "
                f"{p.verdict} | "
                + (
                    f"{_g(d.value)} | [{_g(d.ci95[0])}, {_g(d.ci95[1])}] | {d.verdict} |"
                    if d is not None
                    else "- | - | - |"
                )
            )
        lines += [
            "",
            "Whiteness (Ljung-Box, 20 lags; white when p > 0.01): stochastic grey-box "
            "innovations, deterministic grey-box simulation residuals, ARX one-step residuals.",
            "",
            "| run | output | stochastic innovations p | deterministic residuals p | "
            "ARX one-step residuals p (validation) |",
            "|---|---|---|---|---|",
        ]
        names = ("T1", "T2")
        for run in (*res.runs, vd):
            for j, w in enumerate(run.whiteness):
                det_p = r["det_whiteness"][j].p_value if run.role == "estimation" else None
                arx_p = (
                    r["arx_whiteness"][j].p_value
                    if run.role == "validation" and j < len(r["arx_whiteness"])
                    else None
                )
                lines.append(
                    f"| {run.name} ({run.role}) | {names[j]} | {_g(w.p_value)} | "
                    f"{_g(det_p)} | {_g(arx_p)} |"
                )
        lines += [
            "",
            "Fit % (stochastic model, per output): "
            + "; ".join(
                f"{run.name} ({run.role}) simulation "
                + "/".join(f"{v:.1f}" for v in run.simulation_fit_percent)
                + ", one-step "
                + "/".join(f"{v:.1f}" for v in run.one_step_fit_percent)
                + f", {run.k_step}-step "
                + "/".join(f"{v:.1f}" for v in run.k_step_fit_percent)
                for run in (*res.runs, vd)
            )
            + ".",
            "",
            _ekf_line(r["ekf"], r["ekf_val"]),
            "",
        ]
    return "\n".join(lines)


def _ekf_line(res, vd) -> str:
    """The board with radiation (EKF): status, parameters and innovations whiteness."""
    params = ", ".join(
        f"{p.name} {_g(p.value)} [{_g(p.ci95[0])}, {_g(p.ci95[1])}] {p.unit}"
        + ("" if p.verdict == "identifiable" else f" ({p.verdict})")
        for p in res.parameters
    )
    white = "; ".join(
        f"{run.name} " + "/".join(_g(w.p_value) for w in run.whiteness) for run in (*res.runs, vd)
    )
    return (
        f"The folder's board with radiation, extended Kalman filter ({res.status}, "
        f"{res.n_steps} BFGS steps): {params}. Innovations Ljung-Box p per output: {white}."
    )


def main() -> None:
    t0 = time.perf_counter()
    results = [analyse(f) for f in ("two_heaters", "one_heater")]
    text = report(results)
    text += f"\nTotal runtime {time.perf_counter() - t0:.0f} s.\n"
    with atomic_output_file(HERE / "stochastic.md") as fh:
        fh.write(text)
    print(text)


if __name__ == "__main__":
    main()
