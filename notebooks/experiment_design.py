# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # What to measure next: experiment design at the fitted posterior
#
# A fitted grey-box model knows how well it knows its parameters, and it can predict how
# much a new experiment would tell it. This notebook closes that loop on the laser chevron:
#
# 1. Fit the embedded laser-chevron data (`greybox.io.load_experiment_set`, `greybox.fit`).
# 2. **Design** the next runs for the parameters of interest, the absorptance and the
#    thermal time constant `thermal.tau_s`, at the fitted posterior and on top of the data
#    already taken (`greybox.design.design_problem`, `greybox.design.LabConstraints`,
#    `greybox.design.design_experiment`), and compare with the habitual experiment of the same
#    length and power budget (`greybox.design.habitual_baseline`, `greybox.design.evaluate_design`,
#    `greybox.design.comparison_table`).
# 3. **"Run"** the designed experiment on synthetic data at the known truth
#    (`greybox.waveforms.record` with `greybox.waveforms.CameraDefects`, as `experiments/chevron_laser/generate.py`
#    made the embedded set), refit on old + new runs, and compare the **achieved** standard
#    errors with the **predicted** ones.
# 4. **Inverse design:** a laser waveform that steps the shuttle to a target stroke within a
#    settling time (`greybox.design.track_target`), with the predicted response's 95 % band.

# %%
import json
import os
import time
from pathlib import Path

import greybox.io

# float64, and compiled programs kept on disk as the greybox commands keep them (a second
# run of this notebook loads them instead of compiling)
greybox.io.configure_jax()

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

import greybox  # noqa: E402
import greybox.io  # noqa: E402

CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")
ROOT = next(p for p in (Path.cwd(), *Path.cwd().parents) if (p / "experiments").is_dir())
DATA = ROOT / "experiments" / "chevron_laser"  # ../experiments/chevron_laser from here

T_START = time.perf_counter()
INTEREST = ("absorptance", "thermal.tau_s")
# problem sizes: CI=true shrinks the new runs, the candidate grid and the optimiser
RUN_S = 5.0 if CI else 10.0  # length of each new run [s]
N_NEW = 2 if CI else 3  # number of new runs
N_PERIODS = 6 if CI else 12  # candidate pulse periods (log-spaced, whole ms)
DUTIES = [0.1, 0.2, 0.3, 0.5] if CI else list(np.round(np.arange(0.05, 0.951, 0.05), 2))
N_ITER_TRACK = 150 if CI else 400  # projected-gradient iterations of the inverse design
print(
    f"CI mode: {CI}; {N_NEW} new runs of {RUN_S:g} s, {N_PERIODS} periods x "
    f"{len(DUTIES)} duties, {N_ITER_TRACK} tracking iterations"
)

# %% [markdown]
# ## 1. Fit the data already taken
#
# Six estimation runs (5-30 mW, 200-1000 ms periods, 50 % duty, about 11 s each), the fit
# options of the folder's `experiment.toml` (Huber loss, exact zero-order-hold simulation).
# The data are synthetic, so the truth is known (`truth.json`); it is used only in part 3,
# to "run" the new experiment, and to check the intervals at the end.

# %%
fitset = greybox.io.load_experiment_set(DATA)
t0 = time.perf_counter()
result = greybox.fit(fitset.model, fitset.estimation, fitset.free, **fitset.fit_options)
print(f"fit of {len(fitset.estimation)} runs: {time.perf_counter() - t0:.1f} s, {result.status}")
TRUTH = json.loads((DATA / "truth.json").read_text())
TRUE = {p: v["value"] for p, v in TRUTH["parameters"].items()}
for path in INTEREST:
    e = result.estimate(path)
    print(
        f"  {path:14s} {e.value:.5g} {e.unit:2s} SE {e.se:.3g}, 95 % [{e.ci95[0]:.5g}, "
        f"{e.ci95[1]:.5g}]  (truth {TRUE[path]:g})"
    )
sigma = np.asarray(result.sigma)
print(f"  noise sigma {sigma[0] * 1e9:.1f} nm (truth {TRUTH['camera']['noise_um'] * 1e3:g} nm)")
shared = tuple(p for p in fitset.free if not p.per_experiment)
n_shared = len(shared)

