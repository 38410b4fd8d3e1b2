"""TCLab: fit the grey-box thermal model and black-box baselines, compare with Park et al. (2020).

For each pair (two_heaters, one_heater): fit on the estimation run, simulate the validation
run (no re-fitting of the physics on validation data), score SAE [degC], write `results.md`
and figures next to this file. Every number is a free-run simulation result, never one-step
prediction.

- Structure selection is `greybox compare` on the experiment folder: its `[[candidates]]`
  (sensor lags per sensor or shared, area A free or not, ambient fixed at 23 C or from the
  first readings, sensor offsets), ranked by AIC on the estimation run among the valid fits;
  the selection table below is read from its compare.json. The folder's default ([model] and
  [fit] free) must be the preferred candidate: this script checks it and says so.
- The grey-box rows are `greybox fit` on the folder as committed and on copies whose [model]
  and [fit] free are those of a candidate: SAE from metrics.csv, curves from predictions/,
  parameters from params.json.
- The comparison rows (the paper's table and the black-box baselines) keep the paper's fixed
  23 C ambient (the paper's model).

Run: .venv/bin/python experiments/tclab/compare.py
"""

import json
import shutil
import sys
import tempfile
import tomllib
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
from greybox.io import atomic_output_file, load_experiment_set  # noqa: E402

# `greybox fit` rows: candidates of the folders' [[candidates]] fitted and validated as the
# folder is, {candidate name: row label}; the folder as committed is fitted as well
PER_SENSOR_23C = "per-sensor lag, ambient 23 C"
SHARED_23C = "shared lag (the paper's structure), ambient 23 C"
FIRST_READING = "per-sensor lag, ambient from first readings"
FIRST_READING_OFFSET = "per-sensor lag, ambient from first readings, sensor 2 offset"
FIT_ROWS = {
    PER_SENSOR_23C: "ambient fixed at the paper's 23 C",
    FIRST_READING: "ambient from each run's first readings",
    FIRST_READING_OFFSET: "ambient from the first readings minus the offsets, sensor 2 "
    "offset fitted (shared by the runs)",
    SHARED_23C: "the paper's shared lag, ambient 23 C",
}


