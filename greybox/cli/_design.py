"""`greybox design`: propose the next experiment (runs and waveforms) for a device or a fit."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from greybox.cli._trust import add_trust_device_option

HELP = """\
Design the next experiment: choose laser waveforms (one per run) that maximise the Fisher
information of the parameters of interest (D-optimal by default), under the lab's
constraints, for a device at its nominal values (--device) or at a fitted posterior
(--params params.json from `greybox fit`; --bayesian-draws N averages the criterion over N
draws from the fit's covariance).

Per-run camera offsets are marginalised; shared parameters that are not of interest are
nuisance parameters. Pulse trains are searched on a grid (period in whole ms, duty in 5 %
steps, power at the largest value the power range and average cap allow) and a union of
--runs runs is chosen greedily with exchange passes; --family multilevel refines free
levels on a --min-pulse-ms grid by projected gradient ascent through the simulator.

Output (in --out, written atomically):
  experiment.toml   ready to record into: [camera], [fit] and one [[runs]] table per run
                    with its waveform (record <run name>.csv with t_s and y_px)
  design.txt        predicted standard errors per parameter of interest, design vs the
                    baseline (--baseline EXPERIMENT_TOML's estimation runs, else 50 % duty
                    pulse trains at the same average power), and the verdict
  design.json       the same numbers, machine-readable
A request no waveform can satisfy (infeasible constraints, a parameter of interest the
camera data cannot identify) is an error naming the option, never a poor design.
"""

OPTION_OF = {
    "power_max_W": "--power-max-mW",
    "power_min_W": "--power-min-mW",
    "average_power_max_W": "--average-power-max-mW",
    "min_pulse_s": "--min-pulse-ms",
    "run_duration_s": "--run-duration-s",
    "n_runs": "--runs",
    "fps": "--fps",
    "exposure_s": "--exposure-ms",
    "lead_s": "--lead-ms",
    "interest": "--interest",
    "sigma": "--noise-um",
    "n_draws": "--bayesian-draws",
}


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "design",
        help="design the next experiment (optimal laser waveforms) for a device or a fit",
        description=HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--params", metavar="PARAMS_JSON", help="params.json from `greybox fit`")
    src.add_argument(
        "--device", metavar="NAME", help="device at nominal values (e.g. chevron_laser)"
    )
    p.add_argument(
        "--interest",
        nargs="+",
        metavar="PATH",
        help="parameters to measure (default: every shared free parameter)",
    )
    p.add_argument("--power-max-mW", type=float, required=True, help="highest laser power [mW]")
    p.add_argument("--power-min-mW", type=float, default=0.0, help="lowest non-zero power [mW]")
    p.add_argument(
        "--average-power-max-mW", type=float, default=None, help="cap on each run's mean power [mW]"
    )
    p.add_argument(
        "--min-pulse-ms", type=float, default=20.0, help="shortest pulse / edge spacing [ms]"
    )
    p.add_argument("--run-duration-s", type=float, required=True, help="length of one run [s]")
    p.add_argument("--runs", type=int, default=1, help="number of runs (default 1)")
    p.add_argument("--fps", type=float, default=30.0, help="camera frame rate [1/s] (default 30)")
    p.add_argument(
        "--exposure-ms", type=float, default=10.0, help="camera exposure [ms] (default 10)"
    )
    p.add_argument("--lead-ms", type=float, default=300.0, help="laser-off start of each run [ms]")
    p.add_argument(
        "--noise-um",
        type=float,
        default=None,
        help="tracking noise sd [um] (default: the fit's sigma, or 0.05 for --device)",
    )
    p.add_argument("--criterion", choices=("D", "A", "E"), default="D")
    p.add_argument("--family", choices=("pulse_train", "multilevel"), default="pulse_train")
    p.add_argument("--bayesian-draws", type=int, default=0, help="posterior draws (with --params)")
    p.add_argument(
        "--baseline", metavar="EXPERIMENT_TOML", help="compare with these estimation runs"
    )
    p.add_argument("--out", metavar="DIR", default="results/design", help="output folder")
    add_trust_device_option(p)
    p.set_defaults(func=run)
    return p


def _input_error(err: ValueError):
    from greybox._model.errors import InputError

    text = str(err)
    field, _, rest = text.partition(": ")
    if field in OPTION_OF:
        return InputError(rest, field=OPTION_OF[field])
    return InputError(text)


def run(args) -> int:
    from greybox.cli._ticker import Ticker, to_stderr

    with Ticker(to_stderr) as tick:  # a line after every 5 s of silence (the optimisation)
        tick.phase_is("designing (compiling the information matrix, then optimising)")
        return _run(args)


def _run(args) -> int:
    from greybox.io._jax_setup import configure

    configure()  # float64, compiled programs kept on disk
    import numpy as np

    from greybox._model.errors import InputError
    from greybox._model.freeparams import FreeParameter
    from greybox._registry import get_device
    from greybox.design import _design as D
    from greybox.io._atomic import atomic_output_dir, check_output_dir
    from greybox.io._design_file import experiment_toml
    from greybox.io._toml import non_finite

    for name, v in vars(args).items():  # every numeric option: NaN and infinities by name
        if isinstance(v, float) and non_finite(v):
            raise InputError(non_finite(v), field="--" + name.replace("_", "-"))
    if args.runs < 1 or args.runs > D.MAX_DESIGN_RUNS:
        raise InputError(
            f"{args.runs} runs; give 1 to {D.MAX_DESIGN_RUNS} (design larger campaigns in parts)",
            field="--runs",
        )
    if args.bayesian_draws < 0 or args.bayesian_draws > D.MAX_DRAWS:
        raise InputError(f"give 0 to {D.MAX_DRAWS} draws", field="--bayesian-draws")
    inputs = [args.params] if args.params else []
    check_output_dir(args.out, inputs=inputs)  # before the work, like every command
    if args.params:
        from greybox._usercode import trusted_devices
        from greybox.io._params_file import load_params

        with trusted_devices(args.params, args.trust_device):
            fitted = load_params(args.params)
        spec, model, free = fitted.spec, fitted.model, tuple(fitted.free)
        raw, cov, method = fitted.raw, fitted.covariance_raw, fitted.method
        sigma = fitted.sigma if args.noise_um is None else args.noise_um * 1e-6
        source = f"fit {args.params}"
    else:
        try:
            spec = get_device(args.device)
        except ValueError as err:
            raise InputError(str(err), field="--device") from None
        model, free = spec.model(), tuple(spec.free_parameters())
        raw = cov = method = None
        sigma = 0.05e-6 if args.noise_um is None else args.noise_um * 1e-6
        source = f"device {spec.name} at nominal values"
        if args.bayesian_draws:
            raise InputError(
                "a Bayesian design needs a fitted posterior; give --params",
                field="--bayesian-draws",
            )
    from greybox.blocks._camera import Camera

    if not isinstance(getattr(model, "readout", None), Camera):  # e.g. a thermocouple
        raise InputError(
            f"{spec.name} is read out by a sensor, not a camera: greybox design chooses laser "
            "pulse trains for a filmed device (camera frames, exposure, image noise); it has "
            "no design for a sensor-read device",
            field="--params" if args.params else "--device",
        )
    default_paths = [p.path for p in spec.free_parameters()]
    interest = args.interest or [p.path for p in free if not p.per_experiment]
    # a parameter of interest that is not free is freed with the device's range
    extra = []
    for path in interest:
        if path in [p.path for p in free]:
            continue
        info = spec.parameter_info(path)
        if info is None:
            raise InputError(
                f"{path!r} is not a parameter of {spec.name}; see its parameter table",
                field="--interest",
            )
        extra.append(FreeParameter(path, unit=info.unit, lower=info.lower, upper=info.upper))
    free = tuple(free) + tuple(extra)
    if raw is not None and extra:
        shared_n = sum(not p.per_experiment for p in fitted.free)
        raw = np.concatenate(
            [raw[:shared_n], [float(p.to_raw(info_value(model, p.path))) for p in extra]]
        )
        big = np.zeros((raw.size, raw.size))
        big[:shared_n, :shared_n] = np.asarray(cov)[:shared_n, :shared_n]
        big[shared_n:, shared_n:] = np.eye(len(extra)) * 1e6  # nothing known about them
        cov = big
        free = (
            tuple(p for p in fitted.free if not p.per_experiment)
            + tuple(extra)
            + tuple(p for p in fitted.free if p.per_experiment)
        )
    try:
        constraints = D.LabConstraints(
            power_max_W=args.power_max_mW * 1e-3,
            power_min_W=args.power_min_mW * 1e-3,
            average_power_max_W=(
                None if args.average_power_max_mW is None else args.average_power_max_mW * 1e-3
            ),
            min_pulse_s=args.min_pulse_ms * 1e-3,
            run_duration_s=args.run_duration_s,
            n_runs=args.runs,
            fps=args.fps,
            exposure_s=args.exposure_ms * 1e-3,
            lead_s=args.lead_ms * 1e-3,
        )
        problem = D.design_problem(
            model,
            free,
            interest,
            sigma,
            raw=raw,
            covariance_raw=cov,
            n_draws=args.bayesian_draws,
            exposure_s=constraints.exposure_s,
            method=method,
        )
        _check_design_memory(args, spec, model, free, constraints)
        print(f"designing {args.runs} run(s) of {args.run_duration_s:g} s for {source} ...")
        design = D.design_experiment(
            problem, constraints, family=args.family, criterion=args.criterion
        )
        baseline, base_label = _baseline(args, D, spec, constraints, problem)
    except InputError:
        raise
    except ValueError as err:
        raise _input_error(err) from None
    rows = D.comparison_table(problem, design, baseline)
    gain = D.det_gain(problem, design, baseline)
    table = D.format_design_table(rows, baseline_label="baseline")
    m_per_px = float(model.camera.m_per_px)
    toml = experiment_toml(
        design,
        device=spec.name,
        free=free,
        m_per_px=m_per_px,
        description=f"{args.criterion}-optimal design for {', '.join(interest)} ({source})",
        default_free=default_paths,
    )
    bayes = f" (Bayesian, {args.bayesian_draws} posterior draws)" if args.bayesian_draws else ""
    report = "\n".join(
        [
            f"greybox design: {args.criterion}-optimal{bayes} {args.family} design for "
            f"{', '.join(interest)} ({source})",
            f"baseline: {base_label}",
            f"runs: {len(design.runs)} x {args.run_duration_s:g} s; laser energy "
            f"{design.energy_J * 1e3:.4g} mJ (baseline {baseline.energy_J * 1e3:.4g} mJ)",
            "",
            "predicted standard errors (SI; delta method at the "
            + ("posterior mean" if args.params else "nominal values")
            + "; per-run camera offsets marginalised):",
            table,
            f"det(information)^(1/p): {gain:.3g} x the baseline's",
            f"verdict: {design.verdict}",
            "",
            "runs:",
            *[f"  {r.name}: {r.description}" for r in design.runs],
        ]
    )
    doc = {
        "criterion": args.criterion,
        "family": args.family,
        "bayesian_draws": args.bayesian_draws,
        "source": source,
        "interest": list(interest),
        "det_gain": gain,
        "table": rows,
        "verdict": design.verdict,
        "runs": [{"name": r.name, "waveform": r.description} for r in design.runs],
        "energy_J": {"design": design.energy_J, "baseline": baseline.energy_J},
    }
    with atomic_output_dir(args.out) as tmp:
        from greybox.io._results import usual_permissions

        usual_permissions(tmp)
        (tmp / "experiment.toml").write_text(toml)
        (tmp / "design.txt").write_text(report + "\n")
        (tmp / "design.json").write_text(json.dumps(doc, indent=2, default=float) + "\n")
    print(report)
    print(f"wrote {Path(args.out)}/ (experiment.toml, design.txt, design.json)")
    return 0


def _check_design_memory(args, spec, model, free, constraints) -> None:
    """The memory model of every fitting command (`greybox._estimate.memory`): the sensitivities of
    all runs at once, once per posterior draw, against the same limit as `greybox fit`."""
    from greybox._estimate import memory as _memory
    from greybox._model.errors import InputError
    from greybox.io._experiment_set import max_problem_bytes

    constraints.check()
    working = _memory.solve_bytes(
        runs=args.runs,
        frames=int(constraints.run_duration_s * constraints.fps) + 1,
        states=int(model.n_states),
        outputs=len(spec.outputs),
        inputs=len(spec.inputs),
        raw=len(free),
    )
    need = _memory.peak_bytes(working, items=max(1, args.bayesian_draws))
    if need > max_problem_bytes():
        raise InputError(
            f"the design would need about {_memory.format_gb(need)} (limit "
            f"{_memory.format_gb(max_problem_bytes())}); fewer or shorter runs, or fewer draws",
            field="--runs",
        )


def info_value(model, path):
    from greybox._model.parameters import get_value

    return get_value(model, path)


def _baseline(args, D, spec, constraints, problem):
    """(Design, label): the --baseline file's estimation runs, or 50 % duty pulse trains."""
    import tomllib

    from greybox._model.errors import InputError
    from greybox.io import waveform_from_description

    if args.baseline:
        path = Path(args.baseline)
        if not path.is_file():
            raise InputError("no such file; give an experiment.toml", field="--baseline")
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
        runs = []
        for r in doc.get("runs", []):
            if r.get("role") != "estimation" or not isinstance(r.get("waveform"), dict):
                continue
            wave, _ = waveform_from_description(
                r["waveform"], spec.inputs[0], lambda msg, *k: InputError(msg, field="--baseline")
            )
            runs.append(D.DesignedRun(r["name"], wave, r["waveform"], "pulse_train"))
        if not runs:
            raise InputError("no estimation runs with a described waveform", field="--baseline")
        return D.evaluate_design(
            problem, runs, constraints
        ), f"{len(runs)} estimation runs of {path}"
    runs = D.habitual_baseline(constraints)
    return (
        D.evaluate_design(problem, runs, constraints),
        f"{len(runs)} x {runs[0].description['power_mW']:g} mW, "
        f"{runs[0].description['period_ms']:g} ms, 50 % duty pulse trains (same runs and cap)",
    )