# %% [markdown]
# ## 2. Design the next runs at the fitted posterior
#
# The lab's constraints: at most 30 mW (the highest power already used), an average of at
# most 10 mW per run (heat budget), pulses and gaps of at least 20 ms, the 30 fps camera
# with its 10 ms exposure, and a laser-off lead of 0.3 s in every run.
#
# `design_problem(..., raw=result.raw, covariance_raw=result.covariance_raw,
# include_existing=True)` evaluates the Fisher information at the **fitted** values and
# adds the information the six runs already hold (the inverse of the fit's covariance), so
# the predicted standard errors are those of a refit on **old + new** runs. The per-run
# camera offsets are nuisance parameters, marginalised per run. `design_experiment` picks
# the union of pulse trains (power, period, duty) that maximises det(M)^(1/2) of the
# information of the two parameters of interest (D-optimal), from a candidate grid; the
# comparison is the habitual experiment with the same number, length and power budget of
# runs (50 % duty, 400 ms period, the highest power the cap allows).

# %%
constraints = greybox.design.LabConstraints(
    power_max_W=0.030,
    run_duration_s=RUN_S,
    n_runs=N_NEW,
    average_power_max_W=0.010,
    min_pulse_s=0.020,
    fps=fitset.camera["fps"],  # the camera of the embedded set: 30 fps, 10 ms exposure
    exposure_s=fitset.camera["exposure_s"],
)
posterior = dict(raw=result.raw, covariance_raw=result.covariance_raw)
problem = greybox.design.design_problem(
    fitset.model, fitset.free, INTEREST, sigma, include_existing=True, **posterior
)
t0 = time.perf_counter()
design = greybox.design.design_experiment(
    problem, constraints, criterion="D", n_periods=N_PERIODS, duties=DUTIES
)
t_design = time.perf_counter() - t0
habitual = greybox.design.evaluate_design(problem, greybox.design.habitual_baseline(constraints), constraints)
rows = greybox.design.comparison_table(problem, design, habitual)
print(f"designed in {t_design:.1f} s; {design.verdict}")
for r in design.runs:
    d = r.description
    print(
        f"  {r.name}: {d['power_mW']:g} mW, period {d['period_ms']:g} ms, duty {d['duty']:.0%}, "
        f"{d['n_pulses']} pulses, mean {r.energy_J / RUN_S * 1e3:.2f} mW"
    )
h = habitual.runs[0].description
print(
    f"  habitual: {h['power_mW']:g} mW, period {h['period_ms']:g} ms, duty {h['duty']:.0%}, "
    f"{h['n_pulses']} pulses (x {N_NEW})"
)
print("\npredicted SE after a refit on the six old runs + the new ones:")
print(greybox.design.format_design_table(rows, design_label="designed", baseline_label="habitual"))

# the same new runs on their own (no existing data): how much each run is worth
alone = greybox.design.design_problem(fitset.model, fitset.free, INTEREST, sigma, **posterior)
rows_alone = greybox.design.comparison_table(
    alone,
    greybox.design.evaluate_design(alone, design.runs, constraints),
    greybox.design.evaluate_design(alone, habitual.runs, constraints),
)
print("\npredicted SE from the new runs alone:")
print(greybox.design.format_design_table(rows_alone, design_label="designed", baseline_label="habitual"))

# %% [markdown]
# **What the design chose and why.** The absorptance (the static gain) is learned from the
# plateau heights and the time constant from the rise and fall transients, so the design
# wants as many sharp edges as possible at as much power as the heat budget allows: under a
# 10 mW average cap it trades duty for peak power (full 30 mW, duty below 50 %) rather
# than running 50 % duty at a lower power, with on-times of a few tau so each edge rises
# most of the way to its plateau. The gain over the habitual experiment is real but modest on
# these runs, and smaller still once the six existing runs are counted (they dominate
# the information); the table of the new runs alone shows what each new run is worth.
#
# ## 3. "Run" the designed experiment and refit
#
# The new runs are recorded by the same simulated camera that made the embedded set
# (`greybox.waveforms.record` at the truth of `truth.json`: absorptance 0.62, tau 45 ms; 2 ms
# timestamp jitter, 50 nm tracking noise, 5 % dropped frames, a few pixels of rest-position
# offset per run), then the model is refitted on the six old runs plus the new ones, with
# the folder's fit options.

