"""TCLab: fit the grey-box thermal model and black-box baselines, compare with Park et al. (2020).

For each pair (two_heaters, one_heater): fit on the estimation run, simulate the validation
run (no re-fitting on validation data), score SAE [degC], write `results.md` and figures next
to this file. Every number is a free-run simulation result, never one-step prediction.

The headline rows come from `greybox fit` itself, run on the experiment folder as committed
(ambient per run from the first readings, `[model] ambient = "first_reading"`) and on a copy
without that line (the paper's fixed 23 C room): their SAE is read from the result folder's
metrics.csv, the validation curves from predictions/validation.csv. The comparison rows below
them keep the paper's fixed 23 C ambient (the paper's model).

Run: .venv/bin/python experiments/tclab/compare.py
"""

import json
import shutil
import sys
import tempfile
from pathlib import Path

import jax

import greybox

jax.config.update("jax_enable_x64", True)

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE), str(HERE.parents[1])]

import numpy as np  # noqa: E402
import study  # noqa: E402
from tclab_data import load_folder, uniform  # noqa: E402

from greybox import blackbox as bb  # noqa: E402
from greybox.cli import main as greybox_main  # noqa: E402
from greybox.io import atomic_output_file  # noqa: E402

AMBIENT_LINE = 'ambient = "first_reading"\n'
# `greybox fit` variants: {label: keep the folder's per-run ambient rule}
GREYBOX_FIT = {
    "ambient per run from the first readings (folder as committed)": True,
    "ambient fixed at the paper's 23 C": False,
}


def greybox_fit(folder: str, per_run_ambient: bool, say=print) -> dict:
    """`greybox fit` on the experiment folder (or a copy without its ambient rule); its
    metrics.csv as {(run, output): row}, the validation predictions and params.json."""
    with tempfile.TemporaryDirectory() as tmp:
        src = HERE / folder
        if not per_run_ambient:
            src = Path(tmp) / folder
            shutil.copytree(HERE / folder, src)
            toml = (src / "experiment.toml").read_text()
            assert AMBIENT_LINE in toml, "the committed folder sets the ambient rule"
            (src / "experiment.toml").write_text(toml.replace(AMBIENT_LINE, ""))
        out = Path(tmp) / "result"
        say(f"[{folder}] greybox fit {src} (per-run ambient: {per_run_ambient})")
        rc = greybox_main(["fit", str(src), "--out", str(out), "--quiet"])
        if rc not in (0, 1):
            raise RuntimeError(f"greybox fit {src} failed (exit status {rc})")
        lines = (out / "metrics.csv").read_text().splitlines()
        head = lines[0].split(",")
        metrics = {}
        for line in lines[1:]:
            row = dict(zip(head, line.split(",")))
            metrics[(row["run"], row["output"])] = row
        pred = (out / "predictions" / "validation.csv").read_text().splitlines()
        cols = pred[0].split(",")
        data = np.array([[float(c) if c else np.nan for c in r.split(",")] for r in pred[1:]])
        unit = metrics[("validation", "T1")]["unit"]
        offset = 273.15 if unit in ("C", "degC") else 0.0
        sim = np.column_stack([data[:, cols.index(f"T{j}_sim_{unit}")] + offset for j in (1, 2)])
        return {
            "metrics": metrics,
            "val_sim_K": sim,
            "params": json.loads((out / "params.json").read_text()),
            "converged": rc == 0,
            "validation_runs": json.loads((out / "validation_runs.json").read_text()),
        }


def greybox_fit_sae(fitted: dict, role: str, outputs) -> float:
    """SAE [degC] of `greybox fit`'s metrics.csv over the scored sensors for run `role`."""
    return sum(float(fitted["metrics"][(role, f"T{j + 1}")]["sae"]) for j in outputs)


