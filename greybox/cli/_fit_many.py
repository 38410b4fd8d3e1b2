"""`greybox fit-many`: many experiment folders (one per device) -> one result folder per device
plus a batch table and figures across devices, fitted with one compiled solver (issue 19)."""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import sys
from pathlib import Path

HELP = """\
Fit every device (one experiment folder each, the format of `greybox fit`) with one
compiled, vmapped solver (`greybox._estimate.batch.fit_batch`): each device is fitted exactly as
`greybox fit` would fit it (same loss, noise estimate, starts and verdicts), but the
solver is compiled once for all devices of the same structure instead of once per device.

Written under --out (atomically, as a whole):
  devices/<FOLDER NAME>/   params.json and report.md of that device (what `greybox fit`
                           writes; figures/ too unless --no-device-figures)
  batch.csv, batch.md      one row per device: status, the headline verdict of its
                           report.md (structure rejected, ...), what was minimised, noise,
                           every fitted value with its standard error and verdict,
                           simulation fit % per output
  figures/                 histograms of each shared parameter across devices and their
                           pairwise scatter
  population.md/.json      with --random/--shared: the population model (median, spread,
                           devices that do not belong, prediction for a new device)

--scheduler local starts a Dask LocalCluster of --workers processes; --scheduler ADDRESS
uses a running Dask cluster (needs: pip install "dask[distributed]"). Without --scheduler
everything runs in this process. Exit status: 0 every device valid; 1 written but some
device's fit is not valid (see batch.md); 2 bad input; 3 a bug in greybox.
"""


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "fit-many",
        help="fit many devices (one experiment folder each) with one compiled solver",
        description=HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "folders", metavar="FOLDER", nargs="+", help="experiment folders, one per device"
    )
    p.add_argument("--out", metavar="DIR", required=True, help="result folder (replaced whole)")
    p.add_argument("--force", action="store_true", help="replace --out even if not a result")
    p.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        default=None,
        help='"local" (a Dask LocalCluster) or a Dask scheduler address; default: this process',
    )
    p.add_argument("--workers", type=int, default=2, help="workers of a local cluster (2)")
    p.add_argument(
        "--memory-budget-mb",
        type=float,
        default=None,
        help="memory one compiled call may use (chooses the chunk size; default 2048 in "
        "process, 1024 per Dask worker)",
    )
    p.add_argument(
        "--random",
        action="append",
        default=[],
        metavar="PATH",
        help="population model: PATH varies across devices (log-normal)",
    )
    p.add_argument(
        "--shared",
        action="append",
        default=[],
        metavar="PATH",
        help="population model: PATH is the same for every device (tested)",
    )
    p.add_argument(
        "--no-device-figures",
        action="store_true",
        help="skip the per-device figures (faster for hundreds of devices)",
    )
    p.add_argument(
        "--no-validate",
        action="store_true",
        help="skip the validation runs (each re-fits per-run offsets per device)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    from greybox.cli._figures import add_figure_format

    add_figure_format(p)
    p.set_defaults(func=run)
    return p


def _device_name(folder, seen) -> str:
    name = Path(folder).resolve().name
    base, k = name, 2
    while name in seen:
        name, k = f"{base}_{k}", k + 1
    seen.add(name)
    return name


def load_devices(folders, say):
    """([(name, ExperimentSet)] of the folders that load, {name: why} of those that do not).
    One bad folder does not lose the batch: it gets a failure line."""
    from greybox._model.errors import InputError
    from greybox.io._experiment_set import check_problem_size, load_experiment_set

    out, failed, seen = [], {}, set()
    for folder in folders:
        name = _device_name(folder, seen)
        try:
            fs = load_experiment_set(folder)
            check_problem_size(fs)
        except InputError as err:
            failed[name] = " ".join(str(err).split())
            say(f"device {name}: not loaded: {failed[name]}")
            continue
        out.append((name, fs))
    say(f"loaded {len(out)} of {len(folders)} device folders")
    return out, failed


def _structure(fs) -> tuple:
    """What one compiled solver needs to be the same for every device: the device, its
    options and the free list (paths, per-run flags, bounds)."""
    free = tuple((p.path, p.per_experiment, p.lower, p.upper) for p in fs.free)
    return fs.spec.name, json.dumps(fs.options, sort_keys=True, default=repr), free


def check_same_structure(loaded) -> None:
    """Refuse, by device name and before any fit, a batch whose devices differ in device,
    options or free list (fit each structure in its own `greybox fit-many`)."""
    from greybox._model.errors import InputError

    groups: dict = {}
    for name, fs in loaded:
        groups.setdefault(_structure(fs), []).append(name)
    if len(groups) <= 1:
        return
    parts = []
    for (device, options, free), names in groups.items():
        shown = ", ".join(names[:5]) + (f" and {len(names) - 5} more" if len(names) > 5 else "")
        parts.append(f"{shown}: {device} {options} free [{', '.join(f[0] for f in free)}]")
    raise InputError(
        f"the devices differ in structure ({'; '.join(parts)}); one batch fits one structure: "
        "give the same device, [model] options and [fit] free list, or run fit-many once per "
        "structure. Nothing was fitted",
        field="FOLDER",
    )


def _option_key(fs) -> str:
    key = {k: repr(v) for k, v in sorted(fs.fit_options.items())}
    key["[noise]"] = repr(fs.noise)  # one noise model (least squares or one ProcessNoise) a batch
    return json.dumps(key)


def _why(err: BaseException) -> str:
    """One line saying why a device's fit failed (the user's file and line when theirs)."""
    from greybox._usercode import blame_user

    blamed = blame_user(err)
    text = str(blamed) if blamed is not None else f"{type(err).__name__}: {err}"
    return " ".join(text.split())[:400]


def _named_member(err: BaseException, members) -> str | None:
    """The member a batch's error is about: `fit_batch` checks every device before it solves
    any and starts such an error with the device's name (None: not one member's)."""
    if type(err) is not ValueError:
        return None
    named = [name for name, _ in members if str(err).startswith(f"{name}: ")]
    return named[0] if len(named) == 1 else None


def _fit_members(members, args, say, failed) -> dict:
    """{name: FitResult} of `members` fitted as one batch; a member the batch refuses by name
    (`_named_member`) is recorded in `failed` and the others are batched again without it."""
    members = list(members)
    while True:
        try:
            return _fit_group(members, args, say)
        except Exception as err:
            name = _named_member(err, members)
            if name is None:
                raise
            why, said = _why(err), f"ValueError: {name}: "
            failed[name] = why[len(said) :] if why.startswith(said) else why
            members = [m for m in members if m[0] != name]
            if not members:
                return {}
            say(f"device {name}: {failed[name]}; fitting the other {len(members)} together")


def fit_devices(loaded, args, say):
    """({name: FitResult}, {name: why}) for every device, batched per distinct fit options.
    A device the batch refuses by name before solving (too few readings for its parameters,
    say) is left out and the others batched again; a batch that raises otherwise is fitted
    again device by device, so one device whose code fails (e.g. its `linear_dynamics`
    raises for its values) loses only itself."""
    from greybox._model.errors import InputError

    by_options: dict = {}
    results, failed = {}, {}
    process = [(name, fs) for name, fs in loaded if fs.noise is not None]
    if process and args.scheduler:
        raise InputError(
            f"{process[0][0]} is a process-noise fit, which --scheduler does not distribute; "
            "leave --scheduler out (process-noise devices are batched in this process)",
            field="--scheduler",
        )
    for name, fs in loaded:  # process-noise devices batch with those of the same [noise]
        by_options.setdefault(_option_key(fs), []).append((name, fs))
    for members in by_options.values():
        try:
            results.update(_fit_members(members, args, say, failed))
        except (InputError, KeyboardInterrupt):
            raise
        except Exception as err:
            members = [m for m in members if m[0] not in failed]  # refused by name already
            if len(members) == 1:
                failed[members[0][0]] = _why(err)
                continue
            say(f"the batch of {len(members)} devices failed ({_why(err)}); fitting one by one")
            for member in members:
                try:
                    results.update(_fit_group([member], args, say))
                except (InputError, KeyboardInterrupt):
                    raise
                except Exception as one:
                    failed[member[0]] = _why(one)
    for name, r in list(results.items()):  # a NaN fit is a failure, never a figure
        if not _finite_result(r):
            cost = float(r.cost)
            failed[name] = f"the fit gave non-finite values (cost {cost:g}); check its data"
            del results[name]
    return results, failed


def _finite_result(r) -> bool:
    values = [float(r.cost)] + [float(p.value) for p in r.parameters]
    return all(math.isfinite(v) for v in values)


def _fit_group(members, args, say) -> dict:
    from greybox._estimate.batch import Device, fit_batch

    budget = None if args.memory_budget_mb is None else args.memory_budget_mb * 1e6
    opts = dict(members[0][1].fit_options)
    opts.pop("progress", None)
    if members[0][1].noise is not None:  # the likelihood back end, vmapped over devices
        from greybox.io._noise_table import noise_model

        devices, noise = [], None
        for n, fs in members:
            model, noise, noise_free = noise_model(fs.noise, fs.model, fs.spec)
            devices.append(Device(n, model, fs.estimation, free=(*fs.free, *noise_free)))
        out = fit_batch(devices, devices[0].free, noise=noise, progress=say, **opts)
        return dict(out.results)
    devices = [Device(n, fs.model, fs.estimation, free=fs.free) for n, fs in members]
    free = members[0][1].free
    if args.scheduler:
        from greybox._estimate.distributed import fit_distributed

        out = fit_distributed(
            devices,
            free,
            scheduler=args.scheduler,
            n_workers=args.workers,
            memory_budget_bytes=budget,
            progress=say,
            **opts,
        )
    else:
        extra = {} if budget is None else {"memory_budget_bytes": budget}
        out = fit_batch(devices, free, progress=say, **opts, **extra)
    return dict(out.results)


def write_device(
    folder: Path, fs, result, validation, figures: bool, fmt: str = "png", defer=None
) -> None:
    """A device's result folder; its figures drawn here, or added to `defer` (a list, drawn
    later by `greybox.io._drawing.draw_many`)."""
    from greybox.io._results import write_fit_files

    folder.mkdir(parents=True)
    write_fit_files(
        folder, fs, result, validation, figures=figures, tables=False, fmt=fmt, defer=defer
    )


def batch_csv(rows) -> str:
    cols = []
    for r in rows:
        cols += [k for k in r if k not in cols]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=cols, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: ("" if v is None else v) for k, v in r.items()})
    return buf.getvalue()


