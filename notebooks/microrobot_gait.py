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
# # The micro-robot's stick-slip gait
#
# The untethered micro-robot (`models/microrobot.py`) walks by stick-slip: a pulsed laser
# spot heats two chevron actuators (left frame bare silicon, right frame gold, so they absorb
# differently), each actuator's foot stroke swings with the temperature, and a foot only
# slips once the stroke swing exceeds the contact's play (the "play" contact surrogate: the
# net step per cycle is about max(0, swing - W) for play width W). Where the spot sits
# relative to the two frames sets the left/right heating ratio, and so the turning.
#
# This notebook uses the micro-robot's pure gait functions
# (`greybox.device_module("microrobot")`; one `jax.vmap` and one
# compilation per sweep):
#
# 1. one gait: pose and foot strokes under a pulse train;
# 2. speed against pulse period (an optimum, unlike the chevron's stroke) and against duty;
# 3. turning against the spot position (the left/right absorbed-power ratio);
# 4. a fit to the tracked-pose data set `experiments/microrobot/` (synthetic, with known
#    truth): what the pose data identify and what they do not, and the fitted model's speed
#    curve with its uncertainty.

# %%
import json
import os
import time
from pathlib import Path

import jax

import greybox
import greybox.io

# float64, and compiled programs kept on disk as the greybox commands keep them (a second
# run of this notebook loads them instead of compiling)
greybox.io.configure_jax()

import jax.numpy as jnp  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from IPython.display import Markdown, display  # noqa: E402

CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")
ROOT = next(p for p in (Path.cwd(), *Path.cwd().parents) if (p / "experiments").is_dir())
DATA = ROOT / "experiments" / "microrobot"

from greybox import fit, validate  # noqa: E402
from greybox.io import load_experiment_set  # noqa: E402
from greybox.parameters import set_values  # noqa: E402
from greybox.uncertainty import delta_method, propagate  # noqa: E402

microrobot = greybox.device_module("microrobot")  # noqa: E402

T_START = time.perf_counter()
N_SWEEP = 16 if CI else 40
N_DRAWS = 8 if CI else 40
POWER_W = 0.020
model = microrobot.SPEC.model(substeps=4)  # play contacts
tau_s = float(model.thermal.frame_time_constant_s())
width_m = float(model.locomotion.play_width_m())
print(
    f"CI mode: {CI}; frame thermal time constant {tau_s * 1e3:.2f} ms, play width "
    f"{width_m * 1e9:.0f} nm, laser {POWER_W * 1e3:.0f} mW"
)

# %% [markdown]
# ## 1. One gait
#
# 12 cycles of a 16 ms, 50 % duty pulse train, spot at its nominal position (60 um towards
# the left frame). Top: the two foot strokes (left heats more). Bottom: the body advance X
# (steps only while the stroke swing exceeds the play) and the heading psi.

# %%
PERIOD_S, DUTY, N_CYCLES, SPC = 0.016, 0.5, 12, 40
states = np.asarray(
    jax.jit(lambda m: microrobot.pose_history(m, PERIOD_S, DUTY, POWER_W, N_CYCLES, SPC))(model)
)
t = PERIOD_S / SPC * np.arange(states.shape[0])
strokes = np.asarray(jax.vmap(model.strokes_m)(jnp.asarray(states[:, :4])))
fig, (ax0, ax1) = plt.subplots(2, 1, figsize=(10, 6), sharex=True, layout="constrained")
ax0.plot(t * 1e3, strokes[:, 0] * 1e6, color="C0", label="left foot stroke (bare Si frame)")
ax0.plot(t * 1e3, strokes[:, 1] * 1e6, color="C1", label="right foot stroke (gold frame)")
ax0.set_ylabel("free foot stroke [um]")
ax0.legend(fontsize=8)
ax0.set_title(
    f"Pulse train: {PERIOD_S * 1e3:.0f} ms period, {DUTY:.0%} duty, {POWER_W * 1e3:.0f} mW"
)
ax1.plot(t * 1e3, states[:, 4] * 1e6, color="C2", label="body advance X")
ax1.set_ylabel("X [um]")
ax1b = ax1.twinx()
ax1b.plot(t * 1e3, np.degrees(states[:, 6]) * 1e3, color="C3", lw=1, label="heading psi")
ax1b.set_ylabel("heading psi [mdeg]", color="C3")
ax1.set_xlabel("time [ms]")
ax1.legend(loc="upper left", fontsize=8)
ax1b.legend(loc="lower left", fontsize=8)
for ax in (ax0, ax1):
    ax.grid(alpha=0.3)