def analyse(folder: str, say=print) -> dict:
    """All fits and scores for one experiment folder."""
    one = folder == "one_heater"
    runs = load_folder(HERE / folder, ambient="paper")
    est, val = runs["estimation"], runs["validation"]
    outputs = (0,) if one else (0, 1)  # the paper scores T1 only for the single heater
    out = {
        "folder": folder,
        "outputs": outputs,
        "est": est,
        "val": val,
        "rows": [],
        "sims": {},
        "greybox": {},
    }

    def row(name, z_est, z_val, note="", k=None, ic_outputs=(0, 1)):
        """One table row; AIC/BIC from the estimation-run simulation residuals when fitted."""
        ic = (
            (None, None)
            if k is None
            else study.information_criteria(
                est.y[:, list(ic_outputs)], np.asarray(z_est)[:, list(ic_outputs)], k
            )
        )
        out["rows"].append(
            (
                name,
                study.scores(est.y, z_est, outputs),
                study.scores(val.y, z_val, outputs),
                *ic,
                note,
            )
        )

    # Candidate structures, selected by AIC on the estimation run; the two-heater set also
    # tries a free radiating area A (rejected variants stay in the selection table)
    variants = [(label, shared, ()) for label, shared in study.STRUCTURES.items()]
    if not one:
        variants += [
            (f"{label} + free area A", shared, (study.AREA_FREE,))
            for label, shared in study.STRUCTURES.items()
        ]
    out["greybox_fit"] = {}
    for label, per_run in GREYBOX_FIT.items():
        fitted = out["greybox_fit"][label] = greybox_fit(folder, per_run, say)
        if per_run:
            out["sims"][f"greybox fit, {label.split(' (')[0]}"] = fitted["val_sim_K"]
    candidates, out["variants"] = {}, []
    for label, shared, extra in variants:
        say(f"[{folder}] grey-box {label} (l2 loss, adaptive solver) on the estimation run")
        res = study.fit_greybox(est, one_heater=one, shared_sensor_lag=shared, extra_free=extra)
        z_est, z_val = study.simulate_run(res.model, est), study.simulate_run(res.model, val)
        aic, bic = study.information_criteria(est.y, z_est, len(res.free))
        weak = [p.name for p in res.parameters if p.verdict != "identifiable"]
        candidates[label] = (aic, bic, res.converged, not weak)
        out["variants"].append(
            (
                label,
                len(res.free),
                study.scores(est.y, z_est, outputs),
                study.scores(val.y, z_val, outputs),
                aic,
                bic,
                res,
                weak,
            )
        )
        if extra:
            continue
        out["greybox"][label] = res
        out["sims"][f"grey-box, {label}"] = z_val
        row(
            f"grey-box, {label}, {len(res.free)} parameters",
            z_est,
            z_val,
            ("converged" if res.converged else f"NOT converged: {res.message}")
            + (f"; not identifiable: {', '.join(weak)}" if weak else ""),
            k=len(res.free),
        )
    out["selected"] = study.select_by_aic(candidates)
    out["rows"] = [
        (f"**{r[0]} (AIC-selected)**", *r[1:]) if out["selected"] in r[0] else r
        for r in out["rows"]
    ]
    tclab = greybox.device_module("tclab")

    z_pub = [study.simulate_run(tclab.SPEC.model(shared_sensor_lag=True), e) for e in (est, val)]
    row("energy balance, paper's published parameters", *z_pub, "not fitted here")

    u_est, u_val = uniform(est), uniform(val)
    if one:  # heater 2 is off: a single-input, single-output problem as in the paper
        u_est, u_val = (
            bb.UniformData(d.u[:, :1], d.y[:, :1], d.dt, name=d.name) for d in (u_est, u_val)
        )
    arx = study.fit_arx22(u_est)
    out["arx"] = arx
    z = [bb.simulate(arx, d) + 273.15 for d in (u_est, u_val)]
    if one:
        z = [np.column_stack([zz, np.full_like(zz, np.nan)]) for zz in z]
    row(
        "ARX [2 2 1] + offset, diagonal A",
        *z,
        "least squares (one-step) fit, simulated",
        k=arx.parameters.size,
        ic_outputs=outputs,
    )
    out["sims"]["ARX (least squares)"] = z[1]
    if not one:
        pub = study.paper_arx()
        row(
            "ARX, paper's published coefficients",
            *[bb.simulate(pub, d) + 273.15 for d in (u_est, u_val)],
            "not fitted here",
        )
        for kind, label in (
            ("armax", "ARMAX [2 2 2 1] per sensor"),
            ("oe", "OE [2 1 1] per sensor"),
            ("oe22", "OE [2 2 1] per sensor"),
        ):
            say(f"[{folder}] {label}")
            models = study.fit_miso(u_est, kind)
            note = "simulation-error fit" if kind != "armax" else "one-step (PEM) fit, simulated"
            bad = [
                f"T{j + 1} after {m.n_steps} LM steps"
                for j, m in enumerate(models)
                if not m.converged
            ]
            if bad:
                note += f"; NOT converged ({', '.join(bad)})"
            row(
                label,
                *[study.simulate_miso(models, d) + 273.15 for d in (u_est, u_val)],
                note,
                k=study.MISO[kind][1] * len(models),
            )
            out.setdefault("miso", {})[kind] = models
    return out