def greybox_compare(folder: str, say=print) -> dict:
    """`greybox compare` on the experiment folder: its compare.json (and compare.md text)."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "compare"
        say(f"[{folder}] greybox compare {HERE / folder}")
        rc = greybox_main(["compare", str(HERE / folder), "--out", str(out), "--quiet"])
        if rc not in (0, 1):
            raise RuntimeError(f"greybox compare {folder} failed (exit status {rc})")
        doc = json.loads((out / "compare.json").read_text())
        doc["markdown"] = (out / "compare.md").read_text()
    doc["by_name"] = {c["name"]: c for c in doc["candidates"]}
    return doc


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{json.dumps(k)} = {_toml_value(x)}" for k, x in v.items()) + " }"
    raise TypeError(type(v))


def candidate_toml(text: str, name: str) -> str:
    """The folder's experiment.toml with [model] and [fit] free replaced by candidate
    `name`'s (as `greybox compare` fits it: the candidate's options over [model])."""
    data = tomllib.loads(text)
    cand = next(c for c in data["candidates"] if c["name"] == name)
    data["model"] = {**data.get("model", {}), **cand.get("model", {})}
    data.setdefault("fit", {})["free"] = cand["free"]
    del data["candidates"]
    lines = []
    for table in ("experiment", "model", "fit"):
        lines.append(f"[{table}]")
        lines += [f"{k} = {_toml_value(v)}" for k, v in data.get(table, {}).items()]
        lines.append("")
    for run in data["runs"]:
        lines.append("[[runs]]")
        lines += [f"{k} = {_toml_value(v)}" for k, v in run.items()]
        lines.append("")
    return "\n".join(lines)


def greybox_fit(folder: str, candidate: str | None = None, say=print) -> dict:
    """`greybox fit` on the experiment folder (candidate None) or on a copy fitted as
    candidate `candidate`: metrics.csv as {(run, output): row}, the predictions of both runs
    (simulation, K), params.json and validation_runs.json."""
    with tempfile.TemporaryDirectory() as tmp:
        src = HERE / folder
        if candidate is not None:
            src = Path(tmp) / folder
            shutil.copytree(HERE / folder, src)
            toml = (src / "experiment.toml").read_text()
            (src / "experiment.toml").write_text(candidate_toml(toml, candidate))
        out = Path(tmp) / "result"
        say(f"[{folder}] greybox fit {src} ({candidate or 'as committed'})")
        rc = greybox_main(["fit", str(src), "--out", str(out), "--quiet"])
        if rc not in (0, 1):
            raise RuntimeError(f"greybox fit {src} failed (exit status {rc})")
        lines = (out / "metrics.csv").read_text().splitlines()
        head = lines[0].split(",")
        metrics = {}
        for line in lines[1:]:
            row = dict(zip(head, line.split(",")))
            metrics[(row["run"], row["output"])] = row
        sims = {}
        for run in ("estimation", "validation"):
            pred = (out / "predictions" / f"{run}.csv").read_text().splitlines()
            cols = pred[0].split(",")
            data = np.array([[float(c) if c else np.nan for c in r.split(",")] for r in pred[1:]])
            unit = metrics[(run, "T1")]["unit"]
            offset = 273.15 if unit in ("C", "degC") else 0.0
            sims[run] = np.column_stack(
                [data[:, cols.index(f"T{j}_sim_{unit}")] + offset for j in (1, 2)]
            )
        return {
            "candidate": candidate,
            "metrics": metrics,
            "sims_K": sims,
            "params": json.loads((out / "params.json").read_text()),
            "converged": rc == 0,
            "validation_runs": json.loads((out / "validation_runs.json").read_text()),
        }


def greybox_fit_sae(fitted: dict, role: str, outputs) -> float:
    """SAE [degC] of `greybox fit`'s metrics.csv over the scored sensors for run `role`."""
    return sum(float(fitted["metrics"][(role, f"T{j + 1}")]["sae"]) for j in outputs)


def committed_candidate(folder: str, compared: dict) -> str | None:
    """The candidate whose options and free list are the folder's default (None if none)."""
    fs = load_experiment_set(HERE / folder)
    free = [p.path for p in fs.free]
    for c in compared["candidates"]:
        if c["options"] == fs.options and c["free"] == free:
            return c["name"]
    return None


def model_ambient_C(fitted: dict, run: str = "validation") -> float:
    """The ambient [degC] a fitted model used for `run`: 23 C, or with the first-reading rule
    the mean of the run's first readings minus the fitted sensor offsets."""
    p = fitted["params"]
    if p["device"]["options"].get("ambient") != "first_reading":
        return p["model"]["fixed"].get("ambient_K", 296.15) - 273.15
    s = fitted["validation_runs"]["runs"][run]["settings"] if run == "validation" else None
    if s is None:
        raise KeyError(run)
    values = {**p["model"]["fixed"], **p["model"]["fitted"]}
    offsets = [values.get(f"readout.offset[{j}]", 0.0) for j in (0, 1)]
    return float(np.mean([s["initial_T1_K"] - offsets[0], s["initial_T2_K"] - offsets[1]])) - 273.15