# %%
truth_model = greybox.parameters.set_values(fitset.model, list(TRUE), list(TRUE.values()))
m_per_px = fitset.camera["m_per_px"]
rng = np.random.default_rng(2026)
defects = greybox.waveforms.CameraDefects(
    fps=constraints.fps,
    jitter_s=TRUTH["camera"]["jitter_ms"] * 1e-3,
    noise_m=TRUTH["camera"]["noise_um"] * 1e-6,
    drop_fraction=TRUTH["camera"]["drop_fraction"],
)
new_runs = []
for r in design.runs:
    rest_px = 312.0 + rng.uniform(-4.0, 4.0)
    run_model = greybox.parameters.set_values(truth_model, ["camera.offset_m"], [rest_px * m_per_px])
    exp, _ = greybox.waveforms.record(
        run_model, r.waveform, name=r.name, defects=defects, seed=int(rng.integers(2**31))
    )
    new_runs.append(exp)
    print(f"  recorded {r.name}: {exp.n_frames} frames, {np.isnan(exp.y).sum()} dropped")
t0 = time.perf_counter()
refit = greybox.fit(
    fitset.model, [*fitset.estimation, *new_runs], fitset.free, **fitset.fit_options
)
print(f"refit on {len(fitset.estimation)} + {len(new_runs)} runs: {time.perf_counter() - t0:.1f} s")

labels = {"absorptance": "absorptance [1]", "thermal.tau_s": "tau [ms]"}
scale = {"absorptance": 1.0, "thermal.tau_s": 1e3}
summary = []
for row in rows:
    path = row["path"]
    before, after = result.estimate(path), refit.estimate(path)
    summary.append(
        {
            "path": path,
            "se_before": before.se,
            "se_predicted": row["se_design"],
            "se_habitual": row["se_baseline"],
            "se_achieved": after.se,
            "before": before,
            "after": after,
        }
    )
head = (
    f"{'parameter':16s} {'SE now':>9s} {'predicted':>10s} {'achieved':>9s} "
    f"{'achieved/pred':>13s} {'shrink pred':>11s} {'shrink ach':>10s}"
)
print(head + "\n" + "-" * len(head))
for s in summary:
    k = scale[s["path"]]
    print(
        f"{labels[s['path']]:16s} {s['se_before'] * k:9.4g} {s['se_predicted'] * k:10.4g} "
        f"{s['se_achieved'] * k:9.4g} {s['se_achieved'] / s['se_predicted']:13.3f} "
        f"{s['se_predicted'] / s['se_before']:11.3f} {s['se_achieved'] / s['se_before']:10.3f}"
    )
print()
for s in summary:
    k, b, a = scale[s["path"]], s["before"], s["after"]
    truth = TRUE[s["path"]]
    inside = [lo <= truth <= hi for lo, hi in (b.ci95, a.ci95)]
    print(
        f"{labels[s['path']]:16s} before {b.value * k:.5g} [{b.ci95[0] * k:.5g}, "
        f"{b.ci95[1] * k:.5g}] {'covers' if inside[0] else 'MISSES'} the truth; after "
        f"{a.value * k:.5g} [{a.ci95[0] * k:.5g}, {a.ci95[1] * k:.5g}] "
        f"{'covers' if inside[1] else 'MISSES'} {truth * k:g}"
    )
print(f"noise sigma after the refit: {np.asarray(refit.sigma)[0] * 1e9:.1f} nm")

# %%
fig, axes = plt.subplots(1, 2, figsize=(12, 4.2), layout="constrained")
bars = [
    ("se_before", "now (6 runs, fit)", "0.6"),
    ("se_habitual", f"+ {N_NEW} habitual runs (predicted)", "C1"),
    ("se_predicted", f"+ {N_NEW} designed runs (predicted)", "C0"),
    ("se_achieved", f"+ {N_NEW} designed runs (achieved, refit)", "C2"),
]
for ax, s in zip(axes, summary):
    k = scale[s["path"]]
    vals = [s[key] * k for key, _, _ in bars]
    x = np.arange(len(bars))
    ax.bar(x, vals, color=[c for _, _, c in bars], alpha=0.85)
    for xi, v in zip(x, vals):
        ax.text(xi, v, f"{v:.3g}", ha="center", va="bottom", fontsize=8)
    ax.set_xticks(x, [lab for _, lab, _ in bars], rotation=15, ha="right", fontsize=8)
    ax.set_ylabel(f"standard error of {labels[s['path']]}")
    ax.set_title(
        f"{s['path']}: predicted x{s['se_predicted'] / s['se_before']:.2f}, "
        f"achieved x{s['se_achieved'] / s['se_before']:.2f}"
    )
    ax.grid(alpha=0.3, axis="y")