plt.show()

# %% [markdown]
# ## 2. Speed against period and duty
#
# Short periods: the temperature cannot follow, the stroke swing stays below the play
# width and the robot does not move. Long periods: a full swing per cycle, but few cycles
# per second. In between, an optimum of a few thermal time constants. (Compare the chevron
# in `new_waveforms`: its stroke has no such optimum, because nothing is lost per cycle;
# the play is what makes a period optimal here.)

# %%
periods = np.geomspace(2e-3, 0.2, N_SWEEP)
sweep = jax.jit(lambda m, p: microrobot.speed_vs_period(m, p, DUTY, POWER_W))(
    model, jnp.asarray(periods)
)
speed = np.asarray(sweep["speed_m_per_s"])
best = int(np.argmax(speed))
duties = np.linspace(0.05, 0.95, 9 if CI else 19)
dsweep = jax.jit(lambda m, d: microrobot.speed_vs_duty(m, d, float(periods[best]), POWER_W))(
    model, jnp.asarray(duties)
)
fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(13, 4.2), layout="constrained")
ax0.semilogx(periods * 1e3, speed * 1e6, "o-", ms=3, color="C0", label="speed")
ax0.axvline(
    periods[best] * 1e3,
    color="C0",
    ls=":",
    label=f"best on the grid: {periods[best] * 1e3:.1f} ms = {periods[best] / tau_s:.1f} tau",
)
ax0.set_xlabel("pulse period [ms]")
ax0.set_ylabel("speed [um/s]")
ax0.grid(alpha=0.3, which="both")
ax0b = ax0.twinx()
ax0b.semilogx(
    periods * 1e3,
    np.asarray(sweep["stroke_swing_m"]) * 1e6,
    "--",
    color="C1",
    label="left stroke swing",
)
ax0b.axhline(width_m * 1e6, color="C1", ls=":", lw=1, label="play width W")
ax0b.set_ylabel("stroke swing [um]", color="C1")
ax0.legend(loc="upper left", fontsize=8)
ax0b.legend(loc="center right", fontsize=8)
ax0.set_title(f"Speed against period ({DUTY:.0%} duty, {POWER_W * 1e3:.0f} mW)")
ax1.plot(duties * 100, np.asarray(dsweep["speed_m_per_s"]) * 1e6, "o-", ms=3, color="C2")
ax1.set_xlabel("duty [%]")
ax1.set_ylabel("speed [um/s]")
ax1.set_title(f"Speed against duty (period {periods[best] * 1e3:.1f} ms, on-power fixed)")
ax1.grid(alpha=0.3)
plt.show()
print(
    f"fastest: {speed[best] * 1e6:.2f} um/s at {periods[best] * 1e3:.1f} ms; no motion "
    f"below {periods[np.argmax(speed > 1e-9)] * 1e3:.1f} ms (swing < W)"
)

# %% [markdown]
# ## 3. Turning against spot position
#
# Moving the spot across the body (y, towards the left frame for y > 0) changes how much
# power each frame absorbs; the gold right frame absorbs much less than bare silicon at
# 800 nm anyway. The hotter side steps further, so the robot turns towards the cooler side
# (psi decreases: clockwise). At 20 mW only the left foot's swing exceeds the play: whenever
# the robot moves it also turns, and moving the spot towards the gold side lowers speed and
# turning together until neither foot's swing exceeds the play and the robot stops. Walking
# straight needs the right foot to step as well (more power on the gold side).