def analyse(folder: str, say=print) -> dict:
    """All fits and scores for one experiment folder."""
    one = folder == "one_heater"
    runs = load_folder(HERE / folder)
    est, val = runs["estimation"], runs["validation"]
    outputs = (0,) if one else (0, 1)  # the paper scores T1 only for the single heater
    out = {"folder": folder, "outputs": outputs, "est": est, "val": val, "rows": [], "sims": {}}

    def row(name, z_est, z_val, note="", k=None, ic_outputs=(0, 1)):
        """One comparison row; AIC/BIC (pooled, study.information_criteria) when fitted."""
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

    # structure selection: `greybox compare` on the folder's [[candidates]]
    compared = out["compare"] = greybox_compare(folder, say)
    out["committed"] = committed_candidate(folder, compared)
    if out["committed"] != compared["preferred"]:
        say(
            f"[{folder}] WARNING: the folder's default is {out['committed']!r}, but greybox "
            f"compare prefers {compared['preferred']!r}; update [model] and [fit] free"
        )
    # `greybox fit` on the folder as committed and as the candidates of FIT_ROWS
    fits = out["greybox_fit"] = {"committed": greybox_fit(folder, None, say)}
    for name in FIT_ROWS:
        fits[name] = (
            fits["committed"] if name == out["committed"] else greybox_fit(folder, name, say)
        )
    out["sims"][f"greybox fit, folder default ({out['committed']})"] = fits["committed"]["sims_K"][
        "validation"
    ]
    if out["committed"] != PER_SENSOR_23C:
        out["sims"]["greybox fit, per-sensor lag, ambient 23 C"] = fits[PER_SENSOR_23C]["sims_K"][
            "validation"
        ]

    for name, label in ((PER_SENSOR_23C, "per-sensor lag"), (SHARED_23C, "paper: shared lag")):
        f = fits[name]
        k = len(f["params"]["parameters"])
        status = f["params"]["convergence"]["message"]
        row(
            f"grey-box, {label}, {k} parameters (`greybox fit`, ambient 23 C)",
            f["sims_K"]["estimation"],
            f["sims_K"]["validation"],
            status,
            k=k,
        )
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


def _param_lines(params: dict) -> list[str]:
    """The parameter table of a `greybox fit` params.json."""
    lines = ["| parameter | value | 95 % interval | verdict |", "|---|---|---|---|"]
    for p in params["parameters"]:
        lo, hi = p["ci95"] if p.get("ci95") else (None, None)
        ci = "—" if lo is None else f"{lo:.5g} – {hi:.5g}"
        lines.append(f"| {p['name']} [{p['unit']}] | {p['value']:.5g} | {ci} | {p['verdict']} |")
    return lines


def _num(v) -> str:
    return "—" if v is None else f"{v:.1f}"


def _fit_row(result: dict, key: str, label: str) -> str:
    fitted = result["greybox_fit"][key]
    m, outs = fitted["metrics"], result["outputs"]
    conv = fitted["params"]["convergence"]
    return (
        f"| {label} | {greybox_fit_sae(fitted, 'estimation', outs):.2f} | "
        f"{greybox_fit_sae(fitted, 'validation', outs):.2f} | "
        f"{float(m[('validation', 'T1')]['sae']):.2f} / {float(m[('validation', 'T2')]['sae']):.2f}"
        f" | {float(m[('validation', 'T1')]['fit_percent']):.1f} / "
        f"{float(m[('validation', 'T2')]['fit_percent']):.1f} | "
        f"{model_ambient_C(fitted):.2f} | {conv['status']} |"
    )


