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
# # Grey-box vs black-box on the laser-heated chevron
#
# On the embedded data set (`experiments/chevron_laser/`: six estimation runs, three
# validation runs, 30 fps camera with jitter, dropped frames and a burst of corrupted frames)
# we fit
#
# - the **grey-box** model (`models/chevron_laser.py`: laser spot -> first-order thermal RC
#   -> beam elongation -> chevron kinematics -> camera exposure average; two physical
#   parameters shared by all runs, one camera offset per run), and
# - the **black-box** models of the thesis workflow: ARX, ARMAX, OE, and recursive (Kalman)
#   ARX/ARMAX,
#
# and compare them on (a) the estimation data, (b) the validation data and (c) extrapolation:
# waveforms outside the estimation range (higher power, shorter and longer periods, 20 %
# duty, a pseudo-random trace), generated with the *true* model of the data set.
#
# Every score says its horizon: **simulation** (free run from the input alone) or
# **one-step prediction** (the model also sees the measured output up to the previous sample).
# The point to take away: one-step fit flatters black-box models; what a model is for (new
# waveforms, design) is simulation.

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
from IPython.display import Markdown, display  # noqa: E402

CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")
ROOT = next(p for p in (Path.cwd(), *Path.cwd().parents) if (p / "experiments").is_dir())
DATA = ROOT / "experiments" / "chevron_laser"

from greybox import PulseTrain, fit, validate  # noqa: E402
from greybox import blackbox as bb  # noqa: E402
from greybox.io import load_experiment_set  # noqa: E402
from greybox.metrics import fit_percent  # noqa: E402
from greybox.parameters import parameter_table, set_values  # noqa: E402
from greybox.uncertainty import propagate  # noqa: E402
from greybox.waveforms import CameraDefects, concatenate, multilevel_prbs, record  # noqa: E402


