"""`greybox describe DEVICE`: a device's channels, options and parameters (or the list)."""

from __future__ import annotations

import argparse

from greybox.cli._trust import add_trust_device_option

HELP = """\
Print what a device is: its input and output channels with the file units they accept, its
structural options ([model] in experiment.toml) with allowed values and defaults, its
parameters with unit, nominal value, the optimiser's bounds, the physical range (a fitted
value outside it is flagged as implausible; [physical_ranges] in experiment.toml overrides
it) and what the data can identify, the standard fit's free parameters, and the simulation
path its capability allows.

DEVICE is a built-in or installed name, or a file `path/to/device.py[:SPEC]` (relative to the
current folder), or a params.json written by `greybox fit` (its device with the fitted options;
a device file it names outside its own folder is imported only with --trust-device PATH).
Without DEVICE, lists the built-in and installed devices. The parameters
depend on the structure: --option key=value (repeatable, as in [model]) shows those of
another structure, e.g. `greybox describe chevron_laser --option thermal_nodes=3 --option
elongation_lag=true`.
"""


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "describe",
        help="show a device's channels, options and parameters (or list devices)",
        description=HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "device", metavar="DEVICE", nargs="?", help="device name, file.py:SPEC or params.json"
    )
    p.add_argument(
        "--option",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a structural option, as in [model] (TOML value: 2, true, 1.5, \"linear\" or "
        "linear); repeat for several",
    )
    add_trust_device_option(p)
    p.set_defaults(func=run)
    return p


def _bound(x) -> str:
    return "-" if x is None else f"{x:g}"


def parse_options(items) -> dict:
    """{key: value} from ``KEY=VALUE`` strings, each value read as a TOML value (a bare word
    is a string); a ValueError naming the item otherwise."""
    import tomllib

    out = {}
    for item in items:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ValueError(f"{item!r}: give KEY=VALUE, e.g. thermal_nodes=2")
        try:
            out[key] = tomllib.loads(f"v = {text.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            out[key] = text.strip()
    return out


def describe_lines(spec, options: dict | None = None) -> list[str]:
    """The text `greybox describe` prints for `spec` (with `options`, defaults otherwise)."""
    from greybox._model.device import simulation_methods

    model = spec.model(options)
    lines = [f"device {spec.name}: {type(model).__name__}"]
    if spec.description:
        lines += ["", " ".join(spec.description.split())]
    lines += ["", "inputs (CSV column <name>_<unit>):"]
    for c in spec.inputs:
        rng = (
            ""
            if c.minimum is None and c.maximum is None
            else (f", range {_bound(c.minimum)}..{_bound(c.maximum)} {c.si_unit}")
        )
        lines.append(f"  {c.name}: {c.description} [SI {c.si_unit}; files: "
                     f"{', '.join(c.column_names())}{rng}]")  # fmt: skip
    lines.append("outputs:")
    for c in spec.outputs:
        lines.append(f"  {c.name}: {c.description} [SI {c.si_unit}; files: "
                     f"{', '.join(c.column_names())}]")  # fmt: skip
    lines.append("structural options ([model] in experiment.toml):")
    lines += [f"  {o.describe()}" for o in spec.options] or ["  none"]
    free = {p.path: p for p in spec.free_parameters(options)}
    lines.append(
        "parameters (* = freed by the standard fit; SI units; bounds = the optimiser's, "
        "physical = the range a real device has, outside it a fit is flagged implausible):"
    )
    width = max(len(p.path) for p in spec.parameter_table(options))
    for p in spec.parameter_table(options):
        star = "*" if p.path in free else " "
        per_run = " per run" if p.path in free and free[p.path].per_experiment else ""
        lo, hi = (free[p.path].lower, free[p.path].upper) if p.path in free else (p.lower, p.upper)
        plo, phi = p.physical_range
        lines.append(
            f" {star}{p.path:<{width}}  {p.nominal:<11.4g} [{p.unit}]  bounds "
            f"{_bound(lo)}..{_bound(hi)}  physical {_bound(plo)}..{_bound(phi)}{per_run}  "
            f"{p.description}; data: {p.identifiability or 'not stated'}"
        )
    lines.append(f"simulation: {', '.join(simulation_methods(model))} (first = default)")
    return lines


def run(args) -> int:
    from greybox.io._jax_setup import configure

    configure()  # float64, compiled programs kept on disk
    from greybox._model.errors import InputError
    from greybox._model.spec import DeviceSpecError
    from greybox._registry import DeviceNotFound, available, resolve

    if args.device is None:
        for name in available():
            print(f"{name}: {' '.join(resolve(name).spec.description.split())[:100]}")
        return 0
    fitted_options = {}
    if args.device.endswith(".json"):  # a fit's params.json: its device, its options
        from greybox._usercode import trusted_devices
        from greybox.io._params_file import load_params

        with trusted_devices(args.device, args.trust_device):
            fitted = load_params(args.device)
        device, fitted_options = fitted.device, dict(fitted.options or {})
    else:
        try:
            device = resolve(args.device)
        except (DeviceNotFound, DeviceSpecError) as err:
            raise InputError(str(err), field="DEVICE") from None
    try:
        options = device.spec.resolve_options({**fitted_options, **parse_options(args.option)})
    except ValueError as err:
        raise InputError(f"{err} (the options are listed without --option)", field="--option")
    chosen = ", ".join(f"{k} = {v!r}" for k, v in options.items())
    print("\n".join(describe_lines(device.spec, options)))
    if chosen:
        print(f"structure shown: {chosen}")
    print(f"source: {device.source} ({device.location})")
    return 0