# %%
spots = np.linspace(-100e-6, 100e-6, 9 if CI else 21)
turn = jax.jit(lambda m, y: microrobot.turning_vs_power_ratio(m, y, PERIOD_S, DUTY, POWER_W))(
    model, jnp.asarray(spots)
)
fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(13, 4.2), layout="constrained")
ax0.plot(
    spots * 1e6,
    np.degrees(np.asarray(turn["turn_rate_rad_per_s"])),
    "o-",
    ms=3,
    color="C3",
    label="turning rate",
)
ax0.set_xlabel("spot position y [um] (left frame at +110 um, right at -110 um)")
ax0.set_ylabel("turning rate d psi/dt [deg/s]")
ax0.grid(alpha=0.3)
ax0b = ax0.twinx()
ax0b.plot(
    spots * 1e6,
    np.asarray(turn["speed_m_per_s"]) * 1e6,
    "s--",
    ms=3,
    color="C0",
    label="mean speed",
)
ax0b.set_ylabel("speed [um/s]", color="C0")
ax0.legend(loc="center left", fontsize=8)
ax0b.legend(loc="upper left", fontsize=8)
ax0.set_title(
    f"Turning and speed against spot position ({PERIOD_S * 1e3:.0f} ms, {POWER_W * 1e3:.0f} mW)"
)
ratio = np.asarray(turn["power_ratio_left_right"])
ax1.semilogx(ratio, np.degrees(np.asarray(turn["turn_rate_rad_per_s"])), "o-", ms=3, color="C3")
ax1.set_xlabel("absorbed power ratio left / right [1]")
ax1.set_ylabel("turning rate d psi/dt [deg/s]")
ax1.set_title("The same, against the left/right heating ratio")
ax1.grid(alpha=0.3, which="both")
plt.show()


# %% [markdown]
# ## 4. A fit to tracked-pose data
#
# The data set `experiments/microrobot/` (made by its `generate.py` from the model at known
# "true" values, `truth.json`): two body features (front and rear) tracked at 30 fps with
# 1 ms jitter, 10 ms exposure, 65 nm tracking noise, 5 % dropped frames and a burst of two
# corrupted frames; five estimation runs (15-25 mW, 16-40 ms periods, spot 30-60 um left of
# the start axis) and one validation run. Several powers separate the thermal gain from the
# play width (the step is about gain x P - W), several periods the thermal time constant,
# several spot positions the turning.
#
# The fit is what `greybox fit experiments/microrobot` does (simulation error at the camera
# frames, Huber loss, four starts; in CI mode only the first, which is the one that reaches
# the optimum), with the device's standard free parameters: the left absorptance
# (the thermal gain), the frame heat capacity (the time constant), the foot friction
# capacity and the leg stiffness (log-normal priors), the turning gain, and one image
# offset pair per run. The gain starts low on purpose (0.30, `default_free_parameters`): a
# start that over-predicts the walk fits worse than no motion, and the fit would descend
# into the play dead zone where every motion gradient is zero.

# %%
fitset = load_experiment_set(DATA)
truth = json.loads((DATA / "truth.json").read_text())
t0 = time.perf_counter()
options = dict(fitset.fit_options)
if CI:  # the first of the folder's four starts is the one that reaches the optimum
    options["n_starts"] = 1
result = fit(fitset.model, fitset.estimation, fitset.free, **options)
checked = validate(result, fitset.validation)
print(f"fit + validation: {time.perf_counter() - t0:.1f} s, converged={result.converged}")
print(
    "residual sigma per output (f1_x, f1_y, f2_x, f2_y): "
    + ", ".join(f"{s * 1e9:.0f}" for s in result.sigma)
    + f" nm (tracking noise {truth['camera']['noise_um'] * 1e3:.0f} nm)"
)
SHOW = {  # display factor and unit per shared parameter
    "absorptance_left": (1.0, "1"),
    "thermal.frame_capacitance_J_per_K": (1e9, "nJ/K"),
    "locomotion.foot_forward_N": (1e6, "uN"),
    "locomotion.stiffness_N_per_m": (1.0, "N/m"),
    "locomotion.turn_gain": (1.0, "1"),
}
w_fit_m, w_se_m = microrobot.play_width_estimate(result)
rows = [
    (
        p.name,
        *SHOW[p.path],
        p.value,
        p.se,
        p.ci95,
        truth["parameters"][p.path]["value"],
        p.verdict + (" (prior)" if p.prior else ""),
    )
    for p in result.parameters
    if p.experiment is None
]
rows.append(
    (
        "play width W = (F_a + F_b)/k (derived)",
        1e9,
        "nm",
        w_fit_m,
        w_se_m,
        (w_fit_m - 1.96 * w_se_m, w_fit_m + 1.96 * w_se_m),
        truth["play_width_m"]["value"],
        "identified (delta method)",
    )
)
lines = [
    "| parameter | estimate | std. error | 95 % interval | true | (est. - true)/se | unit "
    "| verdict |",
    "|---|---|---|---|---|---|---|---|",
]
for name, f, unit, value, se, ci, true, verdict in rows:
    lines.append(
        f"| `{name}` | {value * f:.4g} | {se * f:.2g} | [{ci[0] * f:.4g}, "
        f"{ci[1] * f:.4g}] | {true * f:.4g} | {(value - true) / se:+.1f} | {unit} "
        f"| {verdict} |"
    )
