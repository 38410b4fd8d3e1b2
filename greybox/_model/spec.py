"""`DeviceSpec`: everything greybox needs to know about a device, in one small typed object.

A device author writes one spec per device (built-in devices in ``models/`` and a user's own
file are written the same way): its input and output channels, its parameter table, the
parameters a standard fit frees, the structural options it accepts and a factory
``build(**options) -> model``. `DeviceSpec.check` runs once when the spec is registered and
names whatever is missing or inconsistent, so a mistake in a spec never surfaces as a bare
error deep inside a fit.
"""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Callable, Mapping, Sequence

from greybox._model.channels import Channel
from greybox._model.device import AbstractDevice
from greybox._model.freeparams import FreeParameter
from greybox._model.parameters import ParameterInfo, check_scalar_path, with_overrides

_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]*$")
_KINDS = (bool, int, float, str)


class DeviceSpecError(ValueError):
    """A device spec that cannot work, naming the device and what to fix."""


@dataclasses.dataclass(frozen=True)
class Option:
    """A structural option of a device (chosen per experiment in ``[model]``).

    - `name`, `default`, `meaning` (one line for help texts and ``greybox describe``);
    - `choices`: the allowed values, if a closed set;
    - `minimum`, `maximum`: range for numbers; `unit`: unit of a numeric option.
    The option's type is the type of `default` (bool, int, float or str); an int is accepted
    for a float option.
    """

    name: str
    default: bool | int | float | str
    meaning: str
    choices: tuple = ()
    minimum: float | None = None
    maximum: float | None = None
    unit: str = ""

    @property
    def kind(self) -> type:
        return type(self.default)

    def check(self, value):
        """`value` converted to the option's type; a ValueError saying what is allowed."""
        kind = self.kind
        ok = isinstance(value, kind) and not (kind is int and isinstance(value, bool))
        if kind is float and isinstance(value, int) and not isinstance(value, bool):
            value, ok = float(value), True
        if not ok:
            raise ValueError(f"{value!r} must be a {kind.__name__} ({self.meaning})")
        if kind is float and not math.isfinite(value):  # NaN passes every comparison below
            raise ValueError(f"{value!r} is not finite; give a finite number ({self.meaning})")
        if self.choices and value not in self.choices:
            allowed = ", ".join(repr(c) for c in self.choices)
            raise ValueError(f"{value!r} is not allowed; use one of {allowed}")
        if self.minimum is not None and value < self.minimum:
            raise ValueError(f"{value!r} is below the minimum {self.minimum:g} {self.unit}")
        if self.maximum is not None and value > self.maximum:
            raise ValueError(f"{value!r} is above the maximum {self.maximum:g} {self.unit}")
        return value

    def describe(self) -> str:
        allowed = (
            " | ".join(repr(c) for c in self.choices)
            if self.choices
            else (f"{self.kind.__name__}" + (f" [{self.unit}]" if self.unit else ""))
        )
        return f"{self.name} = {self.default!r}  ({allowed}): {self.meaning}"


def _as_callable(value):
    return value if callable(value) else (lambda **_options: value)


