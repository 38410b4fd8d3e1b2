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
# # The thesis workflow, step by step, and what the grey-box model does instead
#
# Yelike (2012), chapter 3, identified the laser-heated chevron from camera video with the
# MATLAB System Identification Toolbox:
#
# 1. **stitch** six experiments into one pseudo-random-looking record (fig. 3.8);
# 2. **resample** it by interpolation, 191 -> 1910 samples (10x, fig. 3.9);
# 3. fit an **ARX** model (eq. 3.2), convert it to continuous time, look at its step response
#    and its prediction error (fig. 3.10-3.13);
# 4. fit an **ARMAX** model started from the ARX coefficients (eq. 3.7-3.8, fig. 3.14-3.16);
# 5. run **recursive (Kalman) ARX and ARMAX**, started from the batch estimates, and carry the
#    final parameters and covariance from the estimation data into the validation data
#    (fig. 3.18-3.19);
# 6. judge the models by **prediction-error plots**.
#
# Here every step is run on our data (`experiments/chevron_laser/`, synthetic with known
# truth, 30 fps camera with jitter, dropped frames and a burst of corrupted frames) with
# `greybox.blackbox`, and each step is followed by what the grey-box model does instead, and
# why. The short version: the grey-box model is a differential equation, so it is evaluated
# at the camera timestamps themselves; nothing has to be stitched, interpolated or made
# uniform.

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

CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")
ROOT = next(p for p in (Path.cwd(), *Path.cwd().parents) if (p / "experiments").is_dir())
DATA = ROOT / "experiments" / "chevron_laser"

from greybox import blackbox as bb  # noqa: E402
from greybox import fit, simulate, validate  # noqa: E402
from greybox.io import load_experiment_set  # noqa: E402
from greybox.metrics import fit_percent, rmse  # noqa: E402
from greybox.parameters import set_values  # noqa: E402

T_START = time.perf_counter()
fitset = load_experiment_set(DATA)
truth = json.loads((DATA / "truth.json").read_text())
FPS = fitset.camera["fps"]
OVERSAMPLE = 5 if CI else 10  # the thesis: 10x (191 -> 1910 samples)
DT_S = 1.0 / FPS / OVERSAMPLE
print(f"CI mode: {CI}; resampling interval {DT_S * 1e3:.2f} ms ({OVERSAMPLE}x the frame rate)")

# %% [markdown]
# ## Step 1. Stitched experiments
#
# The thesis stitched six runs end to end, so that one record covers 5-30 mW and
# 200-1000 ms. Each run's camera offset (the shuttle's rest position in the image) differs
# by a few pixels: re-focusing between runs. Stitched as recorded, the rest position jumps
# at every run boundary (left), by as much as the whole stroke at 5 mW. We remove each
# run's offset first (the median of the frames before the laser first switches on,
# `Experiment.rest_level()`: every run starts with 300 ms laser-off) and then stitch (right).

# %%
est, val = list(fitset.estimation), list(fitset.validation)
fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(13, 4), layout="constrained")
start = 0
for k, e in enumerate(est):
    n = np.arange(start, start + e.n_frames)
    ax0.plot(n, e.y[:, 0] * 1e6, ".", ms=1.5, color=f"C{k}", label=e.name)
    ax1.plot(n, (e.y[:, 0] - e.rest_level()[0]) * 1e6, ".", ms=1.5, color=f"C{k}")
    start += e.n_frames
ax0.set_title("stitched as recorded")
ax0.set_ylabel("shuttle position in the image [um]")
ax1.set_title("stitched after removing each run's rest position")
ax1.set_ylabel("displacement [um]")
for ax in (ax0, ax1):
    ax.set_xlabel("camera frame (stitched index)")
    ax.grid(alpha=0.3)
