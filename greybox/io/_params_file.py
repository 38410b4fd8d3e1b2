"""`params.json`: what a fit established, enough to rebuild the fitted model without the data.

Written by `greybox fit` (least squares and process noise alike), read by `greybox simulate`
and `load_params`. All values are SI, in the unit named by each entry. Non-finite numbers (a
"not identifiable" parameter's interval) are `null`.

Schema ``"schema": "greybox.params/3"`` (``greybox.params/2``, the least-squares file of the
previous version, is read as well: it is /3 without ``noise_model``):

- ``greybox_version``: the version that wrote it; ``experiment``: name, description and the
  ``[[candidates]]`` entry fitted (or null).
- ``device``: ``name`` (the spec's name), ``ref`` (the reference as written in
  experiment.toml), ``source`` ("builtin", "file", "module", "entry point"), ``location``
  (absolute path of a device file, else the module or name), ``options`` (every structural
  option, defaults filled in). ``model``: what rebuilds the fitted model: ``camera``
  (m_per_px, exposure_s), ``fixed`` ({path: SI value} from [experiment] settings), ``fitted``
  ({path: SI value} for every shared free parameter, noise parameters included), ``method``
  and ``solver`` (the adaptive solver's ``rtol``, ``atol``, ``max_steps`` the fit simulated
  with, which a simulation of the file uses too; absent in older files: the defaults).
- ``noise_model``: ``kind`` ("output error": least squares on the simulation error, with its
  ``loss``; "process noise": maximum likelihood through a Kalman filter, with ``likelihood``,
  ``filter``, ``structure`` (the checked [noise] table: process groups, disturbances,
  initial state, fixed values, priors), ``values`` ({noise path: SI value}, fixed ones
  included), ``k_step``); ``horizons``: the prediction horizons the result reports.
- ``parameters``: one entry per fitted value: name, path, unit, value, se, ci95 [lo, hi],
  verdict ("identifiable" | "weakly identified" | "prior-dominated" | "not identifiable" |
  "at bound" | "not needed"), experiment (the run that owns a per-run value, else null), prior.
- ``free``: the free-parameter specs (path, unit, bounds, per_experiment, prior, initial,
  scale) in the order of ``raw``; ``raw`` and ``covariance_raw``: the optimiser's
  transformed coordinates and their posterior covariance (shared parameters first, then one
  block per estimation run), from which `greybox._estimate.prediction` rebuilds a band;
  ``null_directions_raw``: directions of ``raw`` that nothing determined (usually none).
- ``convergence``: status, valid, converged, message, steps, multi-start costs;
  ``identifiability``: singular values, condition number, weak directions, summary lines.
- Output error only: ``sigma`` (noise scale per output [SI] and whether it was estimated),
  ``fit_percent`` (every valid frame) and ``fit_percent_robust`` (flagged outliers left
  out): ``{"horizon": "simulation", "estimation": {run: %}, "validation": {run: %}}``;
  ``runs``: frames, valid frames, outliers flagged per run.
- ``residuals`` and ``residuals_validation``: the residual test of the estimation and the
  validation runs (the one the headline's verdict uses; ``tested``: the free-run residuals,
  or with process noise the one-step innovations): verdict, Q and p per output, lags
  outside the band, per run Q and p.
- Process noise only: ``log_likelihood``, ``aic``, ``bic``, ``n_observations``; ``runs``:
  per run its role, log-likelihood, that run's own chi-square Ljung-Box of its
  standardised innovations per output (``whiteness``, `ProcessNoise.whiteness_lags` lags)
  and fit % per horizon (simulation, one-step, k-step prediction).
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np

from greybox._estimate.residuals import SHUFFLES_TEXT
from greybox._model.errors import InputError
from greybox._model.freeparams import FreeParameter
from greybox.io._noise_table import NoiseTable

SCHEMA = "greybox.params/3"
READABLE = ("greybox.params/2", SCHEMA)  # /2: a least-squares params.json of greybox < 0.x
_FREE_FIELDS = [f.name for f in dataclasses.fields(FreeParameter)]


def parameter_record(p) -> dict:
    """One fitted value (a `ParameterEstimate`) as params.json holds it, SI with its unit."""
    return {
        "name": p.name,
        "path": p.path,
        "unit": p.unit,
        "value": _num(p.value),
        "se": _num(p.se),
        "ci95": [_num(p.ci95[0]), _num(p.ci95[1])],
        "verdict": p.verdict,
        "bound": p.bound,
        "se_gauss_newton": None if p.se_gauss_newton is None else _num(p.se_gauss_newton),
        "se_hac": None if p.se_hac is None else _num(p.se_hac),
        "se_method": p.se_method,
        "experiment": p.experiment,
        "prior": None if p.prior is None else {"median": p.prior[0], "log_sd": p.prior[1]},
    }


def _num(x):
    """JSON-safe float: NaN and infinities become None."""
    x = float(x)
    return x if math.isfinite(x) else None


def _nums(a):
    return [_num(v) if np.ndim(v) == 0 else _nums(v) for v in np.asarray(a, dtype=float)]


def _fit_scores(field: str, frames: str, result, validation) -> dict:
    """One simulation fit % table of params.json: {run: %} per role for `field`."""
    val = getattr(validation, field) if validation is not None else {}
    return {
        "horizon": "simulation",
        "frames": frames,
        "estimation": {k: _num(v) for k, v in getattr(result, field).items()},
        "validation": {k: _num(v) for k, v in val.items()},
    }


def _common_document(fitset, result) -> dict:
    """What every params.json holds, whatever the noise model: the device and how to rebuild
    it, every fitted value with its uncertainty, the raw estimate and its covariance."""
    import greybox
    from greybox._estimate.fit import simulate_settings
    from greybox._estimate.verdict import fit_headline

    shared = [p for p in result.free if not p.per_experiment]
    fitted = {p.path: _num(result.estimate(p.path).value) for p in shared}
    return {
        "schema": SCHEMA,
        "greybox_version": greybox.__version__,
        "experiment": {
            "name": fitset.name,
            "description": fitset.description,
            "candidate": getattr(fitset, "candidate", None),
        },
        "device": {
            "name": fitset.spec.name,
            "ref": fitset.device.ref,
            "source": fitset.device.source,
            "location": fitset.device.location,
            "options": dict(fitset.options),
        },
        "model": {
            "camera": {
                "m_per_px": fitset.camera["m_per_px"],
                "exposure_s": fitset.camera["exposure_s"],
                "fps": fitset.camera["fps"],
            },
            "fixed": dict(fitset.fixed),
            "fitted": fitted,
            "method": result.method,
            "solver": simulate_settings(result.solver),
        },
        "parameters": [parameter_record(p) for p in result.parameters],
        # the headline verdict and every fitted value outside its physical range
        "headline": fit_headline(result, getattr(fitset, "physical_ranges", {})).as_json(),
        "free": [{k: getattr(p, k) for k in _FREE_FIELDS} for p in result.free],
        "raw": _nums(result.raw),
        "covariance_raw": _nums(result.covariance_raw),
    }


def _process_document(fitset, result, validation) -> dict:
    """params.json of a process-noise fit: the common part, the noise model (structure, every
    noise value, the likelihood and criteria) and per-run diagnostics."""
    from greybox._model.parameters import get_value
    from greybox.io._results import diagnostics_doc, horizon_labels

    outputs = [c.name for c in fitset.spec.outputs]
    noise_paths = [
        f"{f}.{nm}"
        for f in ("process", "measurement", "output_walk", "input_walk")
        for nm in getattr(result.model, f).names
    ]
    runs = {}
    for e in result.experiments:
        runs[e.name] = {"role": "estimation", "frames": e.n_frames}
    for e in getattr(validation, "experiments", ()) or ():
        runs[e.name] = {"role": "validation", "frames": e.n_frames}
    for r in (*result.runs, *(getattr(validation, "runs", ()) or ())):
        runs.setdefault(r.name, {}).update(diagnostics_doc(r, outputs))
    ident = getattr(result, "identifiability", None)
    doc = _common_document(fitset, result)
    doc["residuals"] = _residual_tests(result, outputs, innovations=True)
    doc["residuals_validation"] = _residual_tests(validation, outputs, innovations=True)
    doc["model"]["fitted"] = {
        p.path: _num(p.value) for p in result.parameters if p.experiment is None
    }
    doc["noise_model"] = {
        "kind": "process noise",
        "likelihood": result.likelihood,
        "filter": result.filter_name,
        "ekf_substeps": int(result.model.ekf_substeps) if result.model.use_ekf else None,
        "structure": fitset.noise.to_json(),
        "values": {p: _num(get_value(result.model, p)) for p in noise_paths},
        "horizons": list(horizon_labels(result).values()),
        "k_step": int(result.k_step),
    }
    doc.update(
        {
            "log_likelihood": _num(result.log_likelihood),
            "aic": _num(result.aic),
            "bic": _num(result.bic),
            "n_observations": int(result.n_observations),
            "runs": runs,
            "convergence": {
                "status": result.status,
                "valid": bool(result.valid),
                "converged": bool(result.converged),
                "message": result.message,
                "steps": int(result.n_steps),
                "multistart": [
                    {"cost": _num(c), "converged": bool(ok)}
                    for c, ok in getattr(result, "multistart_costs", ())
                ],
            },
            "identifiability": None
            if ident is None
            else {
                "singular_values": _nums(ident.singular_values),
                "condition_number": _num(ident.condition_number),
                "weak_directions": [
                    {"combination": w.combination, "sd_raw": _num(w.sd_raw), "text": w.describe()}
                    for w in ident.weak_directions
                ],
                "summary": ident.summary(),
            },
        }
    )
    return doc


def _residual_tests(res, outputs, innovations: bool = False) -> dict | None:
    """The residual test of a fit or a validation (`res.residuals`, None where it has none):
    on the simulation residuals or, with process noise (`innovations`), on the one-step
    innovations."""
    a = getattr(res, "residuals", None)
    if a is None:
        return None
    return {
        "tested": "innovations (measured - one-step prediction)"
        if innovations
        else "residuals (measured - free-run simulation)",
        "verdict": a.verdict,
        "white": bool(a.all_white),
        "test": "Ljung-Box over lags 1..test_lag_frames, pooled over runs; p-value from "
        f"{SHUFFLES_TEXT}, the chi-square with test_lag_frames dof beyond their "
        "resolution; whiteness rejected at p < 0.01 / n_outputs",
        "test_lag_frames": a.test_lag,
        "max_lag_frames": a.max_lag,
        "frame_interval_s": _num(a.frame_interval_s),
        "outputs": [
            {
                "name": outputs[j] if j < len(outputs) else f"output {j + 1}",
                "q": _num(a.q[j]),
                "dof": a.dof,
                "p_value": _num(a.p_value[j]),
                "white": bool(a.white[j]),
                "lags_outside_band": list(a.lags_outside[j]),
            }
            for j in range(len(a.q))
        ],
        "runs": {r.name: {"q": _nums(r.q), "p_value": _nums(r.p_value)} for r in a.runs},
        "cross_correlation": a.cross_lines(),
        "notes": list(a.notes),
    }


def params_document(fitset, result, validation=None) -> dict:
    """The `params.json` content (a plain dict) for a fit of `fitset` (an `ExperimentSet`),
    least squares or process noise (`result.noise`)."""
    if getattr(getattr(result, "noise", None), "name", "") == "process noise":
        return _process_document(fitset, result, validation)
    runs = {}
    for e in result.experiments:
        runs[e.name] = {
            "role": "estimation",
            "frames": e.n_frames,
            "valid_frames": int(e.mask.all(axis=1).sum()),
            "outliers_flagged": int(result.n_outliers[e.name]),
        }
    if validation is not None:
        for e in validation.experiments:
            runs[e.name] = {
                "role": "validation",
                "frames": e.n_frames,
                "valid_frames": int(e.mask.all(axis=1).sum()),
                "outliers_flagged": int(validation.n_outliers[e.name]),
            }
    ident = result.identifiability
    outputs = [c.name for c in fitset.spec.outputs]

    def per_output(field: str, frames: str) -> dict:
        """{run: [figure per output channel]} per role (simulation fit % or noise ceiling)."""
        val = getattr(validation, field) if validation is not None else {}
        return {
            "horizon": "simulation",
            "frames": frames,
            "outputs": outputs,
            "estimation": {k: _nums(v) for k, v in getattr(result, field).items()},
            "validation": {k: _nums(v) for k, v in val.items()},
        }

    def gof(res) -> dict | None:
        g = getattr(res, "goodness_of_fit", None) if res is not None else None
        if g is None:
            return None
        return {
            "chi2": _num(g.chi2),
            "dof": int(g.dof),
            "p_value": _num(g.p_value),
            "ratio": _nums(g.ratio),
            "robust_ratio": _nums(g.robust_ratio),
        }

    return {
        **_common_document(fitset, result),
        "noise_model": {
            "kind": "output error",
            "loss": result.loss,
            "horizons": ["simulation"],
        },
        "raw_labels": list(ident.raw_labels),
        "covariance_gauss_newton_raw": _nums(result.covariance_gauss_newton_raw),
        "covariance_hac_raw": _nums(result.covariance_hac_raw),
        "standard_errors": {
            "headline": result.se_method,
            "why": "residuals not white" if result.se_method == "hac" else "residuals white",
            "hac": "Newey-West sandwich after an FIR model-error model on the inputs (Ljung and "
            "Guo 1997) and VAR(1) prewhitening (Andrews and Monahan 1992); Bartlett kernel, "
            "Andrews (1991) AR(1) plug-in bandwidth; n/(n-k) factor",
            "hac_bandwidth_frames": int(result.hac_bandwidth),
        },
        "null_directions_raw": _nums(
            np.reshape(
                getattr(ident, "null_directions", np.zeros((0, result.raw.size))),
                (-1, result.raw.size),
            )
        ),
        "sigma": {
            "value": _nums(result.sigma),
            "unit": [c.si_unit for c in fitset.spec.outputs],
            "estimated": result.sigma_source == "estimated",
            "source": result.sigma_source,
            "how": {
                "estimated": "robust (MAD) scale of the residuals",
                "declared": "declared by the user; not re-estimated",
                "per-frame": "RMS of the known per-frame noise (Experiment.sigma)",
            }[result.sigma_source],
            "goodness_of_fit": gof(result),
            "goodness_of_fit_validation": gof(validation),
        },
        "fit_percent": per_output("fit_percent", "all valid frames"),
        "fit_percent_robust": per_output(
            "fit_percent_robust", "valid frames not flagged as outliers"
        ),
        "noise_ceiling": per_output("noise_ceiling", "all valid frames"),
        "residuals": _residual_tests(result, outputs),
        "residuals_validation": _residual_tests(validation, outputs),
        "runs": runs,
        "n_data": int(result.n_data),
        "convergence": {
            "status": result.status,
            "valid": bool(result.valid),
            "converged": bool(result.converged),
            "message": result.message,
            "steps": int(result.n_steps),
            "cost": _num(result.cost),
            "loss": result.loss,
            "multistart": [
                {"cost": _num(c), "converged": bool(ok)} for c, ok in result.multistart_costs
            ],
            "best_start": int(result.best_start),
            "starts_at_best": int(result.n_starts_at_best),
        },
        "identifiability": {
            "singular_values": _nums(ident.singular_values),
            "condition_number": _num(ident.condition_number),
            "weak_directions": [
                {"combination": w.combination, "sd_raw": _num(w.sd_raw), "text": w.describe()}
                for w in ident.weak_directions
            ],
            "summary": ident.summary(),
        },
    }


def write_params(path, document: dict) -> None:
    """Write `document` as strict JSON (no NaN) to `path`."""
    Path(path).write_text(json.dumps(document, indent=2, allow_nan=False) + "\n")


@dataclasses.dataclass(frozen=True)
class FittedModel:
    """A fitted model rebuilt from `params.json`.

    - `model`: the device model with the fitted shared values, the fixed settings and the
      camera; per-run nuisance values (camera offset, drift) stay at the device default (0).
    - `free`: the free-parameter specs; `raw`, `covariance_raw`, `null_directions`: as
      fitted (all parameters; see `greybox._estimate.prediction.prediction_band`).
    - `sigma`: noise scale per output [SI]; `method`: simulation path used by the fit;
      `solver`: the fit's adaptive-solver settings (`solver_rtol`, ...; empty: defaults).
    """

    device: object  # greybox._registry.ResolvedDevice
    options: dict
    model: object
    free: tuple
    raw: np.ndarray
    covariance_raw: np.ndarray
    null_directions: np.ndarray
    sigma: np.ndarray
    method: str
    document: dict
    noise: object = None  # the `NoiseTable` of a process-noise fit (`model` is stochastic)
    solver: dict = dataclasses.field(default_factory=dict)

    @property
    def noise_model(self) -> str:
        """"output error" (least squares) or "process noise" (a stochastic model)."""
        return "output error" if self.noise is None else "process noise"

    @property
    def spec(self):
        return self.device.spec

    @property
    def posterior(self):
        """The fit's `greybox.Posterior`, rebuilt from the file."""
        from greybox._estimate.posterior import Posterior

        return Posterior(
            self.model,
            self.free,
            self.raw,
            self.covariance_raw,
            self.null_directions,
            self.sigma,
            self.method,
            solver=dict(self.solver),
        )

    @property
    def device_name(self) -> str:
        return self.device.spec.name