def report(result: dict) -> list[str]:
    folder = result["folder"]
    paper = study.PAPER[folder]
    one = result["outputs"] == (0,)
    which = "T1 only (600 points)" if one else "T1 + T2 (1,200 points)"
    cmp, committed = result["compare"], result["committed"]
    lines = [
        f"## {folder.replace('_', ' ')}",
        "",
        f"SAE in degC over {which}. **All numbers are free-run simulation results** (not "
        "one-step prediction): grey-box from the first measured temperatures; ARX/ARMAX/OE "
        "from their first 2 measured samples, then on their own outputs. Fitted on the "
        "estimation run only; nothing but declared per-run values is re-fitted on the "
        "validation run (here: none).",
        "",
        "### Structure selection: `greybox compare` on the folder",
        "",
        f"Preferred: **{cmp['preferred']}** (rule: lowest {cmp['rule'].upper()} on the "
        "estimation run among the valid fits; validation fit % shown, never used to choose). "
        + (
            "The folder's default ([model] and [fit] free) is this candidate."
            if committed == cmp["preferred"]
            else f"**The folder's default is {committed!r}, not the preferred candidate.**"
        )
        + " AIC/BIC as `greybox compare` computes them: Gaussian log-likelihood of the "
        "free-run simulation residuals with each output's noise variance at its ML value, "
        "k = fitted values + one noise variance per output, n = 1,200 readings (both "
        "sensors).",
        "",
        "| candidate | k | AIC | BIC | fit % est. (T1 / T2) | fit % val. (T1 / T2) | status |",
        "|---|---|---|---|---|---|---|",
    ]
    for c in cmp["candidates"]:
        mark = " **(preferred)**" if c["name"] == cmp["preferred"] else ""
        pct = lambda d: " / ".join(f"{v:.1f}" for v in next(iter(d.values())))  # noqa: E731
        status = c["status"] + (
            f" ({c['message'].split(';')[0].removeprefix('at bound: ')})"
            if c["status"] == "at bound"
            else ""
        )
        lines.append(
            f"| {c['name']}{mark} | {c['k']} | {c['aic']:.1f} | {c['bic']:.1f} | "
            f"{pct(c['fit_percent_estimation'])} | {pct(c['fit_percent_validation'])} | "
            f"{status} |"
        )
    lines += [
        "",
        "### `greybox fit` on the folder and on candidates of it",
        "",
        "Metrics from each result folder's metrics.csv (SAE in degC); ambient of the "
        "validation run as the model used it.",
        "",
        "| `greybox fit` | estimation SAE | validation SAE | validation SAE T1 / T2 | fit % "
        "(validation, T1 / T2) | ambient (val.) [C] | status |",
        "|---|---|---|---|---|---|---|",
        _fit_row(result, "committed", f"**folder as committed ({committed})**"),
    ]
    for name, label in FIT_ROWS.items():
        if name != committed:
            lines.append(_fit_row(result, name, label))
    lines += [
        "",
        "### Comparison with the paper (the paper's fixed 23 C ambient)",
        "",
        "AIC/BIC in this table: from the free-run simulation residuals on the **estimation "
        "run only**, pooled over the sensors (AIC = n ln(RSS/n) + 2k, BIC = n ln(RSS/n) + "
        "k ln n; a different constant from `greybox compare`'s, so compare rows within this "
        "table only; "
        + (
            "grey-box rows over both sensors, n = 1,200, as fitted; the SISO ARX row over T1, "
            "n = 600, so not comparable with them)."
            if one
            else "n = 1,200 residuals)."
        ),
        "",
        "| model | estimation SAE | validation SAE | AIC (est.) | BIC (est.) | note |",
        "|---|---|---|---|---|---|",
    ]
    for name, (e, v) in paper.items():
        lines.append(f"| paper: {name} | {e:.2f} | {v:.2f} | — | — | Park et al. 2020 |")
    for name, e, v, aic, bic, note in result["rows"]:
        lines.append(f"| ours: {name} | {e:.2f} | {v:.2f} | {_num(aic)} | {_num(bic)} | {note} |")
    shown = [("committed", f"folder default ({committed})")] + [
        (k, FIT_ROWS[k]) for k in (PER_SENSOR_23C, SHARED_23C) if k != committed
    ]
    for key, label in shown:
        p = result["greybox_fit"][key]["params"]
        conv = p["convergence"]
        lines += [
            "",
            f"`greybox fit`, {label} ({conv['loss']} loss, {p['model']['method']} solver, "
            f"simulation error, {p['n_data']} points, {conv['steps']} LM steps, "
            f"{conv['message'].split(';')[0]}; intervals: "
            f"{p['standard_errors']['headline']}):",
            "",
        ]
        lines += _param_lines(p)
        lines += ["", "Identifiability: " + "; ".join(p["identifiability"]["summary"])]
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