ax0.legend(fontsize=7, markerscale=6)
plt.show()
print(
    f"{sum(e.n_frames for e in est)} estimation frames in 6 runs (the thesis: 191); "
    f"rest positions span {np.ptp([e.rest_level()[0] for e in est]) * 1e6:.2f} um"
)

# %% [markdown]
# **What the grey-box does instead.** Nothing is stitched. `greybox.fit` takes the six runs
# as six `Experiment`s, each on its own time axis, simulates them all (vmapped) and fits the
# shared physics (absorptance, thermal time constant) and one camera offset per run, with
# intervals. A pseudo-random record is not needed either: what identifies tau and the gain
# is the set of runs together (several powers and periods), not one long sequence.

# %%
t0 = time.perf_counter()
grey = fit(fitset.model, est, fitset.free, **fitset.fit_options)
print(f"grey-box fit of the 6 runs: {time.perf_counter() - t0:.1f} s, converged={grey.converged}")
for p in grey.parameters:
    scale, unit = (1e6 / fitset.camera["m_per_px"] / 1e6, "px") if p.unit == "m" else (1.0, p.unit)
    print(
        f"  {p.name:32s} {p.value * scale:10.4g} {unit:3s} 95 % [{p.ci95[0] * scale:.4g}, "
        f"{p.ci95[1] * scale:.4g}]  {p.verdict}"
    )

# %% [markdown]
# ## Step 2. Resampling by interpolation
#
# A camera at 30 fps gives one frame per 33 ms, irregularly (jitter), with dropped frames.
# The thesis interpolated the record onto a 10x finer uniform grid. Here each run is
# resampled separately (the interpolant must not bridge two runs) with a shape-preserving
# piecewise cubic (`pchip`, `greybox.blackbox.uniform_from_experiment`), after removing its
# rest position, with the laser input evaluated exactly on the grid, and the runs stitched.
#
# Zoomed in on one run: the interpolant (orange) passes through every camera frame, noise
# included, and between frames it invents a shape; the true displacement (grey, known here
# because the data are synthetic) peaks between frames, and the interpolant cuts those
# peaks off.


# %%
def uniform(e):
    """One run on the DT_S grid (mW in, um out; resampled=True) and its grid times [s]."""
    d, t_grid, _ = bb.uniform_from_experiment(e, DT_S, input_scale=1e3, output_scale=1e6)
    return d, t_grid


def stitch(datas, name):
    return bb.UniformData(
        np.concatenate([d.u for d in datas]), np.concatenate([d.y for d in datas]), DT_S, True, name
    )


est_u = [uniform(e) for e in est]
val_u = [uniform(e) for e in val]
est_st = stitch([d for d, _ in est_u], "stitched estimation")
val_st = stitch([d for d, _ in val_u], "stitched validation")
print(
    f"resampled: {sum(e.n_frames for e in est)} frames -> {est_st.n_samples} samples (estimation)"
)

