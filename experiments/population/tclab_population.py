"""Population model on TCLab boards: what the class predicts for a new board (issue 19).

Only ONE real TCLab board is in this repository (Park et al. 2020, experiments/tclab: the
1-heater and 2-heater data sets come from the same published study; no second board's data
exist here). So the population is shown on synthetic boards built around the real one:

1. the real board's two-heater estimation run is one device ("park2020", real data);
2. N synthetic boards: the real board's fitted physics with a small manufacturing spread
   (log-sd 0.03 on U, Us, tau1, tau2) and heater gains alpha1, alpha2 that vary ~20 % (log-sd
   0.2, so two boards commonly differ by ~40 %, as measured between real boards), driven by
   the same heater sequence, initial temperatures as measured, Gaussian sensor noise 0.15 K;
   one of them ("weak_heater") has alpha2 at 35 % of its draw (a failing transistor);
3. every board is fitted with one compiled solver (`fit_batch`, the device's standard
   six-parameter structure, l2 loss, adaptive solver as in experiments/tclab);
4. stage 2 (`population_fit`): all six parameters as log-normal random effects; the thermal
   ones also tested for sharing (Cochran's Q);
5. a new board: parameters predicted at the population median with a 95 % band, and the
   temperatures it predicts on the real validation run (400 boards drawn from the fitted
   population), compared with the real board's measured validation temperatures and with a
   fresh synthetic board not used in the fit.

Writes results.md and population.png next to this file.
Usage (repository root): .venv/bin/python experiments/population/tclab_population.py
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import greybox  # noqa: E402

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tclab"))
from tclab_data import load_folder  # noqa: E402

SPEC = greybox.get_device("tclab")
THERMAL = ("U_W_per_m2K", "Us_W_per_m2K", "tau1_s", "tau2_s")
GAINS = ("alpha1_W_per_pct", "alpha2_W_per_pct")
SPREAD = {**{k: 0.03 for k in THERMAL}, **{k: 0.2 for k in GAINS}}
NOISE_K = 0.15
SEED = 2020


def synthetic_board(model, truth, exp, rng, name):
    board = greybox.parameters.set_values(model, list(truth), list(truth.values()))
    run = exp.apply_settings(board)
    clean = np.asarray(greybox.simulate(run, exp.inputs, exp.t_s, t_start_s=exp.t_start_s))
    clean = clean.reshape(exp.n_frames, -1)
    y = clean + rng.normal(0.0, NOISE_K, clean.shape)
    return greybox.Experiment(
        name, exp.t_s, y, exp.inputs, t_start_s=exp.t_start_s, settings=dict(exp.settings)
    ), clean


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--boards", type=int, default=15, help="synthetic boards (plus the real one)")
    n_boards = ap.parse_args(argv).boards
    t0 = time.perf_counter()
    runs = load_folder(HERE.parent / "tclab" / "two_heaters")
    est, val = runs["estimation"], runs["validation"]
    model = SPEC.model()
    free = SPEC.free_parameters()
    opts = dict(method="adaptive", loss="l2", n_starts=1)

    real = greybox.fit(model, [est], free, **opts)
    centre = {p.path: p.value for p in real.parameters}
    print(f"real board fitted ({time.perf_counter() - t0:.0f} s): {centre}", file=sys.stderr)

    rng = np.random.default_rng(SEED)
    devices = [greybox.population.Device("park2020", model, [est])]
    truth = {"park2020": centre}
    for k in range(n_boards):
        name = f"board{k:02d}" if k != 3 else "weak_heater"
        vals = {p: v * np.exp(SPREAD[p] * rng.normal()) for p, v in centre.items()}
        if name == "weak_heater":
            vals["alpha2_W_per_pct"] *= 0.35
        e, _ = synthetic_board(model, vals, est, rng, "estimation")
        devices.append(greybox.population.Device(name, model, [e]))
        truth[name] = vals
    t1 = time.perf_counter()
    batch = greybox.fit_batch(devices, free, **opts, progress=lambda m: print(m, file=sys.stderr))
    batch_s = time.perf_counter() - t1
    kinds = {p: "random" for p in (*THERMAL, *GAINS)}
    pop = greybox.population.population_from_batch(batch.results, kinds)
    shared_test = greybox.population.population_from_batch(
        batch.results, {p: "shared" for p in THERMAL}
    )

    # a new board: draws from the fitted population -> temperatures on the validation input
    draws = 400
    sims = []
    for _ in range(draws):
        vals = {}
        for p, q in pop.parameters.items():
            mu = q.log_mu + q.log_mu_se * rng.normal()
            vals[p] = float(np.exp(mu + q.omega * rng.normal()))
        board = val.apply_settings(
            greybox.parameters.set_values(model, list(vals), list(vals.values()))
        )
        z = greybox.simulate(board, val.inputs, val.t_s, t_start_s=val.t_start_s)
        sims.append(np.asarray(z).reshape(val.n_frames, -1))
    sims = np.array(sims) - 273.15
    lo, mid, hi = np.percentile(sims, [2.5, 50, 97.5], axis=0)
    y_real = val.y - 273.15
    inside_real = np.mean((y_real >= lo) & (y_real <= hi), axis=0)
    fresh_vals = {p: v * np.exp(SPREAD[p] * rng.normal()) for p, v in centre.items()}
    fresh, fresh_clean = synthetic_board(model, fresh_vals, val, rng, "fresh")
    inside_fresh = np.mean(((fresh_clean - 273.15) >= lo) & ((fresh_clean - 273.15) <= hi), axis=0)
    z_own = (
        np.asarray(
            greybox.simulate(
                val.apply_settings(
                    greybox.parameters.set_values(model, list(centre), list(centre.values()))
                ),
                val.inputs,
                val.t_s,
                t_start_s=val.t_start_s,
            )
        ).reshape(val.n_frames, -1)
        - 273.15
    )
    width = np.mean(hi - lo, axis=0)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(14, 3.8))
    for j, ax in enumerate(axes[:2]):
        ax.fill_between(
            val.t_s, lo[:, j], hi[:, j], color="C0", alpha=0.3, label="new board, 95 % band"
        )
        ax.plot(val.t_s, mid[:, j], "C0", lw=1, label="population median")
        ax.plot(val.t_s, y_real[:, j], "k", lw=0.8, label="real board (measured)")
        ax.plot(val.t_s, fresh_clean[:, j] - 273.15, "C3--", lw=0.8, label="fresh synthetic board")
        ax.set_xlabel("t [s]")
        ax.set_ylabel(f"T{j + 1} [degC]")
        ax.legend(fontsize=7)
    a1 = np.array([batch[d.name].estimate("alpha1_W_per_pct").value for d in devices])
    a2 = np.array([batch[d.name].estimate("alpha2_W_per_pct").value for d in devices])
    ax = axes[2]
    ax.scatter(a1 * 1e3, a2 * 1e3, c=["C3" if pop.flags[d.name] else "C0" for d in devices])
    for d, x, y in zip(devices, a1, a2):
        if d.name in ("park2020", "weak_heater"):
            ax.annotate(d.name, (x * 1e3, y * 1e3), fontsize=7)
    ax.set_xlabel("alpha1 [mW/%]")
    ax.set_ylabel("alpha2 [mW/%]")
    fig.tight_layout()
    fig.savefig(HERE / "population.png", dpi=110)
    plt.close(fig)

    def f(x, d=4):
        return f"{x:.{d}g}"

    lines = [
        "# Population model on TCLab boards",
        "",
        "Generated by `experiments/population/tclab_population.py` "
        f"(seed {SEED}, {time.perf_counter() - t0:.0f} s on this machine).",
        "",
        "**Only one real TCLab board is available here** (Park et al. 2020, "
        "`experiments/tclab`; no second board's data exist in the repository). The population "
        f"is therefore shown on {n_boards} synthetic boards built around the real one plus the "
        "real board itself (`park2020`, its measured two-heater estimation run): the real "
        "board's fitted physics with a small spread (log-sd 0.03) on U, Us, tau1, tau2 and "
        "heater gains alpha1, alpha2 with log-sd 0.2 (two boards commonly differ by ~40 %), "
        f"the same heater sequence and initial temperatures, sensor noise {NOISE_K} K; "
        "`weak_heater` has alpha2 at 35 % of its draw. The numbers below are what the method "
        "does on such a class, not a measurement of real boards.",
        "",
        f"Stage 1: {len(devices)} boards fitted with one compiled solver (`fit_batch`, "
        f"six parameters each, l2 loss, adaptive solver) in {batch_s:.0f} s; "
        f"{sum(r.valid for r in batch.results.values())} valid fits.",
        "",
        f"Stage 2 method: {pop.method}.",
        "",
        "| parameter | true spread (log-sd) | population median (SE) | spread omega (SE) | "
        "raw log-sd of estimates | new board: 95 % band | Cochran Q p (sharing) |",
        "|---|---|---|---|---|---|---|",
    ]
    for p, q in pop.parameters.items():
        qp = shared_test.parameters[p].q_p if p in THERMAL else float("nan")
        lines.append(
            f"| {p} | {SPREAD[p]} | {f(q.median)} ({f(q.median_se, 2)}) | "
            f"{f(q.omega, 3)} ({f(q.omega_se, 2)}) | {f(q.raw_log_sd, 3)} | "
            f"{f(q.new_device[1])} – {f(q.new_device[2])} | "
            + ("—" if not np.isfinite(qp) else f"{qp:.2g}")
            + " |"
        )
    weak = batch["weak_heater"].estimate("alpha2_W_per_pct")
    weak_bound = next(p.lower for p in free if p.path == "alpha2_W_per_pct")
    lines += [
        "",
        "Boards that do not belong: "
        + ("; ".join(f"`{d}` ({', '.join(r)})" for d, r in pop.flags.items() if r) or "none")
        + ".",
        "",
        "Why: "
        + (
            "; ".join(
                f"`{d}`: status {batch[d].status} ({batch[d].message})"
                for d in pop.flags
                if not batch[d].valid
            )
            or "every flagged board's own fit is valid, the flag comes from the comparison "
            "with the class"
        )
        + f". `weak_heater`: alpha2 fitted {weak.value:.4g} (SE {weak.se:.2g}, "
        f"{weak.verdict}) against its true {truth['weak_heater']['alpha2_W_per_pct']:.4g} "
        f"(lower bound {weak_bound:g})"
        + ". A flag on the residual noise scale means that board's free-run residuals are "
        "larger than the class's: for `park2020` that is the real board's model error (the "
        "synthetic boards are simulated by the model itself, with white noise only), so the "
        "flag is the method doing its job on a board that is not like the others.",
        "",
        "Standardised (leave-one-out) random effect of the real board: "
        + ", ".join(f"{p} {pop.parameters[p].z[0]:+.1f}" for p in pop.parameters)
        + ".",
        "",
        "## What it predicts for a new board",
        "",
        "Parameters: the population median with the 95 % band in the table above "
        "(exp(mu ± t sqrt(omega² + se(mu)²))). Temperatures: 400 boards drawn from the fitted "
        "population (log-normal, the median's uncertainty included) simulated on the real "
        "validation run's heater sequence (free-run, from the measured initial temperatures):",
        "",
        "| | T1 | T2 |",
        "|---|---|---|",
        f"| mean width of the 95 % band [K] | {width[0]:.1f} | {width[1]:.1f} |",
        f"| real board's measured validation temperatures inside the band | "
        f"{100 * inside_real[0]:.0f} % | {100 * inside_real[1]:.0f} % |",
        f"| a fresh synthetic board (not fitted) inside the band | {100 * inside_fresh[0]:.0f} % | "
        f"{100 * inside_fresh[1]:.0f} % |",
        f"| real board's own fitted model: validation SAE [K] | "
        f"{np.nansum(np.abs(z_own[:, 0] - y_real[:, 0])):.0f} | "
        f"{np.nansum(np.abs(z_own[:, 1] - y_real[:, 1])):.0f} |",
        f"| population median board: validation SAE [K] | "
        f"{np.nansum(np.abs(mid[:, 0] - y_real[:, 0])):.0f} | "
        f"{np.nansum(np.abs(mid[:, 1] - y_real[:, 1])):.0f} |",
        "",
        "The band is wide because heater gains differ between boards: a new board's "
        "temperatures are known only to within the gain spread until its two gains are "
        "re-fitted (per-board gains, shared thermal physics). The band is a statement about "
        "this synthetic class; for real boards it needs real boards' data.",
        "",
        "![population](population.png)",
    ]
    (HERE / "results.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
