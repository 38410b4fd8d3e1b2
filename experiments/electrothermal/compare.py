"""Polynomial (thesis ch. 5) against grey-box fits of the electro-thermal chevron data.

Reads table.csv and force_readings.csv (run generate.py first), writes report.md and PNG figures
next to this script. Every grey-box prediction is a steady-state simulation of the physics (no
measured value is fed back); polynomial scores are in-sample unless marked held-out.

Run: .venv/bin/python experiments/electrothermal/compare.py
"""

from __future__ import annotations

import json
import pathlib
import sys

import jax

import greybox

jax.config.update("jax_enable_x64", True)

ROOT = pathlib.Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from greybox import fit_table  # noqa: E402
from greybox.io import atomic_output_file  # noqa: E402
from greybox.metrics import rmse  # noqa: E402

ec = greybox.device_module("electrothermal_chevron")  # noqa: E402
SURFACE = greybox.device_module("electrothermal_chevron").surface  # noqa: E402

HERE = pathlib.Path(__file__).resolve().parent
N_STEPS = 16  # samples per half-cycle in the fit (2e-6 relative accuracy against a long simulation)
TRAIN_MAX_V, TRAIN_MAX_HZ = 16.0, 200.0  # extrapolation study: fit inside, score outside


def read_csv(path: pathlib.Path, columns: tuple[str, ...]) -> dict:
    with open(path) as fh:
        header = fh.readline().strip().split(",")
    if tuple(header) != columns:
        raise ValueError(f"{path}:1: header {','.join(header)!r}; expected {','.join(columns)!r}")
    data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    return {c: data[:, i] for i, c in enumerate(columns)}


def fmt_param(p, scale=1.0, unit=""):
    return (
        f"{p.value * scale:.5g} {unit} (95 % CI {p.ci95[0] * scale:.5g} to "
        f"{p.ci95[1] * scale:.5g}; {p.verdict})"
    )