def _fmt(v) -> str:
    if isinstance(v, float):
        return "—" if not math.isfinite(v) else f"{v:.5g}"
    return str(v)


def batch_markdown(results, population=None, headlines=None) -> str:
    """batch.md: one row per device (status, its report's headline verdict from
    `headlines`, {device: `verdict.Headline`}, every shared value with its standard error,
    simulation fit %), what was fitted, and the population model if any."""
    headlines = headlines or {}
    shared = [p for p in next(iter(results.values())).parameters if p.experiment is None]
    head = ["device", "status", "verdict", *[f"{p.name} [{p.unit}]" for p in shared]]
    head.append("fit % (mean, min)")
    process = sum(bool(getattr(r, "process_noise", False)) for r in results.values())
    objectives = [
        *(["least squares on the free-run simulation error"] if process < len(results) else []),
        *(["maximum likelihood of the one-step prediction errors, Kalman filter"] * bool(process)),
    ]
    lines = [
        "# Batch fit",
        "",
        f"{len(results)} devices, each fitted as `greybox fit` fits one ("
        + "; ".join(objectives)
        + "; one compiled solver per structure). Values ± standard error; verdict: the "
        "headline of the device's report.md (the residual test, bounds, physical ranges); fit "
        "% is simulation fit % per output, mean and worst run.",
        "",
        "| " + " | ".join(head) + " |",
        "|" + "---|" * len(head),
    ]
    for name, r in results.items():
        h = headlines.get(name)
        cells = [name, r.status, "—" if h is None else h.verdict]
        for p in shared:
            q = r.estimate(p.name)
            cells.append(
                f"{_fmt(q.value)} ± {_fmt(q.se)}"
                + ("" if q.verdict == "identifiable" else f" ({q.verdict})")
            )
        fits = [
            list(map(float, v if hasattr(v, "__len__") else [v])) for v in r.fit_percent.values()
        ]
        per_out = list(zip(*fits))
        cells.append("; ".join(f"{sum(c) / len(c):.1f}, {min(c):.1f}" for c in per_out))
        lines.append("| " + " | ".join(cells) + " |")
    if population is not None:
        lines += ["", population_markdown(population)]
    return "\n".join(lines) + "\n"