fig.suptitle("Standard errors before and after the new runs: predicted vs achieved")
plt.show()

# %% [markdown]
# **Predicted vs measured.** The "predicted" bars are computed before any new data exist,
# from the Fisher information at the fitted values plus the information the six old runs
# hold; the "achieved" bar is the standard error the refit on old + new runs reports. The
# ratios printed above (achieved / predicted) are the check: the design's prediction is
# only as good as the fitted values it was made at and the camera model it assumes.
#
# Caveats, stated plainly:
#
# - **One noise realisation.** The achieved SE is what one refit reports (the
#   Gauss-Newton covariance at the refit's estimate and noise level); it is not the
#   spread of estimates over repeated experiments. `benchmarks/design.py` checks that
#   spread over 200 replicates; here the coverage of the truth by each 95 % interval is
#   one draw, not a coverage rate.
# - **Designed at the fitted values**, not the truth (which a lab does not know): the
#   information depends on the parameters, so a design made at slightly wrong values is
#   slightly suboptimal, and its predicted SEs are slightly off.
# - The prediction assumes nominal frame times; the recorded runs have timestamp jitter and
#   about 5 % dropped frames, which cost a few per cent of the information. The Huber loss
#   of the refit and its re-estimated noise level also differ slightly from the Gaussian
#   model the prediction uses.
# - The six old runs hold much of the information, so the designed runs beat the habitual
#   ones by less once the old runs are counted; the design's advantage shows more clearly
#   in the table of the new runs alone (also a prediction: only the designed runs were
#   "run" here, the habitual ones were not).
# - Under CI=true the notebook shrinks the new runs (2 x 5 s instead of 3 x 10 s) and the
#   candidate grid, so its numbers differ from the committed full-size run.
#
# ## 4. Inverse design: a waveform for a target stroke
#
# A step of the shuttle from rest to 1.0 um at t = 0.1 s, settled within 60 ms (about 1.3
# tau: a plain step of the hold power would take about 4 tau to get within 2 %) and held to
# 2 % until 0.6 s, with at most 30 mW and levels on a 5 ms grid. `greybox.design.track_target`
# optimises the levels by projected gradient descent through the exact simulator, at the
# refitted values, and returns the predicted response with its 95 % confidence band
# (parameter uncertainty of the refit, delta method). The same waveform is then simulated
# at the truth: the synthetic stand-in for trying it on the device.

# %%
STROKE_M, STEP_S, SETTLE_S, END_S = 1.0e-6, 0.1, 0.06, 0.6
fitted_model = greybox.parameters.set_values(
    fitset.model, [p.path for p in shared], [p.to_value(r) for p, r in zip(shared, refit.raw)]
)
t0 = time.perf_counter()
track = greybox.design.track_target(
    fitted_model,
    stroke_m=STROKE_M,
    step_time_s=STEP_S,
    settling_s=SETTLE_S,
    duration_s=END_S,
    power_max_W=0.030,
    hold_s=0.005,
    tolerance=0.02,
    n_iter=N_ITER_TRACK,
    free=shared,
    raw=refit.raw[:n_shared],
    covariance_raw=refit.covariance_raw[:n_shared, :n_shared],
)
t_track = time.perf_counter() - t0
at_truth = np.asarray(
    greybox.simulate(greybox.devices.with_camera(truth_model, exposure_s=0.0), track.waveform, track.t_s)
).reshape(-1)
err_truth = float(np.max(np.abs(at_truth - track.target)[track.settled]))
gap = float(np.max(np.abs(at_truth - track.response)))
inside = np.mean((at_truth >= track.band.lower[:, 0]) & (at_truth <= track.band.upper[:, 0]))
half_width = 1.96 * float(np.max(track.band.sd_model[track.settled]))
print(
    f"designed in {t_track:.1f} s ({track.iterations} iterations): predicted max error in "
    f"the settled window {track.max_error * 1e9:.1f} nm (tolerance {track.tolerance * 1e9:.0f}"
    f" nm) -> {'met' if track.met else 'NOT met'}; mean power "
    f"{track.average_power_W * 1e3:.2f} mW, peak {np.max(track.waveform.values) * 1e3:.1f} mW"
)
print(f"  widest 95 % confidence half-width in the settled window: {half_width * 1e9:.1f} nm")
print(
    f"  simulated at the truth: max error {err_truth * 1e9:.1f} nm -> "
    f"{'within' if err_truth <= track.tolerance else 'OUTSIDE'} the tolerance; largest "
    f"|truth - prediction| {gap * 1e9:.1f} nm; inside the 95 % band at {inside:.0%} of "
    "the simulated times"
)