def table(header, rows):
    """A markdown table (rendered in the notebook)."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return Markdown("\n".join(lines))


T_START = time.perf_counter()
print(f"CI mode: {CI}; repository: {ROOT}")

# %% [markdown]
# ## 1. The grey-box fit
#
# `greybox.fit` minimises the free-run **simulation** error at the camera timestamps (robust
# Huber loss: the burst of corrupted frames in `e4_15mW_400ms` is down-weighted, not
# modelled). Free: absorptance and the thermal time constant (shared), one camera offset
# per run. Everything else stays at the device's nominal value.

# %%
fitset = load_experiment_set(DATA)
truth = json.loads((DATA / "truth.json").read_text())
t0 = time.perf_counter()
grey = fit(fitset.model, fitset.estimation, fitset.free, **fitset.fit_options)
print(f"grey-box fit: converged={grey.converged}, {time.perf_counter() - t0:.1f} s")
shared = [p for p in grey.parameters if p.experiment is None]
true_values = {p.name: truth["parameters"][p.path]["value"] for p in shared}
display(Markdown("\n".join(parameter_table(shared, truth=true_values))))

# %% [markdown]
# ## 2. Data for the black-box models
#
# ARX/ARMAX/OE need a uniform time grid; the camera gives irregular frames (30 fps with
# 2 ms jitter) with dropped frames. As the thesis did (191 -> 1910 samples, 10x), each run is
# **resampled** by interpolation (`greybox.blackbox.uniform_from_experiment`: shape-preserving
# `pchip`) onto a 10 ms grid after dropping the NaN frames; the laser input is the known
# waveform evaluated exactly on the grid. Each run's camera offset (the shuttle's rest
# position in the image) is removed by subtracting the **median of the frames before the
# laser first switches on** (`Experiment.rest_level()`; every run starts with 300 ms
# laser-off). Units for the black-box models: mW in, um out. Everything computed on this grid
# is labelled *resampled*.
#
# Scoring is the same for every model: **simulation fit % at the actual camera frames
# against the measured values** (the black-box simulation is interpolated from its grid to
# the frame times, the offset added back; grey-box: its simulation at the frames). The
# grey-box fits its offsets; for a like-for-like comparison the verdict uses the *same*
# pre-laser-median offset rule for the grey-box too (both columns are shown).

# %%
DT_S = 0.010  # resampling interval [s] (camera frame interval 33 ms: ~3.3x)
DELAY_S = 0.300  # laser-off time at the start of every run [s]


def uniform(e):
    """(UniformData in mW/um on the DT_S grid, grid times [s], removed rest level [m])."""
    d, t_grid, rest = bb.uniform_from_experiment(e, DT_S, input_scale=1e3, output_scale=1e6)
    return d, t_grid, float(rest[0])


def blackbox_at_frames(model, e):
    """Black-box free-run simulation [m] at the camera frames of `e` (offset added back)."""
    d, t_grid, off = uniform(e)
    y_grid = bb.simulate(model, d)[:, 0]
    return np.interp(e.t_s, t_grid, y_grid) * 1e-6 + off


est_data = [uniform(e)[0] for e in fitset.estimation]
val_data = [uniform(e)[0] for e in fitset.validation]
print(
    f"resampled: {sum(e.n_frames for e in fitset.estimation)} camera frames -> "
    f"{sum(d.n_samples for d in est_data)} grid samples (estimation)"
)

# %% [markdown]
# ## 3. The black-box models
#
# - **ARX [1 2 0]**: the thesis's order (eq. 3.2), linear least squares (equation error).
# - **ARX, AIC order**: the order picked by `arx_order_search` (one-step loss on the
#   validation data, AIC), as `arxstruc/selstruc` would.
# - **ARMAX [1 2 1 0]**: prediction-error method, started from ARX (Hannan-Rissanen).
# - **OE [2 1 0]** (nb nf nk): minimises the *simulation* error, the linear counterpart of
#   the grey-box fit.
# - **Recursive ARX / ARMAX** (Kalman filter, random-walk parameters) on the stitched
#   estimation runs, started from the batch estimates and carried on into every scored run
#   (the thesis's fig. 3.18-3.19). Their "simulation" uses the final parameters.

# %%
grid = (
    dict(na=range(1, 4), nb=range(1, 3), nk=range(0, 2))
    if CI
    else dict(na=range(1, 5), nb=range(1, 4), nk=range(0, 3))
)
search = bb.arx_order_search(est_data, val_data, **grid)
t0 = time.perf_counter()
arx = bb.fit_arx(est_data, 1, 2, 0)
arx_aic = bb.fit_arx(est_data, *search.best)
armax = bb.fit_armax(est_data, 1, 2, 1, 0)
oe = bb.fit_oe(est_data, 2, 1, 0)
stitched = bb.UniformData(
    np.concatenate([d.u for d in est_data]),
    np.concatenate([d.y for d in est_data]),
    DT_S,
    resampled=True,
    name="stitched estimation runs",
)
KALMAN = dict(P0=1e-3, process_noise=1e-7)  # small prior covariance, slow random walk
rarx = bb.recursive_arx(
    stitched,
    1,
    2,
    0,
    theta0=arx.parameters[0],
    noise_variance=float(arx.noise_variance[0]),
    **KALMAN,
)
rarmax = bb.recursive_armax(
    stitched,
    1,
    2,
    1,
    0,
    theta0=armax.parameters[0],
    noise_variance=float(armax.noise_variance[0]),
    **KALMAN,
)
print(
    f"black-box fits: {time.perf_counter() - t0:.1f} s; AIC-selected ARX order "
    f"{list(search.best)}; ARMAX converged={armax.converged}, OE converged={oe.converged}"
)

BLACK = {
    "ARX [1 2 0]": (arx, None),
    f"ARX {list(search.best)} (AIC)": (arx_aic, None),
    "ARMAX [1 2 1 0]": (armax, None),
    "OE [2 1 0]": (oe, None),
    "recursive ARX [1 2 0]": (rarx.model(), rarx),
    "recursive ARMAX [1 2 1 0]": (rarmax.model(), rarmax),
}


def one_step_fit(name, e):
    """Black-box one-step prediction fit % on the resampled grid (initial samples skipped)."""
    model, recursive = BLACK[name]
    d = uniform(e)[0]
    if recursive is None:
        return float(bb.compare(model, d, k=1, skip_initial=True).fit_percent[0])
    run = (
        bb.recursive_arx(d, 1, 2, 0, init=recursive)
        if recursive.kind == "arx"
        else bb.recursive_armax(d, 1, 2, 1, 0, init=recursive)
    )
    n = bb.n_initial(model)
    return fit_percent(d.y[n:, 0], run.prediction[n:])


# %% [markdown]
# ## 4. Extrapolation waveforms
#
# Generated with the **true** model of the data set (`truth.json`: absorptance 0.62,
# tau 45 ms) and the same camera defects (30 fps, 2 ms jitter, 0.05 um noise, 5 % dropped
# frames), each with 300 ms laser-off before and 700 ms after, and a random rest position:
#
# | run | what is outside the estimation range (5-30 mW, 200-1000 ms, 50 % duty) |
# |---|---|
# | `x1_45mW_400ms` | higher power (45 mW) |
# | `x2_15mW_100ms` | shorter period (100 ms, about 2 tau: 3 camera frames per period) |
# | `x3_20mW_2000ms` | longer period (2 s) |
# | `x4_20mW_500ms_duty20` | 20 % duty |
# | `x5_prbs_0-40mW` | pseudo-random 5-level trace, 0-40 mW, 150 ms holds |
#
# Under `CI=true` only three of them are used, with fewer pulses.

# %%
m_per_px = fitset.camera["m_per_px"]
true_model = set_values(
    fitset.model, list(truth["parameters"]), [v["value"] for v in truth["parameters"].values()]
)
cam = truth["camera"]
defects = CameraDefects(
    fps=cam["fps"],
    jitter_s=cam["jitter_ms"] * 1e-3,
    noise_m=cam["noise_um"] * 1e-6,
    drop_fraction=cam["drop_fraction"],
)
span = 4.0 if CI else 10.0  # seconds of pulses per run


def pulses(power_W, period_s, duty=0.5):
    return PulseTrain(
        power_W, period_s, duty, max(2, int(round(span / period_s))), delay_s=DELAY_S, tail_s=0.7
    )


prbs = concatenate(
    [
        PulseTrain(0.0, DELAY_S, 0.5, 1),
        multilevel_prbs([0.0, 10e-3, 20e-3, 30e-3, 40e-3], 0.15, int(span / 0.15), seed=3),
        PulseTrain(0.0, 0.7, 0.5, 1),
    ]
)
waves = {
    "x1_45mW_400ms": pulses(45e-3, 0.4),
    "x2_15mW_100ms": pulses(15e-3, 0.1),
    "x3_20mW_2000ms": pulses(20e-3, 2.0),
    "x4_20mW_500ms_duty20": pulses(20e-3, 0.5, duty=0.2),
    "x5_prbs_0-40mW": prbs,
}
if CI:
    waves = {k: waves[k] for k in ("x1_45mW_400ms", "x2_15mW_100ms", "x5_prbs_0-40mW")}
rng = np.random.default_rng(20240601)
extrapolation = []
for name, wave in waves.items():
    rest_m = (312.0 + rng.uniform(-4.0, 4.0)) * m_per_px
    run_model = set_values(true_model, ["camera.offset_m"], [rest_m])
    e, _ = record(
        run_model,
        wave,
        name=name,
        defects=defects,
        seed=int(rng.integers(2**31)),
        role="validation",
    )
    extrapolation.append(e)
print("extrapolation runs:", {e.name: e.n_frames for e in extrapolation})

# %% [markdown]
# ## 5. Scores
#
# Every camera frame that is not a dropped frame is scored, including the burst of 8
# corrupted frames in `e4_15mW_400ms` (2-4 um off): that burst dominates the residual norm of
# that run, which is why *every* model scores about 20 % there. (`greybox fit` itself reports
# fit % without the frames it flags as outliers; here all models are treated alike.)
#
# Grey-box on new runs: `greybox.validate` keeps the physics fixed and re-fits only each
# run's camera offset, then simulates. The grey-box is an **output-error model with no noise
# model**: its one-step predictor is its simulation, so its one-step fit equals its
# simulation fit. Black-box one-step fits are computed on the resampled 10 ms grid (where
# the models live), skipping the initial samples.

# %%
t0 = time.perf_counter()
new_runs = list(fitset.validation) + extrapolation
grey_new = validate(grey, new_runs)
grey_pred = {e.name: grey.predict(i)[:, 0] for i, e in enumerate(fitset.estimation)}
grey_pred |= {e.name: z[:, 0] for e, z in zip(new_runs, grey_new.predictions)}
print(f"grey-box validation/extrapolation: {time.perf_counter() - t0:.1f} s")

SETS = {
    "estimation": list(fitset.estimation),
    "validation": list(fitset.validation),
    "extrapolation": extrapolation,
}
runs = [(s, e) for s, es in SETS.items() for e in es]


def grey_same_offset(e):
    """Grey-box simulation with the black-box offset rule (pre-laser median)."""
    z = grey_pred[e.name]
    return z - z[0] + e.rest_level()[0]  # z[0] is the fitted rest position (laser still off)


scores = {}  # (model, run) -> (simulation fit % at frames, one-step fit %)
for s, e in runs:
    y = e.y[:, 0]
    g = fit_percent(y, grey_same_offset(e))
    scores["grey-box", e.name] = (g, g)
    scores["grey-box (offset re-fitted)", e.name] = (fit_percent(y, grey_pred[e.name]),) * 2
    for name, (model, _) in BLACK.items():
        scores[name, e.name] = (fit_percent(y, blackbox_at_frames(model, e)), one_step_fit(name, e))
MODELS = ["grey-box", "grey-box (offset re-fitted)", *BLACK]

rows = []
for s, es in SETS.items():
    for e in es:
        rows.append(
            [s, f"`{e.name}`"]
            + [f"{scores[m, e.name][0]:.1f} / {scores[m, e.name][1]:.1f}" for m in MODELS]
        )
display(
    Markdown(
        "**Fit % per run: simulation at the camera frames / one-step prediction "
        "(black-box one-step on the resampled grid; grey-box one-step = simulation)**"
    )
)
display(table(["set", "run", *MODELS], rows))

# %% [markdown]
# The same numbers as means per set, side by side: simulation (solid) vs one-step
# prediction (hatched). The one-step bars of the black-box models are high everywhere,
# including for models whose simulation is poor: predicting 10 ms ahead from the measured
# (interpolated, smooth) displacement is easy, whatever the model knows about the laser.

# %%
mean = {
    (m, s): np.mean([scores[m, e.name] for e in es], axis=0)
    for m in MODELS
    for s, es in SETS.items()
}
fig, axes = plt.subplots(1, 3, figsize=(14, 4.6), sharey=True, layout="constrained")
x = np.arange(len(MODELS))
for ax, s in zip(axes, SETS):
    sim = [mean[m, s][0] for m in MODELS]
    one = [mean[m, s][1] for m in MODELS]
    ax.bar(x - 0.2, sim, 0.4, label="simulation (at camera frames)", color="C0")
    ax.bar(x + 0.2, one, 0.4, label="one-step prediction", color="C1", hatch="//", alpha=0.7)
    ax.set_xticks(x, MODELS, rotation=55, ha="right", fontsize=8)
    ax.set_title(f"{s} runs (mean)")
    ax.set_ylim(0, 100)
    ax.grid(axis="y", alpha=0.3)
axes[0].set_ylabel("fit [%]")
axes[0].legend(loc="lower left", fontsize=8)
fig.suptitle("Simulation vs one-step prediction fit: one-step flatters the black-box models")
plt.show()

# %% [markdown]
# ## 6. Extrapolation, in pictures
#
# Measured frames, the grey-box simulation and the two best black-box simulations on a
# 2.5 s window of each extrapolation run (displacement relative to the rest position).

# %%
best_black = sorted(BLACK, key=lambda m: -np.mean([scores[m, e.name][0] for e in extrapolation]))[
    :2
]
fig, axes = plt.subplots(
    len(extrapolation), 1, figsize=(11, 2.6 * len(extrapolation)), layout="constrained"
)
for ax, e in zip(np.atleast_1d(axes), extrapolation):
    off = e.rest_level()[0]
    window = (e.t_s > 0.1) & (e.t_s < 2.6)
    t = e.t_s[window]
    ax.plot(t, (e.y[window, 0] - off) * 1e6, ".", ms=4, color="0.3", label="measured (camera)")
    ax.plot(
        t,
        (grey_same_offset(e)[window] - off) * 1e6,
        "-",
        lw=1.6,
        color="C0",
        label=f"grey-box ({scores['grey-box', e.name][0]:.1f} %)",
    )
    for k, m in enumerate(best_black):
        z = blackbox_at_frames(BLACK[m][0], e)
        ax.plot(
            t,
            (z[window] - off) * 1e6,
            "--",
            lw=1.2,
            color=f"C{k + 1}",
            label=f"{m} ({scores[m, e.name][0]:.1f} %)",
        )
    ax.set_title(f"{e.name}: simulation (fit % over the whole run)", fontsize=10)
    ax.set_ylabel("displacement [um]")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper right", ncol=2)
np.atleast_1d(axes)[-1].set_xlabel("time [s]")
plt.show()

# %% [markdown]
# ## 7. What each model says physically
#
# **Grey-box**: the thermal time constant and the static gain (small-signal displacement per
# watt, `static_gain_m_per_W`), each with a 95 % interval. The gain is a function of the
# fitted absorptance; its interval comes from sampling the raw (transformed) parameter
# covariance and pushing every draw through the model (`greybox.uncertainty.propagate`).
#
# **Black-box**: the discrete poles converted to continuous time (`d2c`, Tustin as in the
# thesis; ZOH where it exists) give time constants -1/Re(s); the DC gain is `dc_gain`.
# Both gains are in um/mW (1 um/mW = 1e-3 m/W). Parameter count: the grey-box has 2
# physical parameters plus one offset per run; black-box counts are polynomial coefficients
# (their offsets come from the pre-laser frames, not fitted).

# %%
# the gain of every parameter draw (raw coordinates, shared parameters), in um/mW
gains = propagate(
    lambda m: m.static_gain_m_per_W() * 1e3,
    grey.model,
    grey.free,
    grey.raw,
    grey.covariance_raw,
    400 if CI else 2000,
    seed=1,
)
gain_hat = float(grey.model.static_gain_m_per_W()) * 1e3
tau = grey.estimate("thermal.tau_s")
true_gain = float(true_model.static_gain_m_per_W()) * 1e3


def blackbox_physics(model):
    """(time constants [ms] from d2c poles, DC gain [um/mW], method used)."""
    for method in ("zoh", "tustin"):
        try:
            s = bb.poles(bb.d2c(model, method))[0][0]
            break
        except ValueError:  # a pole on the negative real axis has no ZOH equivalent
            continue
    taus = sorted(-1e3 / np.real(s))
    osc = " (complex pair)" if np.any(np.abs(np.imag(s)) > 1e-9) else ""
    return ", ".join(f"{t:.1f}" for t in taus) + osc, float(bb.dc_gain(model)[0, 0]), method


def n_params(model):
    return int(np.size(model.parameters))


rows = [
    [
        "grey-box",
        f"2 physical + {len(fitset.estimation)} offsets",
        f"{tau.value * 1e3:.2f} [{tau.ci95[0] * 1e3:.2f}, {tau.ci95[1] * 1e3:.2f}]",
        f"{gain_hat:.4f} [{np.percentile(gains, 2.5):.4f}, {np.percentile(gains, 97.5):.4f}]",
        "physics (ODE at the frame times)",
    ]
]
for name, (model, _) in BLACK.items():
    taus, g, method = blackbox_physics(model)
    rows.append([name, n_params(model), taus, f"{g:.4f}", f"d2c {method}"])
rows.append(
    [
        "**truth**",
        "",
        f"{truth['parameters']['thermal.tau_s']['value'] * 1e3:.2f}",
        f"{true_gain:.4f}",
        "`truth.json`",
    ]
)
display(
    table(
        [
            "model",
            "parameters",
            "time constant(s) [ms] (95 % interval)",
            "static gain [um/mW] (95 % interval)",
            "from",
        ],
        rows,
    )
)

# %% [markdown]
# Step responses to a 10 mW step say the same thing in one picture: the grey-box and OE
# responses rise with the physical time constant; the equation-error models (ARX, ARMAX,
# fitted to the one-step error on interpolated data) rise too slowly, because their A(q)
# has to explain the noise and the interpolation as well as the dynamics; the recursive
# versions end with a lower gain after drifting on the data they saw last. The AIC-selected
# ARX has complex poles: an oscillation the device does not have.

# %%
t_step = np.arange(0, 0.4, DT_S)
fig, ax = plt.subplots(figsize=(8, 4.2), layout="constrained")
tau_t = truth["parameters"]["thermal.tau_s"]["value"]
ax.plot(
    t_step * 1e3,
    10 * true_gain * (1 - np.exp(-t_step / tau_t)),
    "k-",
    lw=2.5,
    alpha=0.35,
    label="truth (linearised)",
)
ax.plot(
    t_step * 1e3,
    10 * gain_hat * (1 - np.exp(-t_step / tau.value)),
    "-",
    color="C0",
    lw=1.6,
    label="grey-box (linearised)",
)
for k, (name, (model, _)) in enumerate(BLACK.items()):
    ax.plot(
        t_step * 1e3,
        10 * bb.step_response(model, t_step.size)[:, 0, 0],
        "--",
        color=f"C{k + 1}",
        lw=1.1,
        label=name,
    )
ax.set_xlabel("time after the step [ms]")
ax.set_ylabel("displacement [um]")
ax.set_title("Response to a 10 mW laser step (black-box: resampled 10 ms grid)")
ax.grid(alpha=0.3)
ax.legend(fontsize=8)
plt.show()

# %% [markdown]
# ## 8. Verdict
#
# Mean fit % per set. Simulation is at the camera frames (same offset rule for every
# model); one-step prediction is on the resampled grid for the black-box models and equals
# simulation for the grey-box.

# %%
rows = []
for m in MODELS:
    if m == "grey-box (offset re-fitted)":
        continue
    cells = [f"{mean[m, s][0]:.1f}" for s in SETS] + [f"{mean[m, s][1]:.1f}" for s in SETS]
    params = f"2 + {len(fitset.estimation)} offsets" if m == "grey-box" else n_params(BLACK[m][0])
    rows.append([m, params, *cells])
display(
    table(
        [
            "model",
            "parameters",
            *[f"simulation: {s}" for s in SETS],
            *[f"one-step: {s}" for s in SETS],
        ],
        rows,
    )
)

wins, losses = [], []
for e in extrapolation:
    g = scores["grey-box", e.name][0]
    best = max(BLACK, key=lambda m: scores[m, e.name][0])
    b = scores[best, e.name][0]
    (wins if g > b else losses).append(
        f"`{e.name}`: grey-box {g:.1f} % vs best black-box {best} {b:.1f} %"
    )
lines = ["**Extrapolation, simulation fit %, grey-box against the best black-box per run:**"]
lines += [f"- grey-box wins: {w}" for w in wins]
lines += [f"- **grey-box does NOT win**: {w}" for w in losses]
lines.append("")
lines.append(
    "The grey-box beats every black-box model in simulation on every extrapolation waveform."
    if not losses
    else f"The grey-box loses on {len(losses)} of {len(extrapolation)} extrapolation "
    "waveforms (listed above)."
)
display(Markdown("\n".join(lines)))
print(f"notebook run time: {time.perf_counter() - T_START:.0f} s")

# %% [markdown]
# ### Reading the verdict
#
# - **One-step fit flatters the black-box models.** ARX and ARMAX reach high one-step fit %
#   on every set while their simulations are much worse: a one-step predictor sees the
#   measured displacement 10 ms ago, and on an interpolated (smooth) record that alone
#   predicts most of the next sample. The grey-box has no noise model, so it is judged only
#   on simulation, the harder test.
# - **OE is the closest black-box competitor**: it is fitted the way the grey-box is (to the
#   simulation error), and the device *is* nearly linear (first-order thermal lag, chevron
#   kinematics only slightly concave at these strokes), so a first-order OE model captures
#   most of it. The grey-box still wins: it is fitted at the true frame times (no
#   interpolation), models the 10 ms exposure average and the kinematic nonlinearity (the
#   45 mW run), and has 2 physical parameters instead of 3 free coefficients. The margins
#   over OE are small (about 0.2-1.5 points of fit %): on this nearly linear device the
#   grey-box's advantage is less in fit % than in what comes with it (physical parameters
#   with intervals, no resampling, the same model for any waveform or camera).
# - OE's one-step fit (which for an OE model is its simulation, scored on the resampled
#   grid) drops far below its at-the-frames score on the 100 ms run: with 3 camera frames
#   per period the interpolated "measurement" between frames is invented by the interpolant,
#   and a model that gets the physics right is penalised against it.
# - **ARX/ARMAX time constants are wrong** (equation-error bias with noisy, interpolated
#   outputs), so they extrapolate poorly in period; the recursive versions drift with the
#   data they see and inherit that bias.
# - The grey-box's parameters mean something: tau and the gain come with intervals that
#   contain the truth, and they carry over to any waveform.