display(
    Markdown(
        "**Recovered vs true** (simulation fit of the 5 estimation runs; intervals "
        "from the fit's raw coordinates, W's by the delta method)\n\n" + "\n".join(lines)
    )
)
for line in result.identifiability.summary():
    print(line)

# %% [markdown]
# What the pose data identify:
#
# - **the thermal gain** (left absorptance, with the conductances fixed), **the frame heat
#   capacity** (the time constant, through the step against the period) and **the turning
#   gain**: each to well under 1 %;
# - **the play width W = (F_a + F_b)/k** (derived; `models.microrobot.play_width_estimate`):
#   to about 1 %;
# - **not** the foot friction capacity or the leg stiffness separately: each stays at its
#   prior, and the identifiability report names their combination (both up or down together,
#   W unchanged) as the direction nothing in the data determines.
#
# The gain and W both come out a little low, by a couple of standard errors: they lie on one
# ridge (the step per cycle is about gain x P - W, so a slightly lower gain with a slightly
# narrower play gives nearly the same walk) and their errors are strongly correlated, so the
# two misses are one event; the joint test below puts the truth just outside the joint 95 %
# region.

# %%
gain_and_width, v = delta_method(
    lambda m: jnp.stack([m.absorptance_left, m.locomotion.play_width_m()]),
    result.model,
    result.free,
    result.raw,
    result.covariance_raw,
)
miss = gain_and_width - np.array(
    [truth["parameters"]["absorptance_left"]["value"], truth["play_width_m"]["value"]]
)
print(
    f"correlation of gain and W estimates: {v[0, 1] / np.sqrt(v[0, 0] * v[1, 1]):+.2f}; "
    f"joint chi-square of the truth: {miss @ np.linalg.solve(v, miss):.1f} on 2 degrees of "
    "freedom (95 % region: < 5.99)"
)

# %% [markdown]
# Measured and simulated image positions of the front feature, relative to where the model
# starts, for the run with the largest motion and for the validation run (physics fixed,
# only its image offsets re-fitted by `greybox.validate`). The simulation fit % is close
# to 100 % for every run only because the features sit +-200 um from the image origin; the
# residual sigma against the 65 nm tracking noise is the meaningful measure.