# %%
fig, (ax0, ax_err, ax1) = plt.subplots(
    3, 1, figsize=(11, 8.4), sharex=True, layout="constrained", height_ratios=[2, 1.4, 1]
)
t_ms = track.t_s * 1e3
band = track.band
ax0.fill_between(
    t_ms,
    band.lower[:, 0] * 1e6,
    band.upper[:, 0] * 1e6,
    color="C0",
    alpha=0.3,
    label="95 % confidence band (refit parameters)",
)
ax0.plot(t_ms, track.response * 1e6, color="C0", lw=1.5, label="predicted response (refit)")
ax0.plot(t_ms, at_truth * 1e6, "--", color="C3", lw=1.0, label="same waveform at the truth")
ax0.plot(t_ms, track.target * 1e6, color="k", lw=0.8, label="target")
tol = track.tolerance * 1e6
settle_at = (STEP_S + SETTLE_S) * 1e3
ax0.fill_between(
    [settle_at, END_S * 1e3],
    STROKE_M * 1e6 - tol,
    STROKE_M * 1e6 + tol,
    color="0.5",
    alpha=0.2,
    label="+- 2 % tolerance after settling",
)
ax0.axvline(settle_at, color="0.4", ls=":", lw=1)
ax0.set_ylabel("displacement [um]")
ax0.set_title(
    f"Step to {STROKE_M * 1e6:g} um within {SETTLE_S * 1e3:g} ms: predicted max error "
    f"{track.max_error * 1e9:.1f} nm, at the truth {err_truth * 1e9:.1f} nm "
    f"(tolerance {track.tolerance * 1e9:.0f} nm)"
)
ax0.legend(fontsize=8, loc="lower right")
ax0.grid(alpha=0.3)
# the band is a few nm wide: zoom in on the error (response - target) after the step
after = track.t_s >= STEP_S
ax_err.fill_between(
    t_ms[after],
    (band.lower[after, 0] - track.target[after]) * 1e9,
    (band.upper[after, 0] - track.target[after]) * 1e9,
    color="C0",
    alpha=0.3,
)
ax_err.plot(t_ms[after], (track.response - track.target)[after] * 1e9, color="C0", lw=1.2)
ax_err.plot(t_ms[after], (at_truth - track.target)[after] * 1e9, "--", color="C3", lw=1.0)
ax_err.axhspan(-tol * 1e3, tol * 1e3, xmin=0, xmax=1, color="0.5", alpha=0.12)
ax_err.axvline(settle_at, color="0.4", ls=":", lw=1)
ax_err.set_ylim(-3 * tol * 1e3, 2 * tol * 1e3)
ax_err.set_ylabel("error [nm]")
ax_err.grid(alpha=0.3)
tt = np.linspace(0.0, END_S, 3001)[:-1]
ax1.step(tt * 1e3, np.ravel(track.waveform(tt)) * 1e3, where="post", color="C1")
ax1.set_ylabel("laser [mW]")
ax1.set_xlabel("time [ms]")
ax1.grid(alpha=0.3)
plt.show()

# %% [markdown]
# **Predicted vs measured, again.** The blue curve and band are the prediction from the
# refitted model: the band is the parameter part only (how far the response could move
# within the refit's 95 % confidence), a few nanometres, far inside the 20 nm tolerance
# (the middle panel zooms in on the error, response minus target). The dashed red curve is
# the same waveform simulated at the true parameters: on a real device this is the
# measurement one would make next. The largest gap between the two (printed above) is
# smaller than the band's widest half-width, the printed share of times at which the truth
# response lies inside the predicted band says how well the band covers it, and the target
# is met at the truth too. The waveform overdrives at the start (about twice the hold
# power while the shuttle is far from the target), dips, gives a short second boost, then
# settles at the hold power: the usual answer for a first-order lag that must settle
# faster than its time constant allows.
#
# Caveats: the inverse design is exact only within the model (one thermal time constant,
# quasi-static mechanics, no laser power noise); the band covers parameter uncertainty, not
# model error, and a camera would add its ~50 nm tracking noise on top of each reading.

# %%
print(f"notebook run time: {time.perf_counter() - T_START:.0f} s")