def _val_sae(result: dict, key: str) -> float:
    return greybox_fit_sae(result["greybox_fit"][key], "validation", result["outputs"])


def _fitted(result: dict, key: str, path: str) -> dict:
    return next(p for p in result["greybox_fit"][key]["params"]["parameters"] if p["path"] == path)


def notes(two: dict, one: dict) -> str:
    """The notes section; the numbers quoted come from this run's results."""
    arx_ls, arx_pub = _row(two, "ARX [2 2 1]"), _row(two, "ARX, paper's")
    oe1, oe2 = _row(two, "OE [2 1 1]"), _row(two, "OE [2 2 1]")
    oe2_ok = all(m.converged for m in two["miso"]["oe22"])
    paper_arx = study.PAPER["two_heaters"]["ARX (na=2, nb=2)"][1]
    ci = lambda p: f"{p['value']:.2f} s (95 % {p['ci95'][0]:.2f}–{p['ci95'][1]:.2f})"  # noqa: E731
    t1, t2 = (_fitted(two, PER_SENSOR_23C, f"tau{j}_s") for j in (1, 2))
    one_t2 = _fitted(one, PER_SENSOR_23C, "tau2_s")
    shared_val = _row(two, "grey-box, paper: shared lag")[1]
    oe2_poles = [max(max(abs(np.roots(f))) for f in m.f[0]) for m in two["miso"]["oe22"]]
    ratios = [
        p["se_hac"] / p["se_gauss_newton"]
        for r in (two, one)
        for f in r["greybox_fit"].values()
        for p in f["params"]["parameters"]
        if p["se_hac"] and p["se_gauss_newton"]
    ]
    return f"""## Notes
- Intervals: the residuals of every TCLab fit are far from white (slow drift the model does not
  carry), so the headline 95 % intervals are the HAC sandwich ones (`greybox fit`'s rule),
  {min(ratios):.1f}-{max(ratios):.1f}x the Gauss-Newton standard errors, which assume white
  residuals. The sandwich leaves out the part of the residuals that the heater inputs
  explain (a deterministic misfit, not noise: `benchmarks/whiteness.py`), so these intervals
  are narrower than the plain Newey-West ones this page showed before (3-5x the Gauss-Newton
  ones).
- Model: `models/tclab.py` (`TCLab`), a 2-node `greybox.blocks.ThermalNetwork`
  (convection + radiation to ambient, conduction + radiation between heaters, a first-order lag
  per sensor, an offset per sensor: reading = temperature + offset), the paper's fixed
  constants (Ta = 23 C, m = 4 g, cp = 500 J/(kg K), A = 10 cm^2, As = 2 cm^2, eps = 0.9).
  Heater inputs are held from each logged sample to the next (the level logged at t_k is
  applied on [t_k, t_k+1), as the TCLab scripts set it). Each run starts from its first
  readings minus the sensor offsets.
- Structure selection is `greybox compare` on each folder (its `[[candidates]]` in
  experiment.toml; the tables above are its compare.json), replacing this script's own
  selection code. The candidates were written down before their validation numbers were
  computed, but the sensor-lag and area variants were tried during development and their
  validation numbers looked at then, so no validation SAE here is a fully blind test.
  Two-heater per-sensor lags (ambient 23 C): tau1 = {ci(t1)}, tau2 = {ci(t2)}.
- The paper's own parameters (tclab_estimate.txt) simulated here give the "published
  parameters" row; its validation SAE is above the paper's 840.95, so the paper's table was not
  a plain simulation of those parameters (GEKKO's collocation and its input-timing convention,
  where the level at t_k acts on (t_k-1, t_k], are the likely reasons). Our fit of the paper's
  structure (shared lag, 23 C) lands at {shared_val:.2f} on validation, also above 840.95;
  the per-sensor lag is what brings the simulation below it.
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
  value: heater 2 never runs, so the data cannot identify it); SAE is T1 only. With the
  ambient fixed at 23 C, tau2 comes out at {ci(one_t2)}, far from the two-heater run's
  {t2["value"]:.2f} s: it absorbs misfit rather than measuring the sensor.
- The one-heater estimation run has logged timestamps 0.99–1.02 s apart: the grey-box uses
  them; the black-box models treat the samples as uniform at 1 s.
{ambient_note(two, one)}"""


