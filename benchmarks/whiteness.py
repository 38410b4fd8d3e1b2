"""Calibration of the residual test and of the sandwich (HAC) standard errors.

Run: .venv/bin/python benchmarks/whiteness.py [--replicates 200]

1. False alarms. Well-specified data (the one-node chevron recorded by `greybox.record`: two
   pulse runs of 4 s at ~30 fps with 2 ms jitter, 5 % dropped frames, 0.05 um white noise)
   fitted with the one-node model: how often does the pooled Ljung-Box test call the
   residuals not white? Reported at the verdict's level (1 %) and at 5 %, each with the
   binomial 95 % interval of the rejection rate that a test of exactly nominal size gives
   over this many replicates.
2. Coverage under misspecification. Data from an independent two-node chevron (numpy: pad and
   beam nodes plus an elongation lag, time constants 4, 21 and 79 ms; the same static stroke
   map), fitted with the one-node model. The best-approximating values theta* are the fit to
   the noise-free signal at the same frame times; each replicate adds noise and drops frames,
   and counts whether the Gauss-Newton and the Newey-West (HAC) 95 % intervals contain
   theta* (for absorptance and tau). Two noise models:
   - "white": white noise on a deterministic misfit. The estimator's spread comes from the
     white noise alone, but the noise scale estimated from the residuals is inflated by the
     misfit, so Gauss-Newton intervals are too wide, not too narrow;
   - "ar1": AR(1) noise (rho 0.8 per frame, 0.05 um marginal sd) on the same misfit: the
     residuals are also autocorrelated at random, Gauss-Newton intervals are too narrow and
     the sandwich is built for this (it cannot tell the deterministic misfit from random
     noise, so it errs on the wide side).
   And, as a control, the one-node model on its own data with the same AR(1) noise (only the
   noise model is wrong; theta* is the truth).
   The L2 loss is used throughout, so that theta* does not depend on the noise scale.

Last line: one JSON object.
"""

from __future__ import annotations

import argparse
import json
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from scipy.signal import lfilter  # noqa: E402
from scipy.special import erf  # noqa: E402
from scipy.stats import binom  # noqa: E402

import greybox  # noqa: E402
from greybox import CameraDefects, Experiment, PiecewiseConstant, fit, record, set_values  # noqa: E402

CHEVRON = greybox.get_device("chevron_laser")
RUNS = ((10, 0.3), (30, 0.6))  # (mW, period s)
DURATION_S = 4.0
NOISE_M = 0.05e-6
PARAMS = ("absorptance", "thermal.tau_s")
Z95 = 1.959963984540054

# the independent two-node chevron (as tests/test_residuals.py)
L_M, ANGLE, CTE = 3.5e-3, np.deg2rad(2.0), 2.6e-6
WAIST_M, PAD_M = 150e-6, 200e-6
C1, C2, G12, G1, G2, LAG_S = 1.0e-5, 2.0e-5, 2e-4, 2e-4, 2e-4, 0.004
ABSORPTANCE = 0.25


def stroke_m(rise_K):
    dl = CTE * L_M * rise_K
    ls = L_M * np.sin(ANGLE)
    growth = 2 * L_M * dl + dl**2
    return growth / (np.sqrt(ls**2 + growth) + ls)