_MAX_PARAMS_BYTES = 64 * 2**20


def _finite_vector(values, field: str, file: str) -> np.ndarray:
    try:
        out = np.asarray(values, dtype=float)
    except (TypeError, ValueError, OverflowError):
        raise InputError("must be a list of numbers", file=file, field=field) from None
    if out.ndim != 1 or not np.all(np.isfinite(out)):
        raise InputError(
            "must be a flat list of finite numbers (regenerate it with `greybox fit`)",
            file=file,
            field=field,
        )
    return out


def _check_covariance(cov: np.ndarray, file: str) -> None:
    """covariance_raw must be finite, symmetric and positive semi-definite."""
    if cov.size == 0:
        return
    if not np.all(np.isfinite(cov)):
        i, j = np.argwhere(~np.isfinite(cov))[0]
        raise InputError(
            f"entry [{i}][{j}] is not a finite number; a band cannot be computed from it "
            "(regenerate the file with `greybox fit`)",
            file=file,
            field="covariance_raw",
        )
    scale = max(float(np.max(np.abs(cov))), 1e-300)
    if np.max(np.abs(cov - cov.T)) > 1e-8 * scale:
        raise InputError("is not symmetric", file=file, field="covariance_raw")
    d = np.diag(cov)
    if np.any(d < 0):
        i = int(np.flatnonzero(d < 0)[0])
        raise InputError(
            f"variance [{i}][{i}] = {d[i]:g} is negative; a covariance is positive "
            "semi-definite (regenerate the file with `greybox fit`)",
            file=file,
            field="covariance_raw",
        )
    eig = np.linalg.eigvalsh(0.5 * (cov + cov.T))
    if eig[0] < -1e-8 * max(eig[-1], 1e-300):
        raise InputError(
            f"is not positive semi-definite (smallest eigenvalue {eig[0]:g}); regenerate "
            "the file with `greybox fit`",
            file=file,
            field="covariance_raw",
        )