e = est[1]  # e2_10mW_200ms: short period, the hardest case for a 30 fps camera
d, t_grid = est_u[1]
true_model = set_values(
    fitset.model,
    [*truth["parameters"], "camera.offset_m"],
    [*(v["value"] for v in truth["parameters"].values()), truth["camera_offset_m"][e.name]],
)
# the clean truth as the camera would have seen it at any instant (exposure-averaged)
t_fine = np.arange(1.0, 2.0, 1e-3)
clean = np.asarray(simulate(true_model, e.inputs, t_fine)).ravel()
fig, ax = plt.subplots(figsize=(11, 4), layout="constrained")
off = e.rest_level()[0]
ax.plot(t_fine, (clean - off) * 1e6, "-", color="0.6", lw=2.5, label="true response (noise-free)")
win = (t_grid > 1.0) & (t_grid < 2.0)
ax.plot(
    t_grid[win],
    d.y[win, 0],
    ".-",
    color="C1",
    ms=2.5,
    lw=0.8,
    label=f"pchip interpolant ({DT_S * 1e3:.1f} ms grid)",
)
wf = (e.t_s > 1.0) & (e.t_s < 2.0)
ax.plot(e.t_s[wf], (e.y[wf, 0] - off) * 1e6, "o", color="k", ms=4, label="camera frames")
grey_e2 = grey.predict(1)[:, 0]
ax.plot(
    e.t_s[wf],
    (grey_e2[wf] - off) * 1e6,
    "x",
    color="C0",
    ms=7,
    mew=2,
    label="grey-box model at the camera timestamps",
)
ax.set_xlabel("time [s]")
ax.set_ylabel("displacement [um]")
ax.set_title(f"{e.name}: what interpolation adds between frames")
ax.grid(alpha=0.3)
ax.legend(fontsize=8, loc="upper right")
plt.show()
clean_grid = np.asarray(simulate(true_model, e.inputs, t_grid)).ravel()
clean_frames = np.asarray(simulate(true_model, e.inputs, e.t_s)).ravel()
print(
    f"rms error against the noise-free truth: interpolated data on the {DT_S * 1e3:.1f} ms "
    f"grid {rmse(clean_grid - off, d.y[:, 0] * 1e-6) * 1e9:.0f} nm (camera noise "
    f"{truth['camera']['noise_um'] * 1e3:.0f} nm); grey-box model at the camera frames "
    f"{rmse(clean_frames, grey_e2) * 1e9:.0f} nm"
)

# %% [markdown]
# The interpolated "measurements" are wrong by more than the camera noise, and their errors
# are correlated from sample to sample (an interpolant is smooth): a black-box model fitted
# to them learns the interpolant as much as the device.
#
# **What the grey-box does instead.** No interpolation is needed: the model is an ODE,
# simulated exactly (zero-order hold on the piecewise-constant laser) and read out at each
# camera timestamp, averaged over the 10 ms exposure like the camera does. Dropped frames
# are simply absent (NaN), not bridged; timestamp jitter is used as recorded. The blue
# crosses above are the model at the frames: only real measurements are fitted.

# %% [markdown]
# ## Step 3. ARX
#
# The thesis's ARX [na nb nk] = [1 2 0] (eq. 3.2: A = 1 + 0.8182 q^-1, B = 0.3736 +
# 0.3355 q^-1), by least squares on the stitched, resampled estimation record. Below: the
# coefficients with standard errors, the continuous-time equivalent (Tustin, as the thesis),
# and the unit step response (fig. 3.10).

# %%
arx = bb.fit_arx(est_st, 1, 2, 0)
for name, v, se in zip(arx.parameter_names, arx.parameters[0], arx.std_errors[0]):
    print(f"  {name:6s} {v:+.5f} +- {se:.5f}")
ct = bb.d2c(arx, "tustin")
pole_s = bb.poles(ct)[0][0]
print(f"continuous (Tustin): B(s)/F(s) = {np.round(ct.num[0][0], 3)} / {np.round(ct.den[0][0], 3)}")
print(
    f"pole {pole_s[0]:.2f} 1/s -> time constant {-1e3 / pole_s[0].real:.1f} ms; DC gain "
    f"{bb.dc_gain(arx)[0, 0]:.4f} um/mW"
)
tau = grey.estimate("thermal.tau_s")
gain_um_per_mW = float(grey.model.static_gain_m_per_W()) * 1e3
n_step = int(0.4 / DT_S)
t_step = DT_S * np.arange(n_step)
fig, ax = plt.subplots(figsize=(8, 3.8), layout="constrained")
ax.plot(
    t_step * 1e3,
    bb.step_response(arx, n_step)[:, 0, 0],
    "--",
    color="C1",
    label="ARX [1 2 0] (discrete, resampled grid)",
)
ax.plot(
    t_step * 1e3,
    gain_um_per_mW * (1 - np.exp(-t_step / tau.value)),
    "-",
    color="C0",
    label=f"grey-box (linearised): tau = {tau.value * 1e3:.1f} ms",
)
ax.set_xlabel("time after a 1 mW step [ms]")
ax.set_ylabel("displacement [um]")
ax.set_title("Unit step response (cf. thesis fig. 3.10)")
ax.grid(alpha=0.3)
ax.legend()
plt.show()