def two_node_readings(times_s, levels_W, t_frames, exposure_s=0.010):
    a = np.array(
        [
            [-(G12 + G1) / C1, G12 / C1, 0.0],
            [G12 / C2, -(G12 + G2) / C2, 0.0],
            [0.0, 1.0 / LAG_S, -1.0 / LAG_S],
        ]
    )
    b = np.array([1.0 / C1, 0.0, 0.0])
    lam, vec = np.linalg.eig(a)
    lam, vec = lam.real, vec.real
    inv = np.linalg.inv(vec)
    frac = erf(np.sqrt(2) / WAIST_M * PAD_M / 2) ** 2

    def steady(k):
        return -np.linalg.solve(a, b * ABSORPTANCE * frac * levels_W[k])

    state = [np.zeros(3)]
    for k in range(len(times_s) - 1):
        xs = steady(k)
        dt = times_s[k + 1] - times_s[k]
        state.append(xs + vec @ (np.exp(lam * dt) * (inv @ (state[-1] - xs))))

    def rise(t):
        k = np.searchsorted(times_s, t, side="right") - 1
        if k < 0:
            return 0.0
        xs = steady(k)
        return (xs + vec @ (np.exp(lam * (t - times_s[k])) * (inv @ (state[k] - xs))))[2]

    nodes, weights = np.polynomial.legendre.leggauss(6)
    out = []
    for tf in t_frames:
        lo = tf - exposure_s
        cuts = np.concatenate([[lo], times_s[(times_s > lo) & (times_s < tf)], [tf]])
        total = 0.0
        for u, v in zip(cuts[:-1], cuts[1:]):
            ts = (u + v) / 2 + (v - u) / 2 * nodes
            total += (v - u) / 2 * np.sum(weights * stroke_m(np.array([rise(x) for x in ts])))
        out.append(total / exposure_s)
    return np.asarray(out)


def two_node_clean():
    """(waveforms, frame times, noise-free readings) of the misspecified runs (fixed)."""
    rng = np.random.default_rng(2024)
    out = []
    for p_mw, period in RUNS:
        n = int(np.ceil(DURATION_S / period))
        rises = np.arange(n) * period
        times = np.column_stack([rises, rises + period / 2]).reshape(-1)
        levels = np.tile([p_mw * 1e-3, 0.0], n)
        end = n * period
        t = np.sort((np.arange(int(end * 30)) + 0.5) / 30 + rng.normal(0, 2e-3, int(end * 30)))
        t = t[(t > 0.011) & (t < end)]
        out.append((PiecewiseConstant(times, levels, end), t, two_node_readings(times, levels, t)))
    return out


def start_model():
    return set_values(CHEVRON.model(), list(PARAMS), [0.5, 0.05])


def free():
    return list(CHEVRON.free_parameters())


def covered(result, target: dict) -> tuple[bool, bool]:
    """(Gauss-Newton covers theta*, HAC covers theta*) for every parameter in PARAMS, each
    interval taken in the raw (transformed) coordinate as `greybox` reports it."""
    gn, hac = True, True
    for k, name in enumerate(PARAMS):
        p = result.free[k]
        est = result.estimate(name)
        d = abs(p.value_derivative(result.raw[k]))
        miss = abs(result.raw[k] - float(p.to_raw(target[name])))
        gn &= miss < Z95 * est.se_gauss_newton / d
        hac &= miss < Z95 * est.se_hac / d
    return bool(gn), bool(hac)