def load_params(path, trust_device=()) -> FittedModel:
    """Read `params.json` and rebuild the fitted model. Raises `InputError` naming the field.
    A device file it names is imported only from its own folder or from `trust_device`
    paths (files or folders; README, "A params.json is data")."""
    from greybox._model.parameters import set_values
    from greybox._model.spec import DeviceSpecError
    from greybox._registry import DeviceNotFound, resolve
    from greybox._usercode import params_trust
    from greybox.io._experiment_set import configure_model
    from greybox.io._params_checks import check_params_plausible

    path = Path(path)
    file = str(path)
    if not path.is_file():
        raise InputError(
            "does not exist; give the params.json written by `greybox fit`",
            file=file,
            field="--params",
        )
    try:
        if path.stat().st_size > _MAX_PARAMS_BYTES:
            raise InputError(
                f"{path.stat().st_size / 2**20:.0f} MB; a params.json is a few kB to MB",
                file=file,
                field="--params",
            )
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError, ValueError, OSError) as err:
        if isinstance(err, InputError):
            raise
        line = getattr(err, "lineno", None)
        what = str(err) if isinstance(err, json.JSONDecodeError) else type(err).__name__
        raise InputError(
            f"not valid JSON ({what[:100]}); use the file `greybox fit` wrote",
            file=file,
            line=line,
            field="--params",
        ) from None

    if not isinstance(doc, dict):
        raise InputError(
            f"holds a JSON {type(doc).__name__}, not the object `greybox fit` writes",
            file=file,
            field="--params",
        )

    def need(obj, key, kind, where):
        if not isinstance(obj, dict) or key not in obj or not isinstance(obj[key], kind):
            raise InputError(
                f"missing or malformed; this is not a {SCHEMA} file written by `greybox fit`",
                file=file,
                field=f"{where}{key}",
            )
        return obj[key]

    schema = need(doc, "schema", str, "")
    if schema not in READABLE:
        raise InputError(
            f"{schema[:40]!r}: this greybox reads {' and '.join(READABLE)}",
            file=file,
            field="schema",
        )
    kind = "output error"
    if schema == SCHEMA:
        kind = need(need(doc, "noise_model", dict, ""), "kind", str, "noise_model.")
        if kind not in ("output error", "process noise"):
            raise InputError(
                f"{kind[:40]!r}: use 'output error' or 'process noise'",
                file=file,
                field="noise_model.kind",
            )
    dev = need(doc, "device", dict, "")
    ref = need(dev, "ref", str, "device.")
    location = need(dev, "location", str, "device.")
    source = need(dev, "source", str, "device.")
    given_options = need(dev, "options", dict, "device.")
    # a device file beside params.json (copied with the result) first, else where it was
    # fitted; greybox._usercode.trusted_devices decides which folders may supply code
    candidates = [str(path.parent / Path(location).name), location] if source == "file" else [ref]
    device, last_err = None, None
    for candidate in candidates:
        try:
            with params_trust(path, trust_device):
                device = resolve(
                    candidate
                    if source != "file"
                    else f"{candidate}:{ref.partition(':')[2] or 'SPEC'}"
                )
            break
        except (DeviceNotFound, DeviceSpecError) as err:
            last_err = err
    if device is None:
        raise InputError(
            f"the device that was fitted cannot be loaded ({last_err}); params.json needs the "
            f"same device ({ref!r}): restore the file or install the package",
            file=file,
            field="device",
        )
    if device.spec.name != dev.get("name"):
        raise InputError(
            f"{ref!r} now defines device {device.spec.name!r}, but this file was fitted with "
            f"{dev.get('name')!r}; use the device file it was fitted with",
            file=file,
            field="device.name",
        )
    try:
        options = device.spec.resolve_options(given_options)
    except ValueError as err:
        raise InputError(
            f"{err}; the device's options changed since the fit", file=file, field="device.options"
        ) from None
    spec = need(doc, "model", dict, "")
    camera = need(spec, "camera", dict, "model.")
    fixed = need(spec, "fixed", dict, "model.")
    fitted = need(spec, "fitted", dict, "model.")
    method = need(spec, "method", str, "model.")
    solver = _solver_settings(spec.get("solver", {}), file)
    free_docs = need(doc, "free", list, "")
    try:
        raw = _finite_vector(need(doc, "raw", list, ""), "raw", file)
        cov_list = need(doc, "covariance_raw", list, "")
        noise = None
        if kind == "process noise":
            nm = doc["noise_model"]
            values = need(nm, "values", dict, "noise_model.")
            noise = NoiseTable.from_json(need(nm, "structure", dict, "noise_model."))
            sigma = _finite_vector(
                [values.get(f"measurement.{c.name}") for c in device.spec.outputs],
                "noise_model.values",
                file,
            )
        else:
            sigma = _finite_vector(
                need(need(doc, "sigma", dict, ""), "value", list, "sigma."), "sigma.value", file
            )
        if np.any(sigma < 0):
            raise InputError("noise sigma cannot be negative", file=file, field="sigma.value")
        for k, v in list(fitted.items()) + list(fixed.items()):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise InputError(
                    f"{str(v)[:40]} is not a finite number", file=file, field=f"model.{k[:60]}"
                )
        for k in ("m_per_px", "exposure_s"):
            v = camera.get(k)
            if v is not None and (
                isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v)
            ):
                raise InputError(
                    f"{str(v)[:40]} is not a finite number", file=file, field=f"model.camera.{k}"
                )
        if not all(isinstance(f, dict) for f in free_docs):
            raise InputError("each entry must be an object", file=file, field="free")
        free = tuple(FreeParameter(**{k: f[k] for k in _FREE_FIELDS if k in f}) for f in free_docs)
        cov = np.array([[np.nan if v is None else v for v in row] for row in cov_list], dtype=float)
        nulls = np.array(doc.get("null_directions_raw") or [], dtype=float).reshape(-1, raw.size)
        model = configure_model(device.spec, options, camera, fixed)
        if noise is not None:  # the stochastic model: device, noise structure and values
            from greybox.io._noise_table import structure
            from greybox.stochastic._sde_device import stochastic_device

            model = stochastic_device(
                model, structure(noise), outputs=device.spec.outputs, inputs=device.spec.inputs
            )
            for k, v in values.items():
                if v is None or isinstance(v, bool) or not isinstance(v, (int, float)):
                    raise InputError(
                        f"{str(v)[:40]} is not a finite number",
                        file=file,
                        field=f"noise_model.values.{k[:60]}",
                    )
            model = set_values(model, list(values), [float(v) for v in values.values()])
        model = set_values(model, list(fitted), [float(v) for v in fitted.values()])
        from greybox._model.parameters import check_scalar_path

        for fp in free:  # every free path must name a value of this device
            check_scalar_path(model, fp.path)
        check_params_plausible(free, raw, fitted, camera, file)
    except InputError:
        raise
    except (TypeError, ValueError, KeyError, AttributeError, IndexError, OverflowError) as err:
        if isinstance(err, InputError):
            raise
        raise InputError(
            f"cannot rebuild the fitted model ({str(err)[:120]}); is it a params.json of "
            f"device {device.spec.name!r}? Regenerate it with `greybox fit`",
            file=file,
            field="model",
        ) from None
    if cov.shape != (raw.size, raw.size):
        raise InputError(
            f"covariance_raw is {cov.shape}, raw has {raw.size} entries",
            file=file,
            field="covariance_raw",
        )
    n_shared = sum(not f.per_experiment for f in free)
    n_per = len(free) - n_shared
    extra = raw.size - n_shared
    if extra < 0 or (extra % n_per if n_per else extra) != 0:
        raise InputError(
            f"{len(free)} free parameters ({n_per} per run) do not match the {raw.size} "
            "entries of raw",
            file=file,
            field="free",
        )
    _check_covariance(cov, file)
    return FittedModel(
        device, options, model, free, raw, cov, nulls, sigma, method, doc, noise, solver
    )


def _solver_settings(doc, file) -> dict:
    """`model.solver` ({rtol, atol, max_steps}, each optional) as a fit's `solver` dict."""
    from greybox.io._experiment_set import MAX_SOLVER_STEPS

    kinds = {"rtol": float, "atol": float, "max_steps": int}
    unknown = sorted(map(str, set(doc) - set(kinds)))[:3] if isinstance(doc, dict) else []
    if not isinstance(doc, dict) or unknown:
        what = f"unknown keys {unknown}" if unknown else f"a {type(doc).__name__}"
        raise InputError(
            f"{what}: the adaptive solver's settings are a table of {', '.join(kinds)} "
            "(or leave it out for the defaults)",
            file=file,
            field="model.solver",
        )
    out = {}
    for key, kind in kinds.items():
        if key not in doc:
            continue
        value = doc[key]
        most = MAX_SOLVER_STEPS if key == "max_steps" else 1.0
        number = isinstance(value, (int, float)) and not isinstance(value, bool)
        if not (number and math.isfinite(value) and 0 < value <= most):
            raise InputError(
                f"{value!r} must be a number in (0, {most:g}]",
                file=file,
                field=f"model.solver.{key}",
            )
        out[f"solver_{key}"] = kind(value)
    return out