def population_markdown(pop) -> str:
    lines = [
        "## Population model",
        "",
        f"Method: {pop.method}.",
        "",
        "| parameter | kind | population median (SE) | spread omega (SE) | CV | raw log-sd | "
        "new device: median [95 % band] | Cochran Q p |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, p in pop.parameters.items():
        if p.kind == "fixed":
            lines.append(f"| {name} | fixed | — | — | — | — | — | — |")
            continue
        nd = p.new_device
        lines.append(
            f"| {name} | {p.kind} | {_fmt(p.median)} ({_fmt(p.median_se)}) | "
            f"{_fmt(p.omega)} ({_fmt(p.omega_se)}) | {_fmt(p.cv)} | {_fmt(p.raw_log_sd)} | "
            f"{_fmt(nd[0])} [{_fmt(nd[1])}, {_fmt(nd[2])}] | {_fmt(p.q_p)} |"
        )
    flagged = pop.outliers
    lines += [
        "",
        f"Devices that do not belong ({len(flagged)}):" if flagged else "No device flagged.",
    ]
    for d in flagged:
        lines.append(f"- {d}: {'; '.join(pop.flags[d])}")
    return "\n".join(lines)


def write_figures(folder: Path, results, fmt: str = "png") -> list[str]:
    """Histograms of each shared parameter across devices and their pairwise scatter
    (figures/histograms.<fmt>, figures/scatter.<fmt>)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    first = next(iter(results.values()))
    shared = [p.name for p in first.parameters if p.experiment is None]
    vals = {k: np.array([r.estimate(k).value for r in results.values()]) for k in shared}
    ses = {k: np.array([r.estimate(k).se for r in results.values()]) for k in shared}
    (folder / "figures").mkdir()
    names = []
    fig, axes = plt.subplots(1, len(shared), figsize=(4 * len(shared), 3.2), squeeze=False)
    for ax, k in zip(axes[0], shared):
        ax.hist(vals[k], bins=max(5, min(40, len(vals[k]) // 3)), color="C0", alpha=0.8)
        ax.set_xlabel(k)
        ax.set_ylabel("devices")
    fig.tight_layout()
    fig.savefig(folder / f"figures/histograms.{fmt}", dpi=110)
    plt.close(fig)
    names.append(f"figures/histograms.{fmt}")
    if len(shared) > 1:
        n = len(shared)
        fig, axes = plt.subplots(
            n - 1, n - 1, figsize=(3.6 * (n - 1), 3.4 * (n - 1)), squeeze=False
        )
        for i in range(1, n):
            for j in range(n - 1):
                ax = axes[i - 1][j]
                if j >= i:
                    ax.axis("off")
                    continue
                a, b = shared[j], shared[i]
                ax.errorbar(vals[a], vals[b], xerr=ses[a], yerr=ses[b], fmt=".", ms=3, alpha=0.6)
                ax.set_xlabel(a)
                ax.set_ylabel(b)
        fig.tight_layout()
        fig.savefig(folder / f"figures/scatter.{fmt}", dpi=110)
        plt.close(fig)
        names.append(f"figures/scatter.{fmt}")
    return names


def run(args) -> int:
    from greybox.io._jax_setup import configure

    configure()  # float64, compiled programs kept on disk
    from greybox.cli._common import Progress
    from greybox.cli._ticker import Ticker

    with Ticker(Progress(args.quiet)) as say:  # a line at least every 5 s, in every phase
        return _run(args, say)


def _run(args, say) -> int:
    from greybox._model.errors import InputError
    from greybox.io._atomic import atomic_output_dir, check_output_dir
    from greybox.io._results import usual_permissions

    check_settings(args)
    out = check_output_dir(args.out, force=args.force, inputs=list(args.folders))
    loaded, failed = load_devices(args.folders, say)
    if not loaded:
        raise InputError(f"no device folder loads: {'; '.join(failed.values())}", field="FOLDER")
    check_same_structure(loaded)
    kinds = {**{p: "random" for p in args.random}, **{p: "shared" for p in args.shared}}
    for path in kinds:
        for name, fs in loaded:
            if path not in {p.path for p in fs.free if not p.per_experiment}:
                raise InputError(f"--random/--shared {path}: not a shared free parameter of {name}")
    say(f"fitting {len(loaded)} devices")
    results, failed_fits = fit_devices(loaded, args, say)
    failed.update(failed_fits)
    if not results:
        raise InputError(
            f"no device could be fitted: {'; '.join(f'{k}: {v}' for k, v in failed.items())}",
            field="FOLDER",
        )
    population = None
    if kinds and len(results) >= 2:
        from greybox._estimate.population import population_from_batch

        population = population_from_batch(results, kinds)
    from greybox._estimate.batch import batch_table
    from greybox._estimate.verdict import fit_headline

    sets = dict(loaded)
    say(f"writing {out}")
    with atomic_output_dir(out, kind="fit-many", force=args.force) as tmp:
        usual_permissions(tmp)
        deferred = []  # the devices' figures, drawn side by side once every folder is written
        for name, r in results.items():
            fs = sets[name]
            validation = None
            if fs.validation and not args.no_validate:
                from greybox.cli._common import validate_loaded

                validation = validate_loaded(fs, r)  # the fit's solver settings
            write_device(
                tmp / "devices" / name,
                fs,
                r,
                validation,
                not args.no_device_figures,
                args.figure_format,
                deferred,
            )
        if deferred:
            from greybox.io._drawing import draw_many

            say(f"drawing the figures of {len(deferred)} devices")
            draw_many(deferred)
        heads = {n: fit_headline(r, sets[n].physical_ranges) for n, r in results.items()}
        rows = [dict(row, verdict=heads[row["device"]].verdict) for row in batch_table(results)]
        rows += [
            {"device": k, "status": "failed", "valid": False, "error": v} for k, v in failed.items()
        ]
        (tmp / "batch.csv").write_text(batch_csv(rows))
        figures = write_figures(tmp, results, args.figure_format)
        (tmp / "batch.md").write_text(
            batch_markdown(results, population, heads)
            + failures_markdown(failed)
            + "".join(f"\n![{Path(f).stem}]({f})\n" for f in figures)
        )
        if population is not None:
            (tmp / "population.md").write_text(population_markdown(population) + "\n")
            (tmp / "population.json").write_text(
                json.dumps(_population_document(population), indent=2, allow_nan=False) + "\n"
            )
    for name, why in failed.items():
        print(f"greybox fit-many: device {name} failed: {why}", file=sys.stderr)
    n_bad = sum(not r.valid for r in results.values())
    print(
        f"wrote {out}/ ({len(results)} devices; {n_bad} not valid; {len(failed)} failed) in "
        f"{say.elapsed:.1f} s"
    )
    return 1 if n_bad or failed else 0


def failures_markdown(failed) -> str:
    if not failed:
        return ""
    lines = ["", f"## Devices that failed ({len(failed)})", ""]
    lines += [f"- {name}: {why}" for name, why in failed.items()]
    return "\n".join(lines) + "\n"


MAX_WORKERS = 256  # a local cluster of more processes than this only thrashes


def check_settings(args) -> None:
    """Dask and memory settings, checked before any work: workers, budget, the scheduler
    (installed, and reachable when an address) -- each a located exit 2."""
    from greybox._model.errors import InputError
    from greybox.io._toml import non_finite

    if args.memory_budget_mb is not None:
        problem = non_finite(args.memory_budget_mb)
        if problem or args.memory_budget_mb <= 0:
            raise InputError(
                problem or f"{args.memory_budget_mb:g} MB must be > 0", field="--memory-budget-mb"
            )
    if not 1 <= args.workers <= MAX_WORKERS:
        raise InputError(f"{args.workers} workers; give 1 to {MAX_WORKERS}", field="--workers")
    if args.scheduler is None:
        return
    from greybox._estimate.distributed import check_scheduler

    check_scheduler(args.scheduler)


def _population_document(pop) -> dict:
    def num(x):
        x = float(x)
        return x if math.isfinite(x) else None

    return {
        "method": pop.method,
        "parameters": {
            k: {
                "kind": p.kind,
                "median": num(p.median),
                "median_se": num(p.median_se),
                "omega": num(p.omega),
                "omega_se": num(p.omega_se),
                "new_device": [num(v) for v in p.new_device],
                "z": {d: num(z) for d, z in zip(p.devices, p.z)},
            }
            for k, p in pop.parameters.items()
        },
        "flags": pop.flags,
    }