def ambient_note(two: dict, one: dict) -> str:
    """The note on ambient and sensor offsets; numbers from this run's `greybox fit` rows."""
    sae = {
        k: {key: _val_sae(r, key) for key in (*FIT_ROWS, "committed")}
        for k, r in (("two", two), ("one", one))
    }
    amb = {
        k: model_ambient_C(r["greybox_fit"][FIRST_READING]) for k, r in (("two", two), ("one", one))
    }
    rest = [abs(e.y[0, 0] - e.y[0, 1]) for e in (two["est"], two["val"])]
    d2 = {
        k: _fitted(r, FIRST_READING_OFFSET, "readout.offset[1]")
        for k, r in (("two", two), ("one", one))
    }
    cands = {k: r["compare"]["by_name"] for k, r in (("two", two), ("one", one))}
    both = "per-sensor lag, ambient from first readings, both offsets"
    both_msg = {
        k: c[both]["message"].split(";")[0].removeprefix("at bound: ") for k, c in cands.items()
    }
    fo = lambda p: f"{p['value']:+.2f} K"  # noqa: E731
    return f"""- Ambient and sensor offsets. The two TMP36 sensors disagree at rest by {rest[0]:.2f} C
  (two-heater estimation run) and {rest[1]:.2f} C (its validation run). The model has an
  offset per sensor (`readout.offset[0]`, `readout.offset[1]`, reading = temperature +
  offset) and the first-reading rule (`[model] ambient = "first_reading"`) computes each
  run's initial temperatures and ambient inside the model as first reading minus offset, so a
  fitted offset moves them. Identifiability: with the ambient from the first readings only
  the difference of the offsets is determined (a common shift moves ambient, initial
  temperatures and readings together; only the radiation terms, in absolute temperature,
  see it): freeing both ends at a bound ({both_msg["two"]} on two heaters, {both_msg["one"]}
  on one heater), so that candidate fixes sensor 1's offset at 0 and fits sensor 2's
  ({fo(d2["two"])} two heaters, {fo(d2["one"])} one heater).
- Not a candidate: both offsets against the fixed 23 C ambient. Their common part is then
  the estimation room's departure from 23 C, a per-run quantity, which that structure would
  carry to every other run as a property of the sensors. It was in the candidate list when
  the rule was first run on these folders and had the lowest AIC (two heaters 74.9, one
  heater -1430.5) with implausible offsets (-2.44 / -1.36 K and +2.52 / +2.91 K) and
  validation SAE 1004.75 (two heaters) and 1984.81 (one heater, T1); it was removed for
  the structural reason above, which we state having seen those validation numbers.
- Validation SAE by ambient handling (`greybox fit`, per-sensor lag): two heaters: fixed
  23 C {sae["two"][PER_SENSOR_23C]:.2f}, first readings {sae["two"][FIRST_READING]:.2f},
  first readings + sensor 2 offset {sae["two"][FIRST_READING_OFFSET]:.2f}; one heater (T1):
  fixed 23 C {sae["one"][PER_SENSOR_23C]:.2f}, first readings {sae["one"][FIRST_READING]:.2f},
  first readings + sensor 2 offset {sae["one"][FIRST_READING_OFFSET]:.2f} (the paper:
  1991.23). The first-reading ambient of the validation runs: {amb["two"]:.2f} C (two
  heaters), {amb["one"]:.2f} C (one heater).
- The folder default follows the rule (AIC on the estimation run, `greybox compare`), not
  these validation numbers: the fixed 23 C ambient is a different room from the one these
  runs were recorded in, which the first-reading rule measures per run.
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