@dataclasses.dataclass(frozen=True)
class DeviceSpec:
    """A device: channels, parameters, options and how to build it.

    - `name`: identifier used in ``experiment.toml`` and reports.
    - `inputs`, `outputs`: `Channel`s (column names and units of the files).
    - `build`: ``build(**options) -> model`` at nominal values for the given options.
    - `parameters`: the parameter table (`ParameterInfo`s), or a function of the options;
      each row's physical range (`ParameterInfo.physical`, else its bounds) holds its nominal.
    - `default_free`: the standard fit's `FreeParameter`s, or a function of the options.
    - `options`: the structural `Option`s accepted in ``[model]``.
    - `start_values`: optional hook ``(model, free, experiments) -> free`` that sets starting
      values of per-run parameters from the data (e.g. camera offsets from rest readings).
    - `run_settings`: optional hook ``(model, experiment, options) -> {path: SI value}``:
      per-run settings the device can read off a run's own data when the experiment file
      does not give them (TCLab: the initial temperatures from each sensor's first valid
      reading). `experiment` is the loaded `Experiment` (SI, NaN = missing); values the file
      gives (per-run or [experiment] settings) or that are fitted always win. Loaders call it
      once per run, so io stays device-agnostic.
    - `description`: one paragraph for ``greybox describe``.
    - `state_unit`: the SI unit every state of the model shares ("K" for a thermal network),
      a tuple of one per state (("m", "m/s") for a position and a velocity), or None: the
      unit of its process-noise intensities (unit^2/s; [noise] `state_unit` overrides it).
      Undeclared, they are labelled "(state unit)^2/s": the states' unit is not guessed from
      the outputs' (a chevron's temperatures are read as a displacement).
    """

    name: str
    inputs: tuple[Channel, ...]
    outputs: tuple[Channel, ...]
    build: Callable[..., AbstractDevice]
    parameters: tuple[ParameterInfo, ...] | Callable[..., tuple[ParameterInfo, ...]]
    default_free: Sequence[FreeParameter] | Callable[..., Sequence[FreeParameter]]
    options: tuple[Option, ...] = ()
    start_values: Callable | None = None
    description: str = ""
    run_settings: Callable | None = None
    state_unit: str | tuple[str, ...] | None = None

    def option(self, name: str) -> Option:
        for o in self.options:
            if o.name == name:
                return o
        raise KeyError(name)

    def resolve_options(self, given: Mapping | None = None) -> dict:
        """Every option with `given` values checked and defaults filled in.

        Raises `ValueError` whose message starts with the option name."""
        given = dict(given or {})
        known = {o.name for o in self.options}
        for key in given:
            if key not in known:
                listed = ", ".join(sorted(known)) or "none"
                raise ValueError(f"{key}: {self.name} has no option {key!r}; its options: {listed}")
        out = {}
        for o in self.options:
            if o.name in given:
                try:
                    out[o.name] = o.check(given[o.name])
                except ValueError as err:
                    raise ValueError(f"{o.name}: {err}") from None
            else:
                out[o.name] = o.default
        return out

    def model(self, options: Mapping | None = None, **kwargs):
        """The device built with `options` (defaults for the rest) and parameter values.

        Keyword arguments named after an option are options (``contacts="friction"``); the
        others set parameter values, '__' standing for '.' (``thermal__tau_s=0.05``)."""
        names = {o.name for o in self.options}
        chosen = {**dict(options or {}), **{k: v for k, v in kwargs.items() if k in names}}
        overrides = {k: v for k, v in kwargs.items() if k not in names}
        return with_overrides(self.build(**self.resolve_options(chosen)), overrides)

    def parameter_table(self, options: Mapping | None = None) -> tuple[ParameterInfo, ...]:
        return tuple(_as_callable(self.parameters)(**self.resolve_options(options)))

    def free_parameters(self, options: Mapping | None = None) -> tuple[FreeParameter, ...]:
        return tuple(_as_callable(self.default_free)(**self.resolve_options(options)))

    def parameter_info(self, path: str, options: Mapping | None = None) -> ParameterInfo | None:
        return next((p for p in self.parameter_table(options) if p.path == path), None)

    def check(self) -> DeviceSpec:
        """Check the spec once (at registration); raise `DeviceSpecError` naming the problem."""

        def fail(what: str):
            raise DeviceSpecError(f"device spec {self.name!r}: {what}")

        if not isinstance(self.name, str) or not _NAME.match(self.name):
            fail("name must be an identifier (letters, digits, '_'), e.g. 'my_chevron'")
        for kind, chans in (("inputs", self.inputs), ("outputs", self.outputs)):
            if not chans or not all(isinstance(c, Channel) for c in chans):
                fail(f"{kind} must be a non-empty tuple of greybox.Channel")
            names = [c.name for c in chans]
            if len(set(names)) != len(names):
                fail(f"{kind}: channel names repeat ({names})")
        if not callable(self.build):
            fail("build must be a function build(**options) -> device model")
        units = (self.state_unit,) if isinstance(self.state_unit, str) else self.state_unit
        if units is not None and not (
            isinstance(units, tuple)
            and units
            and all(isinstance(u, str) and u.strip() for u in units)
        ):
            fail(
                "state_unit must be a unit string such as 'K', a tuple of one per state "
                f"such as ('m', 'm/s'), or None; got {self.state_unit!r}"
            )
        if self.run_settings is not None and not callable(self.run_settings):
            fail("run_settings must be a function (model, experiment, options) -> {path: value}")
        seen = set()
        for o in self.options:
            if not isinstance(o, Option):
                fail(f"options must hold greybox.Option objects, got {o!r}")
            if o.name in seen:
                fail(f"option {o.name!r} is declared twice")
            seen.add(o.name)
            if not isinstance(o.default, _KINDS):
                fail(f"option {o.name!r}: default must be a bool, int, float or str")
            try:
                o.check(o.default)
            except ValueError as err:
                fail(f"option {o.name!r}: its default {err}")
        try:
            model = self.model()
        except Exception as err:  # a spec author's bug: name it, keep the cause
            raise DeviceSpecError(
                f"device spec {self.name!r}: build(**defaults) failed: {err}"
            ) from err
        if not isinstance(model, AbstractDevice):
            fail(
                f"build returned {type(model).__name__}, not a greybox device (subclass "
                "greybox.AbstractLinearDevice, AbstractODEDevice or AbstractSteppedDevice)"
            )
        if model.n_inputs != len(self.inputs) or model.n_outputs != len(self.outputs):
            fail(
                f"the model has {model.n_inputs} input(s) and {model.n_outputs} output(s) but "
                f"the spec declares {len(self.inputs)} and {len(self.outputs)} channels"
            )
        table = self.parameter_table()
        paths = [p.path for p in table]
        clash = {o.name for o in self.options} & {p.replace(".", "__") for p in paths}
        if clash:
            fail(f"option names {sorted(clash)} are also parameter paths; rename the options")
        if len(set(paths)) != len(paths):
            fail("a path appears twice in the parameter table")
        for p in table:
            try:
                check_scalar_path(model, p.path)
            except ValueError as err:
                fail(f"parameter table: {err}")
            lo, hi = p.physical_range  # a fact about the device: its nominal value lies inside
            if (lo is not None and hi is not None and not hi > lo) or not (
                (lo is None or p.nominal >= lo) and (hi is None or p.nominal <= hi)
            ):
                fail(
                    f"parameter {p.path!r}: physical range [{lo}, {hi}] must be ordered and "
                    f"hold the nominal value {p.nominal:g}"
                )
        for fp in self.free_parameters():
            if fp.path not in paths:
                fail(f"default free parameter {fp.path!r} is not in the parameter table")
        return self