# %% [markdown]
# The ARX's time constant is about twice the true 45 ms: least squares on the *equation
# error* A(q) y - B(q) u is biased when y is noisy (and interpolated), because the noise
# enters the regressors. Its step response starts with a jump (nk = 0, a direct
# feedthrough b0) that the device does not have.
#
# The thesis's fig. 3.11/3.13: input, measurement, model output and "prediction error", on
# the estimation and the validation records. We draw both kinds of model output, because
# they are very different things: the **one-step prediction** (the model sees the measured
# displacement up to one grid step before) and the **simulation** (the model sees only the
# laser).


# %%
def error_figure(model_outputs, data, title):
    """Input, measurement and model outputs, and their errors, along a stitched record."""
    n = np.arange(data.n_samples)
    fig, axes = plt.subplots(
        3, 1, figsize=(12, 7), sharex=True, layout="constrained", height_ratios=[1, 2, 2]
    )
    axes[0].plot(n, data.u[:, 0], color="C1", lw=0.8)
    axes[0].set_ylabel("laser [mW]")
    axes[1].plot(n, data.y[:, 0], color="k", lw=0.6, label="measured (interpolated)")
    for k, (label, y_hat) in enumerate(model_outputs.items()):
        axes[1].plot(n, y_hat, lw=0.8, color=f"C{k + 2}", label=label)
        axes[2].plot(n, data.y[:, 0] - y_hat, lw=0.6, color=f"C{k + 2}", label=label)
    axes[1].set_ylabel("displacement [um]")
    axes[2].set_ylabel("error [um]")
    axes[2].set_xlabel(f"sample (stitched, {DT_S * 1e3:.2f} ms grid)")
    for ax in axes[1:]:
        ax.legend(fontsize=7, loc="upper right")
    for ax in axes:
        ax.grid(alpha=0.3)
    axes[0].set_title(title)
    return fig


def fits(model, data):
    return (
        float(bb.compare(model, data).fit_percent[0]),
        float(bb.compare(model, data, k=1).fit_percent[0]),
    )


for data, label in ((est_st, "estimation"), (val_st, "validation")):
    sim, one = fits(arx, data)
    error_figure(
        {
            f"ARX one-step prediction ({one:.1f} %)": bb.predict(arx, data, 1)[:, 0],
            f"ARX simulation ({sim:.1f} %)": bb.simulate(arx, data)[:, 0],
        },
        data,
        f"ARX [1 2 0] on the {label} record (cf. thesis fig. "
        f"{'3.11' if label == 'estimation' else '3.13'}); fit % on the "
        "resampled grid",
    )
    plt.show()

# %% [markdown]
# **What the grey-box does instead.** Its parameters are physical, come with intervals, and
# are estimated from the *simulation* error at the camera frames, so the noise does not bias
# them (the error-in-variables problem of the ARX regression does not arise). It has no
# noise model, so its only prediction is the simulation; that is what is scored.

# %%
grey_val = validate(grey, val)
for i, e in enumerate(val):
    print(
        f"  grey-box {e.name}: simulation fit {grey_val.fit_percent[e.name][0]:.1f} % "
        f"(at the camera frames, {grey_val.n_outliers[e.name]} outliers flagged)"
    )
print(
    f"  tau = {tau.value * 1e3:.2f} ms, 95 % [{tau.ci95[0] * 1e3:.2f}, {tau.ci95[1] * 1e3:.2f}]"
    f" (truth {truth['parameters']['thermal.tau_s']['value'] * 1e3:.1f} ms)"
)