def surface_study(truth_info, lines, figures):
    t = read_csv(HERE / "table.csv", ("amplitude_V", "frequency_Hz", "y_pp_um"))
    amps, freqs, table = SURFACE.check_grid(t["amplitude_V"], t["frequency_Hz"], t["y_pp_um"])
    a, f, y_um = t["amplitude_V"], t["frequency_Hz"], t["y_pp_um"]
    x = np.column_stack([a, f])
    poly32 = SURFACE.fit_polynomial(x, y_um, (3, 2))
    poly33 = SURFACE.fit_polynomial(x, y_um, (3, 3))
    xs, ys, fine = SURFACE.grid(poly32, (0.0, amps[-1]), (0.0, freqs[-1]), dx=0.1, dy=1.0)

    start = ec.SPEC.model(
        thermal__tau_s=0.015, thermal__resistance_K_per_W=150.0, joule__tcr_per_K=0.0
    )
    respond = greybox.waveforms.response_function(start, n_steps=N_STEPS)
    predict = lambda m, xx: respond(m, xx[0], xx[1])[1]  # noqa: E731
    free = ec.default_free_parameters()
    gb = fit_table(start, predict, (a, f), y_um * 1e-6, free)
    gb_um = gb.prediction * 1e6

    inside = (a <= TRAIN_MAX_V) & (f <= TRAIN_MAX_HZ)
    p_in = SURFACE.fit_polynomial(x[inside], y_um[inside], (3, 2))
    gb_in = fit_table(start, predict, (a, f), y_um * 1e-6, free, weights=inside.astype(float))
    out = ~inside
    ext = {
        "poly32": rmse(y_um[out], p_in(a[out], f[out])),
        "greybox": rmse(y_um[out], gb_in.prediction[out] * 1e6),
    }

    truth = truth_info["model"]
    lines += [
        "## 1. Amplitude-frequency table (peak-to-peak displacement)",
        "",
        f"{a.size} cells, {amps.size} amplitudes ({amps[0]:g}-{amps[-1]:g} V) x {freqs.size} "
        f"frequencies ({freqs[0]:g}-{freqs[-1]:g} Hz); synthetic noise {truth_info['table']['noise_um']} um.",
        "",
        "| model | parameters | R^2 | RMSE (um) | held-out RMSE beyond "
        f"{TRAIN_MAX_V:g} V / {TRAIN_MAX_HZ:g} Hz (um) |",
        "|---|---|---|---|---|",
        f"| poly32 (thesis eq. 5.1 form) | 9 | {poly32.r_squared:.4f} | {poly32.rmse:.4f} | {ext['poly32']:.3f} |",
        f"| poly33 | 10 | {poly33.r_squared:.4f} | {poly33.rmse:.4f} | - |",
        f"| grey-box (steady-state simulation) | 3 | {gb.r_squared:.5f} | {gb.rmse * 1e6:.4f} | {ext['greybox']:.3f} |",
        "",
        f"poly32 fit: z = {poly32.describe(('V', 'f'))} (um, V, Hz); interpolated on a "
        f"{fine.shape[0]} x {fine.shape[1]} grid (0.1 V x 1 Hz) as in thesis fig. 5.2.",
        "",
        f"Grey-box fit ({'converged' if gb.converged else gb.message}, noise estimated "
        f"sigma = {gb.sigma[0] * 1e6:.4f} um):",
        "",
        f"- tau = {fmt_param(gb.estimate('thermal.tau_s'), 1e3, 'ms')}; truth {truth['thermal.tau_s'] * 1e3:g} ms",
        f"- R_th = {fmt_param(gb.estimate('thermal.resistance_K_per_W'), 1, 'K/W')}; truth {truth['thermal.resistance_K_per_W']:g} K/W",
        f"- TCR = {fmt_param(gb.estimate('joule.tcr_per_K'), 1, '1/K')}; truth {truth['joule.tcr_per_K']:g} 1/K",
        "",
        *[f"  {s}" for s in gb.identifiability.summary()],
        "",
        f"Extrapolation fit on the {int(inside.sum())} cells with amplitude <= {TRAIN_MAX_V:g} V and "
        f"frequency <= {TRAIN_MAX_HZ:g} Hz, scored on the other {int(out.sum())}: grey-box "
        f"tau = {gb_in.estimate('thermal.tau_s').value * 1e3:.4g} ms, "
        f"R_th = {gb_in.estimate('thermal.resistance_K_per_W').value:.4g} K/W, "
        f"TCR = {gb_in.estimate('joule.tcr_per_K').value:.3g} 1/K.",
        "",
    ]

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(14, 4), constrained_layout=True)
    ext_extent = [freqs[0], freqs[-1], amps[0], amps[-1]]
    for ax, z, title in [
        (axes[0], table, "data y_pp (um)"),
        (axes[1], table - poly32(*np.meshgrid(amps, freqs, indexing="ij")), "data - poly32 (um)"),
        (axes[2], table - gb_um.reshape(table.shape), "data - grey-box (um)"),
    ]:
        im = ax.imshow(
            z,
            origin="lower",
            aspect="auto",
            extent=ext_extent,
            cmap="viridis" if ax is axes[0] else "RdBu_r",
            vmin=None if ax is axes[0] else -1.5,
            vmax=None if ax is axes[0] else 1.5,
        )
        ax.set(xlabel="frequency (Hz)", ylabel="amplitude (V)", title=title)
        fig.colorbar(im, ax=ax)
    fig.savefig(HERE / "fig_surface.png", dpi=110)
    plt.close(fig)

    fig, ax = plt.subplots(1, 2, figsize=(11, 4), constrained_layout=True)
    for k, v_show in enumerate([24.0, 12.0]):
        row = a == v_show
        ax[k].plot(f[row], y_um[row], "k.", label="data")
        ax[k].plot(f[row], p_in(a[row], f[row]), "C1-", label="poly32 (fit inside box)")
        ax[k].plot(f[row], gb_in.prediction[row] * 1e6, "C0-", label="grey-box (fit inside box)")
        ax[k].axvline(TRAIN_MAX_HZ, color="0.6", ls="--")
        ax[k].set(
            xlabel="frequency (Hz)",
            ylabel="y_pp (um)",
            title=f"{v_show:g} V"
            + (" (outside training amplitudes)" if v_show > TRAIN_MAX_V else ""),
        )
        ax[k].legend()
    fig.savefig(HERE / "fig_extrapolation.png", dpi=110)
    plt.close(fig)
    figures += ["fig_surface.png", "fig_extrapolation.png"]
    return {
        "poly32": (poly32.r_squared, poly32.rmse),
        "greybox": (gb.r_squared, gb.rmse * 1e6),
        "extrapolation_rmse_um": ext,
    }