# %%
shown = [
    (fitset.estimation[1], result.predict(1), "estimation"),
    (fitset.validation[0], checked.predictions[0], "validation"),
]
fig, axes = plt.subplots(1, 2, figsize=(13, 4), layout="constrained")
for ax, (e, z, role) in zip(axes, shown):
    for j, label in ((0, "front feature x"), (1, "front feature y")):
        ref = z[0, j]
        ax.plot(
            e.t_s, (e.y[:, j] - ref) * 1e6, ".", ms=4, color=f"C{j}", label=f"{label}, measured"
        )
        ax.plot(
            e.t_s,
            (z[:, j] - ref) * 1e6,
            "-",
            lw=1.2,
            color=f"C{j}",
            label=f"{label}, model (simulation)",
        )
    score = (result.fit_percent if role == "estimation" else checked.fit_percent)[e.name]
    ax.set_xlabel("time [s]")
    ax.set_ylabel("image position relative to the start [um]")
    per_output = " / ".join(f"{v:.1f}" for v in score)
    ax.set_title(f"{e.name} ({role}): simulation fit {per_output} % (f1_x / f1_y / f2_x / f2_y)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
plt.show()

# %% [markdown]
# The fitted model's speed-against-period curve (spot at y = 60 um, as in section 2) and
# its uncertainty, against the true robot's, two ways:
#
# - **delta method** (first order in the raw parameters): along the undetermined friction
#   direction W does not change to first order, so only the identified quantities (gain,
#   heat capacity, W) widen the band;
# - **sampling** (`greybox.uncertainty.propagate`: Gaussian draws of the raw shared
#   parameters, each pushed through the gait), the usual tool for an optimum or a threshold.

# %%
SPOT = ["spot.x_m", "spot.y_m"]
fitted_robot = set_values(result.model, SPOT, [0.0, 60e-6])
true_robot = set_values(
    fitted_robot, list(truth["parameters"]), [v["value"] for v in truth["parameters"].values()]
)


def speeds(m):
    return microrobot.speed_vs_period(m, jnp.asarray(periods), DUTY, POWER_W)["speed_m_per_s"]


fitted_curve, v = delta_method(speeds, fitted_robot, result.free, result.raw, result.covariance_raw)
sd_curve = np.sqrt(np.clip(np.diag(v), 0.0, None))
true_curve = np.asarray(jax.jit(speeds)(true_robot))
drawn = propagate(
    lambda m: jnp.concatenate([speeds(m), m.locomotion.play_width_m()[None]]),
    fitted_robot,
    result.free,
    result.raw,
    result.covariance_raw,
    N_DRAWS,
    seed=3,
)
curves, widths = drawn[:, :-1], drawn[:, -1]
stands = curves.max(axis=1) < 1e-9  # draws with no forward walk at any period
fig, ax = plt.subplots(figsize=(9, 4.2), layout="constrained")
for i, c in enumerate(curves):
    ax.semilogx(
        periods * 1e3,
        c * 1e6,
        color="0.6",
        lw=0.6,
        alpha=0.6,
        label=f"{N_DRAWS} Gaussian parameter draws" if i == 0 else None,
    )
ax.fill_between(
    periods * 1e3,
    (fitted_curve - 1.96 * sd_curve) * 1e6,
    (fitted_curve + 1.96 * sd_curve) * 1e6,
    color="C0",
    alpha=0.35,
    label="95 % band, delta method",
)
ax.semilogx(periods * 1e3, fitted_curve * 1e6, color="C0", label="fitted model")
ax.semilogx(periods * 1e3, true_curve * 1e6, "k--", lw=1, label="true robot")
ax.set_xlabel("pulse period [ms]")
ax.set_ylabel("speed [um/s]")
ax.set_title(
    f"Fitted speed against period ({DUTY:.0%} duty, {POWER_W * 1e3:.0f} mW, spot at y = 60 um)"
)
ax.grid(alpha=0.3, which="both")
ax.legend(fontsize=8)
plt.show()
k = int(np.argmax(fitted_curve))
print(
    f"fastest period (grid): fitted {periods[k] * 1e3:.1f} ms, true "
    f"{periods[np.argmax(true_curve)] * 1e3:.1f} ms; top speed fitted "
    f"{fitted_curve[k] * 1e6:.2f} +- {sd_curve[k] * 1e6:.2f} um/s (delta method), true "
    f"{true_curve[k] * 1e6:.2f} um/s"
)
print(
    f"Gaussian draws: W from {widths.min() * 1e9:.0f} to {widths.max() * 1e9:.0f} nm "
    f"(fit: {w_fit_m * 1e9:.1f} +- {w_se_m * 1e9:.1f} nm); no forward walk at any period in "
    f"{stands.sum()} of {N_DRAWS} draws"
)
print(f"notebook run time: {time.perf_counter() - T_START:.0f} s")

# %% [markdown]
# **Why the draws scatter so much more than the fit allows.** The foot capacity and the
# stiffness are each known only to their priors (standard errors a quarter to a half of the
# values), and a Gaussian in their log coordinates is a straight line through a curved
# valley of constant W: far along it W drifts away from its fitted value, and where a draw
# puts the foot capacity above the dimple's share (F_f+ > F_d-/2) the feet stop slipping
# forward and the robot no longer walks forward, which every estimation run rules out. The
# data exclude those draws, but a Gaussian covariance cannot say so. For this model the
# delta-method band (or draws confined to the identified directions) is the honest one;
# sampling is safe when the prior-dominated parameters do not change what the model does.
#
# In short: from tracked poses alone, the gait's speed curve and its optimum period are
# predicted from the identified quantities (gain, time constant, W, turning gain); the
# friction forces and the stiffness need a different experiment (a force measurement or a
# known load), not more pose data.