# %% [markdown]
# ## Step 4. ARMAX, started from ARX
#
# The thesis kept A and B at the ARX orders and added a fifth-order C(q) "to compensate for
# the high frequency noise" (eq. 3.8), started from the ARX coefficients, then minimised the
# prediction error (PEM). `greybox.blackbox.fit_armax` starts from ARX fits as well
# (Hannan-Rissanen: a higher-order ARX gives the innovations, one least-squares step gives
# A, B and C), then Levenberg-Marquardt on the one-step prediction error with C kept
# minimum-phase.

# %%
NC = 2 if CI else 5
t0 = time.perf_counter()
armax = bb.fit_armax(est_st, 1, 2, NC, 0)
print(f"ARMAX [1 2 {NC} 0]: {time.perf_counter() - t0:.1f} s, converged={armax.converged}")
print(
    "  A =",
    np.round(armax.a[0], 4),
    " B =",
    np.round(armax.b[0, 0], 4),
    " C =",
    np.round(armax.c[0], 3),
)
armax_tau = -1e3 / bb.poles(bb.d2c(armax, "tustin"))[0][0].real
print(f"  time constant {armax_tau[0]:.1f} ms; DC gain {bb.dc_gain(armax)[0, 0]:.4f} um/mW")
sim, one = fits(armax, val_st)
error_figure(
    {
        f"ARMAX one-step prediction ({one:.1f} %)": bb.predict(armax, val_st, 1)[:, 0],
        f"ARMAX simulation ({sim:.1f} %)": bb.simulate(armax, val_st)[:, 0],
    },
    val_st,
    f"ARMAX [1 2 {NC} 0] on the validation record (cf. thesis fig. 3.16); "
    "fit % on the resampled grid",
)
plt.show()

# %% [markdown]
# The C(q) polynomial makes the one-step predictor better still: it models the correlated
# error, which here is mostly *interpolation* error. It does not make the simulation better
# (there the deterministic part A, B has to be right), and here it made it much worse: with
# C absorbing the correlated error, the prediction-error fit has no reason to put A's pole
# at the physical time constant (printed above; truth 45 ms). This is the thesis's
# experience too (its ARMAX pole moved from the ARX's, eq. 3.8-3.9).
#
# **What the grey-box does instead.** The measurement error of a camera tracker is close to
# white at the frames (here: Gaussian tracking noise plus a burst of corrupted frames), and
# the grey-box is fitted at the frames, so it needs no noise model. The corrupted burst is
# handled by the robust (Huber) loss, which down-weights frames far from the model instead
# of building a filter around them.

# %%
print("outliers flagged by the grey-box fit:", {k: v for k, v in grey.n_outliers.items() if v})
burst = est[3]
z = grey.predict(3)[:, 0]
r = (burst.y[:, 0] - z) / grey.sigma[0]
fig, ax = plt.subplots(figsize=(11, 3.4), layout="constrained")
ax.plot(burst.t_s, r, ".", ms=3, color="0.3", label="grey-box residual / sigma")
ax.axhline(3, color="C3", ls="--", lw=1, label="+-3 sigma")
ax.axhline(-3, color="C3", ls="--", lw=1)
ax.set_xlabel("time [s]")
ax.set_ylabel("normalised residual [1]")
ax.set_title(
    f"{burst.name}: the corrupted burst stands out of white residuals "
    f"(sigma = {grey.sigma[0] * 1e9:.0f} nm)"
)
ax.grid(alpha=0.3)
ax.legend(fontsize=8)
plt.show()

# %% [markdown]
# ## Step 5. Recursive ARX and ARMAX with a Kalman filter, carried into validation
#
# As in the thesis (section 3.3): order [1 2 0] (and [1 2 1 0] for ARMAX), started from the
# batch estimates, Kalman update with a random-walk parameter model; at the end of the
# estimation record the parameters *and* their covariance start the run over the
# validation record (`init=`). The thesis set P0 = 0; with a zero covariance and no process
# noise a Kalman filter never moves, so here P0 = 1e-3 I and a small process noise.
#
# The ARX pole converts to a time constant at every sample, tau(t) = -dt / ln(-a1(t)); it
# wanders with the data, and stays far from the truth.