def _param_lines(res) -> list[str]:
    lines = ["| parameter | value | 95 % interval | verdict |", "|---|---|---|---|"]
    for p in res.parameters:
        lines.append(
            f"| {p.name} [{p.unit}] | {p.value:.5g} | {p.ci95[0]:.5g} – {p.ci95[1]:.5g} "
            f"| {p.verdict} |"
        )
    return lines


def _num(v) -> str:
    return "—" if v is None else f"{v:.1f}"


def report(result: dict) -> list[str]:
    folder = result["folder"]
    paper = study.PAPER[folder]
    one = result["outputs"] == (0,)
    which = "T1 only (600 points)" if one else "T1 + T2 (1,200 points)"
    lines = [
        f"## {folder.replace('_', ' ')}",
        "",
        f"SAE in degC over {which}. **All numbers are free-run simulation results** (not "
        "one-step prediction): grey-box from the first measured temperatures; ARX/ARMAX/OE "
        "from their first 2 measured samples, then on their own outputs. Fitted on the "
        "estimation run only; nothing is re-fitted on the validation run.",
        "",
        "AIC/BIC: from the free-run simulation residuals on the **estimation run only** "
        "(Gaussian log-likelihood with the ML noise variance, n residuals, k fitted "
        "parameters: AIC = n ln(RSS/n) + 2k, BIC = n ln(RSS/n) + k ln n; lower is better; "
        + (
            "grey-box rows over both sensors, n = 1,200, as fitted; the SISO ARX row over T1, "
            "n = 600, so not comparable with them). "
            if one
            else "n = 1,200 residuals). "
        )
        + "The headline grey-box structure is the AIC-selected one among fits that "
        "converged with every parameter identifiable; the validation run was not used "
        "for fitting or for this selection.",
        "",
        "**Headline: `greybox fit` on the experiment folder** (its metrics.csv; grey-box, "
        "per-sensor lag, the folder's [fit] settings; initial temperatures from each "
        "sensor's first reading):",
        "",
        "| `greybox fit` | estimation SAE | validation SAE | validation SAE T1 / T2 | fit % "
        "(validation, T1 / T2) | converged |",
        "|---|---|---|---|---|---|",
    ]
    for label, fitted in result["greybox_fit"].items():
        m = fitted["metrics"]
        mark = "**" if "committed" in label else ""
        lines.append(
            f"| {mark}{label}{mark} | {greybox_fit_sae(fitted, 'estimation', result['outputs']):.2f}"
            f" | {mark}{greybox_fit_sae(fitted, 'validation', result['outputs']):.2f}{mark} | "
            f"{float(m[('validation', 'T1')]['sae']):.2f} / "
            f"{float(m[('validation', 'T2')]['sae']):.2f} | "
            f"{float(m[('validation', 'T1')]['fit_percent']):.1f} / "
            f"{float(m[('validation', 'T2')]['fit_percent']):.1f} | "
            f"{'yes' if fitted['converged'] else 'NO'} |"
        )
    amb = result["greybox_fit"][next(iter(GREYBOX_FIT))]["validation_runs"]["runs"]
    amb_c = amb["validation"]["settings"].get("ambient_K", float("nan")) - 273.15
    lines += [
        "",
        f"Ambient of the validation run by the rule: {amb_c:.2f} C (the mean of its two "
        "sensors' first readings), against the paper's fixed 23 C. The rows below (the "
        "comparison with the paper and the baselines) keep the paper's fixed 23 C.",
        "",
        "| model | estimation SAE | validation SAE | AIC (est.) | BIC (est.) | note |",
        "|---|---|---|---|---|---|",
    ]
    for name, (e, v) in paper.items():
        lines.append(f"| paper: {name} | {e:.2f} | {v:.2f} | — | — | Park et al. 2020 |")
    for name, e, v, aic, bic, note in result["rows"]:
        lines.append(f"| ours: {name} | {e:.2f} | {v:.2f} | {_num(aic)} | {_num(bic)} | {note} |")
    lines += [
        "",
        "Grey-box structure selection (AIC/BIC on the estimation run; a candidate must "
        "converge with every parameter identifiable to be eligible):",
        "",
        "| candidate | k | est. SAE | val. SAE | AIC | BIC | converged | not identifiable |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for label, k, e, v, aic, bic, res, weak in result["variants"]:
        mark = " **(selected)**" if label == result["selected"] else ""
        bounds = [
            f"{p.name} = {p.value:.4g}" for p in res.parameters if p.verdict != "identifiable"
        ]
        lines.append(
            f"| {label}{mark} | {k} | {e:.2f} | {v:.2f} | {aic:.1f} | {bic:.1f} | "
            f"{'yes' if res.converged else 'NO'} | {', '.join(bounds) or '—'} |"
        )
    for label, res in result["greybox"].items():
        tag = " — AIC-selected" if label == result["selected"] else ""
        lines += [
            "",
            f"Grey-box, {label}{tag} (l2 loss, {res.method} solver, simulation error, "
            f"{res.n_data} points, {res.n_steps} LM steps, {res.message}):",
            "",
        ]
        lines += _param_lines(res)
        lines += ["", "Identifiability: " + "; ".join(res.identifiability.summary())]
    return lines + [""]


def figure(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    val = result["val"]
    n_out = len(result["outputs"])
    fig, axes = plt.subplots(n_out + 1, 1, figsize=(8, 2.6 * (n_out + 1)), sharex=True)
    for j in result["outputs"]:
        ax = axes[j]
        ax.plot(val.t_s, val.y[:, j] - 273.15, ".", ms=2, color="k", label="measured")
        for (label, z), color in zip(result["sims"].items(), ("C1", "C3", "C2", "C0")):
            ax.plot(val.t_s, z[:, j] - 273.15, color=color, lw=1, label=f"{label} (simulation)")
        ax.set_ylabel(f"T{j + 1} [degC]")
        ax.legend(loc="lower right", fontsize=7)
    u = np.asarray(val.inputs(val.t_s)).reshape(val.n_frames, -1)
    axes[-1].plot(val.t_s, u[:, 0], label="H1")
    axes[-1].plot(val.t_s, u[:, 1], label="H2")
    axes[-1].set_ylabel("heater [%]")
    axes[-1].set_xlabel("time [s]")
    axes[-1].legend(fontsize=8)
    axes[0].set_title(f"TCLab {result['folder'].replace('_', ' ')}: validation run")
    fig.tight_layout()
    with atomic_output_file(path, "wb") as fh:
        fig.savefig(fh, format="png", dpi=110)
    plt.close(fig)


def _row(result: dict, prefix: str) -> tuple:
    """(estimation SAE, validation SAE) of the first table row whose name starts with `prefix`."""
    for name, e, v, *_ in result["rows"]:
        if name.strip("*").startswith(prefix):
            return e, v
    raise KeyError(prefix)


def _variant(result: dict, label: str):
    return next(v for v in result["variants"] if v[0] == label)


def notes(two: dict, one: dict) -> str:
    """The notes section; the numbers quoted come from this run's results."""
    sel, paper_label = two["selected"], "paper: shared lag tau"
    own = two["greybox"]["per-sensor lag (tau1, tau2)"]
    t1, t2 = own.estimate("tau1_s"), own.estimate("tau2_s")
    one_t2 = one["greybox"]["per-sensor lag (tau1, tau2)"].estimate("tau2_s")
    both_a = _variant(two, "per-sensor lag (tau1, tau2) + free area A")
    arx_ls, arx_pub = _row(two, "ARX [2 2 1]"), _row(two, "ARX, paper's")
    oe1, oe2 = _row(two, "OE [2 1 1]"), _row(two, "OE [2 2 1]")
    oe2_ok = all(m.converged for m in two["miso"]["oe22"])
    paper_arx = study.PAPER["two_heaters"]["ARX (na=2, nb=2)"][1]
    ci = lambda p: f"{p.value:.2f} s (95 % {p.ci95[0]:.2f}–{p.ci95[1]:.2f})"  # noqa: E731
    eligible = [v for v in two["variants"] if v[6].converged and not v[7]]
    bic_pick = min(eligible, key=lambda v: v[5])[0]
    val_pick = min(eligible, key=lambda v: v[3])[0]
    weak_a = (
        ", ".join(
            f"{p.name} = {p.value:.3g}" for p in both_a[6].parameters if p.verdict != "identifiable"
        )
        or "none"
    )
    # largest pole modulus of any F in the OE [2 2 1] models, per sensor
    oe2_poles = [max(max(abs(np.roots(f))) for f in m.f[0]) for m in two["miso"]["oe22"]]
    return f"""## Notes
- Intervals: the residuals of every TCLab fit are far from white (slow drift the model does not
  carry), so since the residual tests were added the headline 95 % intervals are Newey-West
  (HAC) sandwich intervals, 3-5x wider than the Gauss-Newton intervals this page showed
  before; the point estimates are unchanged. The Gauss-Newton ones assume white residuals
  and were too narrow for these data.
- Model: `models/tclab.py` (`TCLab`), a 2-node `greybox.blocks.ThermalNetwork`
  (convection + radiation to ambient, conduction + radiation between heaters, a first-order lag
  per sensor), the paper's fixed constants (Ta = 23 C, m = 4 g, cp = 500 J/(kg K), A = 10 cm^2,
  As = 2 cm^2, eps = 0.9). Heater inputs are held from each logged sample to the next (the
  level logged at t_k is applied on [t_k, t_k+1), as the TCLab scripts set it).
- Structure: greybox's default TCLab model has one lag per sensor (`shared_sensor_lag=False`,
  6 parameters); `shared_sensor_lag=True` is the paper's structure (one tau, 5 parameters). The
  two TMP36 sensors are separate parts glued on separately, so their lags need not agree; the
  two-heater fit gives tau1 = {ci(t1)} and tau2 = {ci(t2)}. Selection: **{sel}**, by AIC on
  the estimation run only (BIC picks {"the same" if bic_pick == sel else bic_pick}); the
  validation run was never used for fitting or for the selection rule. Honest caveat: four variants were tried during development (the paper's
  structure, + free area A, per-sensor lag, per-sensor lag + free A) and their validation
  numbers were looked at then, so the selected structure's validation SAE is not a fully blind
  test. All four are recomputed above (selection table): the per-sensor lag + free A variant
  has the lowest AIC ({both_a[4]:.1f}) and validation SAE ({both_a[3]:.2f}) but is not eligible
  (converged: {"yes" if both_a[6].converged else "no"}; not identifiable: {weak_a}, at its
  lower bound: the free area and U trade off); the best eligible structure on validation is
  {"also the AIC-selected one" if val_pick == sel else val_pick + ", not the AIC-selected one"}.
- The paper's own parameters (tclab_estimate.txt) simulated here give the "published
  parameters" row; its validation SAE is above the paper's 840.95, so the paper's table was not
  a plain simulation of those parameters (GEKKO's collocation and its input-timing convention,
  where the level at t_k acts on (t_k-1, t_k], are the likely reasons). Our fit of the paper's
  structure ({paper_label}) lands at {_row(two, "grey-box, " + paper_label)[1]:.2f} on
  validation, also above 840.95; the per-sensor lag is what brings the simulation below it.
- ARX: the paper's {paper_arx:.2f} is **not reproduced within 10 %**; the difference is
  explained, not closed. Least squares on one-step errors (as GEKKO `sysid` with
  pred='meas'), nk = 1 (GEKKO's nk = 0), an offset per output, diagonal A, simulated from the
  first two measured samples: {arx_ls[0]:.2f} / {arx_ls[1]:.2f}. Its poles sit next to 1, so a
  small one-step bias integrates into a large drift. The paper's published coefficients
  simulate to {arx_pub[0]:.2f} / {arx_pub[1]:.2f}: a far better estimation SAE than least
  squares gives, which points to GEKKO `sysid`'s default pred='model' (coefficients fitted on
  the simulation error, an output-error fit of the ARX structure with a common denominator per
  output, which greybox's OE, one F per input, cannot express exactly). The gap between the
  published coefficients simulated here and the paper's ARX row is not resolved (initial
  conditions: we start from the first two measured samples; GEKKO's own simulation convention).
  Simulation-error fits here: OE [2 1 1] per sensor {oe1[0]:.2f} / {oe1[1]:.2f}
  ({100 * (oe1[1] / paper_arx - 1):+.1f} % from the paper's ARX validation SAE, a different
  structure, so supporting evidence only); OE [2 2 1] per sensor (nf = 2, the simulation-error
  counterpart of ARX(2,2)) {oe2[0]:.2f} / {oe2[1]:.2f}, {"converged" if oe2_ok else "NOT converged in 200 LM steps"},
  largest F pole modulus {oe2_poles[0]:.3f} (T1 model) and {oe2_poles[1]:.3f} (T2 model){"" if max(oe2_poles) < 0.999 else ": the weak cross-heater path leaves a second-order F ill-determined and it reaches the stability boundary, so this row is not a trustworthy model"}.
  Its SAE is listed for completeness and not used to explain the paper's number.
- Sensitivity of the paper-structure grey-box (explored after looking at the validation run,
  so not used for any headline row; measured once by hand, not recomputed by this script):
  applying each logged heater level one sample earlier (GEKKO's convention) gives
  estimation/validation SAE 270.3/891.6 (the paper's 270.26 reproduced). `greybox fit` with
  `[data] input_applied = "before_reading"` and `[model] shared_sensor_lag = true` (ambient
  fixed at 23 C) gives the same: 270.30/891.63.
- ARMAX/OE have no offset term, so they are fitted on rises above the paper's 23 C ambient.
  AIC/BIC of black-box rows count every estimated coefficient (ARX: na + nb per input + offset
  per output; OE: nb + nf per input per sensor; ARMAX: na + nb per input + nc per sensor).
- One heater: the same two-node model is fitted on both sensors (alpha2 is fixed at the paper's
  value: heater 2 never runs, so the data cannot identify it); SAE is T1 only. Sensor 2 still
  reads the heater-2 node, heated only through the coupling, so tau2 is formally identifiable
  here, but it comes out at {ci(one_t2)}, far from the two-heater run's {t2.value:.2f} s: in
  this run tau2 absorbs the misfit of the coupling path rather than measuring the sensor, so
  it should not be read as a sensor property. The scored T1 SAE barely moves between the two
  structures.
- The one-heater estimation run has logged timestamps 0.99–1.02 s apart: the grey-box uses
  them; the black-box models treat the samples as uniform at 1 s.
{ambient_note(two, one)}"""


def ambient_note(two: dict, one: dict) -> str:
    """The note on the ambient temperature; numbers from this run's `greybox fit` rows."""
    rule, fixed = list(GREYBOX_FIT)
    sae = {
        k: (
            greybox_fit_sae(r["greybox_fit"][rule], "validation", r["outputs"]),
            greybox_fit_sae(r["greybox_fit"][fixed], "validation", r["outputs"]),
        )
        for k, r in (("two", two), ("one", one))
    }
    amb = {
        k: r["greybox_fit"][rule]["validation_runs"]["runs"]["validation"]["settings"]["ambient_K"]
        - 273.15
        for k, r in (("two", two), ("one", one))
    }
    tau2 = {
        k: r["greybox_fit"][lab]["params"]["model"]["fitted"]["tau2_s"]
        for k, r, lab in (("rule", one, rule), ("fixed", one, fixed))
    }
    rest = [abs(e.y[0, 0] - e.y[0, 1]) for e in (two["est"], two["val"])]
    return f"""- Ambient (the `greybox fit` headline rows): the committed folders take each run's
  ambient from the mean of its two sensors' first readings (`[model] ambient =
  "first_reading"`: a documented rule using only the start of each run, the reading the
  paper already uses for the initial temperatures). One heater: the validation run starts at
  {amb["one"]:.2f} C, {23 - amb["one"]:.1f} C below the paper's 23 C room, and the rule takes
  the validation SAE from {sae["one"][1]:.2f} to {sae["one"][0]:.2f} (the paper: 1991.23);
  tau2 comes out at {tau2["rule"]:.1f} s instead of {tau2["fixed"]:.1f} s (with a wrong
  ambient it absorbed the misfit). Two heaters: both runs start near {amb["two"]:.1f} C and
  the rule gives {sae["two"][0]:.2f} against {sae["two"][1]:.2f} with the fixed 23 C: the two
  sensors disagree at rest by {rest[0]:.2f} and {rest[1]:.2f} C (TMP36 offsets; the model
  has no per-sensor offset), so their mean is not the room temperature each sensor reads,
  and a 0.5 C error in ambient is comparable to that. The rule was not tuned on either
  validation run; both outcomes are reported. Sensitivity (measured once with `greybox fit`,
  not recomputed by this script): ambient fitted per run (`{{ path = "ambient_K", per_run =
  true }}` in [fit] free; on a validation run it is re-fitted with the physics fixed, so the
  validation data set it): validation SAE 545.48 (two heaters) and 265.18 (one heater, T1).
"""


def main() -> None:
    lines = [
        "# TCLab (Park et al. 2020): grey-box and black-box models vs the published table",
        "",
        "Generated by `experiments/tclab/compare.py`; data provenance in PROVENANCE.md.",
        "",
    ]
    results = {}
    for folder in ("two_heaters", "one_heater"):
        result = results[folder] = analyse(folder)
        section = report(result)
        print("\n".join(section))
        lines += section + [f"![validation]({folder}_validation.png)", ""]
        figure(result, HERE / f"{folder}_validation.png")
    lines.append(notes(results["two_heaters"], results["one_heater"]))
    with atomic_output_file(HERE / "results.md") as fh:
        fh.write("\n".join(lines))
    print(f"wrote {HERE / 'results.md'}")


if __name__ == "__main__":
    main()