def rate_interval(n: int, p: float) -> list[float]:
    """Central 95 % interval of the rejection rate of a test of exact size p over n runs."""
    return [float(binom.ppf(0.025, n, p) / n), float(binom.ppf(0.975, n, p) / n)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--replicates", type=int, default=1000)
    args = ap.parse_args()
    n = args.replicates
    t0 = time.perf_counter()

    # 1. false alarms on well-specified data
    truth = set_values(CHEVRON.model(), list(PARAMS), [0.62, 0.045])
    p_values = []
    for rep in range(n):
        exps = []
        for i, (p_mw, period) in enumerate(RUNS):
            wave = greybox.PulseTrain(p_mw * 1e-3, period, 0.5, int(np.ceil(DURATION_S / period)))
            exps.append(
                record(
                    truth, wave, name=f"run{i + 1}", defects=CameraDefects(), seed=10_000 * rep + i
                )[0]
            )
        r = fit(start_model(), exps, free(), loss="l2")
        p_values.append(float(r.residuals.p_value[0]))
    p_values = np.asarray(p_values)
    alarm1, alarm5 = float(np.mean(p_values < 0.01)), float(np.mean(p_values < 0.05))
    print(
        f"false alarms over {n} well-specified fits: {alarm1:.3f} at 1 % "
        f"(interval {rate_interval(n, 0.01)}), {alarm5:.3f} at 5 % "
        f"(interval {rate_interval(n, 0.05)}) [{time.perf_counter() - t0:.0f} s]",
        flush=True,
    )

    # 2. coverage of the best-approximating values under misspecification
    clean = two_node_clean()
    noise_free = [Experiment(f"run{i + 1}", t, y, wave) for i, (wave, t, y) in enumerate(clean)]
    best = fit(start_model(), noise_free, free(), loss="l2")
    target = {k: best.estimate(k).value for k in PARAMS}
    print(f"best-approximating values: {target} ({best.status})", flush=True)
    truth_clean = []
    for i, (wave, t, _) in enumerate(clean):
        z = np.asarray(greybox.simulate(truth, wave, t)).reshape(-1)
        truth_clean.append((wave, t, z))
    cases = {
        "white": (clean, target, "white"),
        "ar1": (clean, target, "ar1"),
        "ar1_structure_right": (truth_clean, dict(zip(PARAMS, [0.62, 0.045])), "ar1"),
    }
    coverage = {}
    for case, (signals, theta, noise_kind) in cases.items():
        rng = np.random.default_rng(sum(map(ord, case)))
        hits, whites, bandwidths, ratio = [], [], [], []
        for _ in range(n):
            exps = []
            for i, (wave, t, y) in enumerate(signals):
                if noise_kind == "white":
                    noise = rng.normal(0, NOISE_M, t.size)
                else:
                    rho = 0.8
                    innovations = rng.normal(0, NOISE_M * np.sqrt(1 - rho**2), t.size)
                    noise = lfilter([1.0], [1.0, -rho], innovations)
                yn = y + noise
                yn[rng.uniform(size=t.size) < 0.05] = np.nan
                exps.append(Experiment(f"run{i + 1}", t, yn, wave))
            r = fit(start_model(), exps, free(), loss="l2")
            hits.append(covered(r, theta))
            whites.append(r.residuals.all_white)
            bandwidths.append(r.hac_bandwidth)
            tau = r.estimate("thermal.tau_s")
            ratio.append(tau.se_hac / tau.se_gauss_newton)
        hits = np.asarray(hits)
        coverage[case] = {
            "coverage_gn": float(hits[:, 0].mean()),
            "coverage_hac": float(hits[:, 1].mean()),
            "not_white_rate": float(1 - np.mean(whites)),
            "median_hac_bandwidth_frames": float(np.median(bandwidths)),
            "median_se_ratio_hac_over_gn_tau": float(np.median(ratio)),
        }
        print(f"{case}: {coverage[case]} [{time.perf_counter() - t0:.0f} s]", flush=True)

    interval1 = rate_interval(n, 0.01)
    out = {
        "replicates": n,
        "false_alarm_rate": alarm1,
        "nominal": 0.01,
        "binomial_ci": interval1,
        "within_ci": bool(interval1[0] <= alarm1 <= interval1[1]),
        "false_alarm_rate_5pct": alarm5,
        "binomial_ci_5pct": rate_interval(n, 0.05),
        "best_approximating": target,
        "coverage_gn": coverage["ar1"]["coverage_gn"],
        "coverage_hac": coverage["ar1"]["coverage_hac"],
        "coverage_white_misfit_gn": coverage["white"]["coverage_gn"],
        "coverage_white_misfit_hac": coverage["white"]["coverage_hac"],
        "coverage_ar1_structure_right_gn": coverage["ar1_structure_right"]["coverage_gn"],
        "coverage_ar1_structure_right_hac": coverage["ar1_structure_right"]["coverage_hac"],
        "cases": coverage,
        "seconds": round(time.perf_counter() - t0, 1),
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