# %%
KALMAN = dict(P0=1e-3, process_noise=1e-8)
rarx_est = bb.recursive_arx(
    est_st, 1, 2, 0, theta0=arx.parameters[0], noise_variance=float(arx.noise_variance[0]), **KALMAN
)
rarx_val = bb.recursive_arx(
    val_st, 1, 2, 0, init=rarx_est, noise_variance=float(arx.noise_variance[0]), **KALMAN
)
armax1 = bb.fit_armax(est_st, 1, 2, 1, 0)
rarmax_est = bb.recursive_armax(
    est_st,
    1,
    2,
    1,
    0,
    theta0=armax1.parameters[0],
    noise_variance=float(armax1.noise_variance[0]),
    **KALMAN,
)
rarmax_val = bb.recursive_armax(
    val_st, 1, 2, 1, 0, init=rarmax_est, noise_variance=float(armax1.noise_variance[0]), **KALMAN
)


def tau_ms(a1):
    return -DT_S / np.log(np.clip(-a1, 1e-9, 1 - 1e-12)) * 1e3


n_est = est_st.n_samples
n_all = np.arange(n_est + val_st.n_samples)
fig, ax = plt.subplots(figsize=(11, 4), layout="constrained")
ax.plot(
    n_all,
    tau_ms(np.concatenate([rarx_est.parameters[:, 0], rarx_val.parameters[:, 0]])),
    color="C1",
    lw=1,
    label="recursive ARX [1 2 0]",
)
ax.plot(
    n_all,
    tau_ms(np.concatenate([rarmax_est.parameters[:, 0], rarmax_val.parameters[:, 0]])),
    color="C2",
    lw=1,
    label="recursive ARMAX [1 2 1 0]",
)
ax.axhspan(
    tau.ci95[0] * 1e3,
    tau.ci95[1] * 1e3,
    color="C0",
    alpha=0.3,
    label="grey-box tau, 95 % interval (all runs)",
)
ax.axhline(truth["parameters"]["thermal.tau_s"]["value"] * 1e3, color="k", ls=":", label="truth")
ax.axvline(n_est, color="0.4", lw=1)
ax.set_ylim(0, 250)  # the spike near the middle of the estimation record: e4's corrupted burst
ax.text(n_est, 240, "estimation | validation ", ha="right", va="top", fontsize=8)
ax.set_xlabel(f"sample (stitched, {DT_S * 1e3:.2f} ms grid)")
ax.set_ylabel("time constant from a1 [ms]")
ax.set_title("Recursive estimates carried from estimation into validation")
ax.grid(alpha=0.3)
ax.legend(fontsize=8, loc="center right")
plt.show()
print(
    "final recursive ARX parameters:",
    np.round(rarx_val.final_parameters, 4),
    "+-",
    np.round(np.sqrt(np.diag(rarx_val.covariance)), 4),
)

# %% [markdown]
# The recursive time constant wanders with the data it sees, jumps where the corrupted burst
# of `e4_15mW_400ms` enters the record, and settles nowhere near the truth: carrying it into
# the validation data carries the bias along (the equation-error bias of step 3 again).
#
# **What the grey-box does instead.** The physics does not change between runs, so the
# parameters are fitted once, on all estimation runs together, with a covariance; on the
# validation runs `greybox.validate` holds them fixed and re-fits only each run's camera
# offset (what genuinely changes from run to run), then simulates. If a parameter were
# suspected to drift, the grey-box answer is to free it per run (`per_experiment=True`) and
# compare the per-run intervals: a drift then has a physical name and a size, instead of
# being absorbed into a moving a1.