def force_study(truth_info, lines, figures):
    r = read_csv(HERE / "force_readings.csv", ("voltage_V", "repeat", "sensor_mV"))
    s = truth_info["force"]["sensor"]
    sensor = ec.ForceSensor(
        s["length_m"],
        s["thickness_m"],
        s["gauge_factor"],
        s["bridge_V"],
        s["stiffness_N_per_m"],
        s["resistor_position"],
    )
    avg = ec.average_repeats(
        r["voltage_V"],
        sensor.force_N(r["sensor_mV"] * 1e-3) * 1e3,
        expected_repeats=truth_info["force"]["n_repeats"],
    )  # mN
    v, fm, se = avg.voltage_V, avg.mean, avg.pooled_se
    rows, cv = [], {}
    for order in (2, 8):
        p = SURFACE.fit_polynomial(v, fm, order)
        c = SURFACE.cross_validate(SURFACE.polynomial_predictor(order), v, fm)
        cv[order] = c.rmse
        rows.append(
            f"| poly order {order} | {p.n_params} | {p.rmse:.4f} | {c.rmse:.4f} | "
            f"{c.rmse_interior:.4f} | {p.criteria['aicc']:.1f} | {p.criteria['bic']:.1f} |"
        )
    start = ec.SPEC.model(thermal__resistance_K_per_W=150.0, joule__tcr_per_K=0.0)
    predict = ec.force_predictor(sensor.stiffness_N_per_m)
    free = ec.force_free_parameters()
    pred_mN = lambda m, x: predict(m, x) * 1e3  # noqa: E731
    gb = fit_table(start, pred_mN, v, fm, free, sigma=se)

    def greybox(train, x, z):
        res = fit_table(start, pred_mN, x, z, free, sigma=se, weights=train.astype(float))
        return np.asarray(pred_mN(res.model, x))

    cg = SURFACE.cross_validate(greybox, v, fm)
    cv["greybox"] = cg.rmse
    rss = float(np.sum((gb.prediction - fm) ** 2))
    crit = SURFACE.information_criteria(rss, v.size, len(free))
    rows.append(
        f"| grey-box (R_th, TCR) | 2 | {gb.rmse:.4f} | {cg.rmse:.4f} | "
        f"{cg.rmse_interior:.4f} | {crit['aicc']:.1f} | {crit['bic']:.1f} |"
    )
    truth = truth_info["model"]
    vv = np.linspace(0, 25, 126)
    blocked = np.asarray(jax.vmap(gb.model.blocked_force_N)(vv)) * 1e3
    lines += [
        "## 2. Force against DC voltage",
        "",
        f"{r['voltage_V'].size} sensor readings, {v.size} voltages x {int(avg.n[0])} repeats, converted "
        f"with eqs. 5.2-5.3 ({sensor.volts_per_m * 1e-3:.4g} mV/um, C = {sensor.stiffness_N_per_m:g} N/m) and "
        f"averaged (mean standard error {np.sqrt(np.mean(se**2)):.4f} mN).",
        "",
        "| model | parameters | RMSE in-sample (mN) | leave-one-voltage-out RMSE (mN) | "
        "same, interior voltages only (mN) | AICc | BIC |",
        "|---|---|---|---|---|---|---|",
        *rows,
        "",
        f"Grey-box ({gb.message}; weights = 1 / pooled standard error): "
        f"R_th = {fmt_param(gb.estimate('thermal.resistance_K_per_W'), 1, 'K/W')} (truth "
        f"{truth['thermal.resistance_K_per_W']:g}); TCR = {fmt_param(gb.estimate('joule.tcr_per_K'), 1, '1/K')} "
        f"(truth {truth['joule.tcr_per_K']:g}).",
        f"Blocked force 2 n E A alpha dT sin(a) of the fitted model: {blocked[80]:.3f} mN at 16 V, "
        f"{blocked[-1]:.3f} mN at 25 V; the sensor reads C / (C + k_y) = "
        f"{sensor.stiffness_N_per_m / (sensor.stiffness_N_per_m + float(gb.model.stiffness_N_per_m())):.3f} of it.",
        "",
    ]

    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.5), constrained_layout=True)
    ax.errorbar(v, fm, yerr=1.96 * se, fmt="ko", label="mean of repeats (95 %)")
    for order, col in ((2, "C1"), (8, "C3")):
        p = SURFACE.fit_polynomial(v, fm, order)
        ax.plot(vv, p(vv), col, label=f"poly order {order}")
    ax.plot(vv, np.asarray(pred_mN(gb.model, vv)), "C0", label="grey-box sensor force")
    ax.plot(vv, blocked, "C0--", label="grey-box blocked force")
    ax.axvline(v.max(), color="0.6", ls=":")
    ax.set(xlabel="voltage (V)", ylabel="force (mN)", ylim=(-1, 1.3 * blocked.max()))
    ax.legend()
    fig.savefig(HERE / "fig_force.png", dpi=110)
    plt.close(fig)
    figures.append("fig_force.png")
    return {"cv_rmse_mN": cv}


def main() -> None:
    truth_info = json.loads((HERE / "truth.json").read_text())
    lines = [
        "# Electro-thermal chevron: polynomial against grey-box fits",
        "",
        "Synthetic data from `generate.py` (seed in `truth.json`). Grey-box predictions are "
        "steady-state simulations of the physics (periodic steady state under the square "
        "wave; DC steady state for force); no measured value is fed back.",
        "",
    ]
    figures: list[str] = []
    s = surface_study(truth_info, lines, figures)
    fo = force_study(truth_info, lines, figures)
    lines += ["## Figures", "", *[f"![{f}]({f})" for f in figures], ""]
    with atomic_output_file(HERE / "report.md") as fh:
        fh.write("\n".join(lines))
    print("\n".join(lines))
    print(json.dumps({"surface": s, "force": fo}, default=float))


if __name__ == "__main__":
    main()