# %% [markdown]
# ## Step 6. Prediction-error plots
#
# The thesis compared its models by their prediction error on the validation record. Below,
# the errors on the three validation runs: black-box one-step errors and simulation errors
# (on the resampled grid, the thesis's view), and the grey-box simulation error at the
# camera frames. One-step errors are small for every black-box model, because they are
# one step (3 ms) ahead; the simulation errors show which model knows the device.

# %%
recursive_val_pred = rarx_val.prediction
curves = {
    "ARX one-step": bb.predict(arx, val_st, 1)[:, 0],
    f"ARMAX [1 2 {NC} 0] one-step": bb.predict(armax, val_st, 1)[:, 0],
    "recursive ARX one-step (carried over)": recursive_val_pred,
    "ARX simulation": bb.simulate(arx, val_st)[:, 0],
    f"ARMAX [1 2 {NC} 0] simulation": bb.simulate(armax, val_st)[:, 0],
    "recursive ARX simulation (final parameters)": bb.simulate(rarx_val.model(), val_st)[:, 0],
}
bounds = np.cumsum([0] + [d.n_samples for d, _ in val_u])  # run k: samples bounds[k]:bounds[k+1]
fig, axes = plt.subplots(2, 1, figsize=(12, 6.5), sharex=True, sharey=True, layout="constrained")
for k, (label, y_hat) in enumerate(curves.items()):
    ax = axes[0] if "one-step" in label else axes[1]
    err = val_st.y[:, 0] - y_hat
    for i, (_, t_grid) in enumerate(val_u):  # one line per run, runs placed 20 s apart
        ax.plot(
            t_grid + 20.0 * i,
            err[bounds[i] : bounds[i + 1]],
            lw=0.6,
            color=f"C{k + 1}",
            label=(
                f"{label} ({fit_percent(val_st.y[:, 0], y_hat):.1f} %, resampled grid)"
                if i == 0
                else None
            ),
        )
for i, e in enumerate(val):
    z = grey_val.predictions[i][:, 0]
    axes[1].plot(
        e.t_s + 20.0 * i,
        (e.y[:, 0] - z) * 1e6,
        ".",
        ms=2.5,
        color="C0",
        label=(
            f"grey-box simulation, at the camera frames "
            f"({np.mean(list(grey_val.fit_percent.values())):.1f} % mean)"
        )
        if i == 0
        else None,
    )
axes[0].set_title("one-step prediction errors (validation runs)")
axes[1].set_title("simulation errors (validation runs)")
for ax in axes:
    ax.set_ylabel("measured - model [um]")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="lower right")
    ax.set_ylim(-1.0, 1.0)
axes[1].set_xlabel("time [s] (validation runs placed 20 s apart)")
plt.show()

# %% [markdown]
# ## Summary
#
# - **Stitch experiments** (a black-box fit wants one long exciting record). Grey-box: fits
#   all runs jointly, each on its own time axis, with one camera offset per run.
# - **Resample 10x by interpolation** (polynomial models need a uniform grid). Grey-box:
#   evaluates the ODE at the camera timestamps (exposure-averaged); dropped frames stay
#   missing, nothing is invented between frames.
# - **ARX** (linear least squares is easy). Grey-box: physical parameters (tau, absorptance)
#   from the simulation error at the frames, with 95 % intervals, no noise-induced bias.
# - **ARMAX from ARX** (model the correlated error, here largely interpolation error).
#   Grey-box: no noise model needed at the frames; a robust loss for corrupted frames.
# - **Recursive Kalman ARX/ARMAX carried into validation** (parameters "converge" online).
#   Grey-box: parameters fixed by physics; validation re-fits only each run's offset; a
#   suspected drift becomes a per-run parameter with an interval.
# - **Prediction-error plots** (judge the models). Grey-box: the simulation error at the
#   frames, the test that matters for new waveforms.

# %%
print(f"notebook run time: {time.perf_counter() - T_START:.0f} s")
