"""Physical plausibility: is a fitted value (or a setting) inside its physical range?

Every row of a device's parameter table carries a physical range (`ParameterInfo.physical`,
a fact about the device's material and geometry), distinct from the optimiser's bounds: a
fit may wander anywhere its bounds allow, but a value outside the physical range is not a
property of a real device of that kind. An optimum of the data at such a value says the
structure (or a value held fixed in it) is wrong and something else took up the misfit.

`[physical_ranges]` in experiment.toml overrides a range for another material or geometry
(`parse_physical_ranges`); every value outside its range is reported, all together (pure:
no file I/O, no printing).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping


@dataclasses.dataclass(frozen=True)
class PhysicalRange:
    """The physical range of one parameter: [`lower`, `upper`] in `unit` (SI; None on a side
    means unbounded); `source` says where it comes from ("device" or "experiment.toml")."""

    path: str
    unit: str
    lower: float | None
    upper: float | None
    description: str = ""
    source: str = "device"

    def contains(self, value: float) -> bool:
        if not math.isfinite(value):
            return False
        return (self.lower is None or value >= self.lower) and (
            self.upper is None or value <= self.upper
        )

    @property
    def text(self) -> str:
        lo = "-inf" if self.lower is None else f"{self.lower:g}"
        hi = "inf" if self.upper is None else f"{self.upper:g}"
        unit = "" if self.unit in ("", "1") else f" {self.unit}"
        return f"[{lo}, {hi}]{unit}"


def physical_ranges(parameter_table, overrides: Mapping | None = None) -> dict:
    """{path: `PhysicalRange`} of a parameter table, `overrides` ({path: (lower, upper)},
    e.g. from `parse_physical_ranges`) replacing the device's ranges."""
    overrides = dict(overrides or {})
    out = {}
    for p in parameter_table:
        if p.path in overrides:
            lo, hi = overrides[p.path]
            out[p.path] = PhysicalRange(p.path, p.unit, lo, hi, p.description, "experiment.toml")
        else:
            lo, hi = p.physical_range
            out[p.path] = PhysicalRange(p.path, p.unit, lo, hi, p.description)
    return out


def _flatten(table: Mapping, prefix: str = "") -> dict:
    """Dotted keys: TOML reads an unquoted ``thermal.tau_s = ...`` as nested tables."""
    out = {}
    for k, v in table.items():
        key = f"{prefix}.{k}" if prefix else str(k)
        if isinstance(v, Mapping):
            out.update(_flatten(v, key))
        else:
            out[key] = v
    return out


def _bound(v) -> float | None:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or math.isnan(v):
        raise ValueError
    return None if math.isinf(v) else float(v)


def parse_physical_ranges(table, parameter_table) -> tuple[dict, list]:
    """The overrides of ``[physical_ranges]`` and every problem in it.

    `table`: the TOML table ``{path: [lower, upper]}`` in the parameter's SI unit (``inf`` /
    ``-inf`` for an open side; a dotted path may be quoted or written as nested keys).
    Returns ({path: (lower or None, upper or None)}, [(key, message), ...]): all problems,
    not only the first (an unknown path, a value that is not two numbers, lower >= upper).
    """
    if not isinstance(table, Mapping):
        return {}, [
            ((), 'must be a table of path = [lower, upper] (SI), e.g. "thermal.tau_s" = [1e-3, 1]')
        ]
    rows = {p.path: p for p in parameter_table}
    overrides, problems = {}, []
    for key, value in _flatten(table).items():
        if key not in rows:
            listed = ", ".join(rows)
            problems.append(
                (key, f"{key!r} is not a parameter of this structure; the parameters are: {listed}")
            )
            continue
        unit = rows[key].unit
        try:
            if not isinstance(value, list) or len(value) != 2:
                raise ValueError
            lo, hi = (_bound(v) for v in value)
        except ValueError:
            problems.append(
                (
                    key,
                    f"{repr(value)[:40]}: give [lower, upper] in {unit} (SI numbers; inf or "
                    "-inf for an open side)",
                )
            )
            continue
        if lo is not None and hi is not None and not hi > lo:
            problems.append((key, f"upper {hi:g} must exceed lower {lo:g} ({unit})"))
            continue
        overrides[key] = (lo, hi)
    return overrides, problems


def out_of_range_settings(settings: Mapping, ranges: Mapping) -> list:
    """[(path, message)] for every setting outside its physical range (all of them)."""
    out = []
    for path, v in settings.items():
        r = ranges.get(path)
        if r is None or r.contains(float(v)):
            continue
        how = (
            "set in [physical_ranges]"
            if r.source == "experiment.toml"
            else "override it in [physical_ranges] for another material or geometry"
        )
        out.append(
            (
                path,
                f"{float(v):g} {r.unit} is outside the physical range of {path} {r.text} "
                f"({r.description}); give a value in range in SI units, or {how}",
            )
        )
    return out


@dataclasses.dataclass(frozen=True)
class Implausible:
    """A fitted value outside its physical range (`experiment`: the run of a per-run value)."""

    name: str
    path: str
    value: float
    unit: str
    range: PhysicalRange
    experiment: str | None = None

    @property
    def side(self) -> str:
        r = self.range
        return "below" if r.lower is not None and self.value < r.lower else "above"

    @property
    def text(self) -> str:
        unit = "" if self.unit in ("", "1") else f" {self.unit}"
        src = " (set in experiment.toml)" if self.range.source == "experiment.toml" else ""
        return (
            f"{self.name} = {self.value:.4g}{unit} is {self.side} its physical range "
            f"{self.range.text}{src}"
        )

    def as_json(self) -> dict:
        return {
            "name": self.name,
            "path": self.path,
            "value": self.value,
            "unit": self.unit,
            "physical_range": [  # JSON has no inf: an open side is null
                v if v is not None and math.isfinite(v) else None
                for v in (self.range.lower, self.range.upper)
            ],
            "range_source": self.range.source,
            "run": self.experiment,
        }


def implausible_values(estimates: Iterable, ranges: Mapping) -> tuple[Implausible, ...]:
    """Every fitted value outside its physical range, all together.

    `estimates`: objects with `name`, `path`, `value` and optionally `unit` and `experiment`
    (a `FitResult`'s `parameters`); `ranges`: {path: `PhysicalRange`} (`physical_ranges`)."""
    out = []
    for p in estimates:
        r = ranges.get(p.path)
        # a non-finite value is a diverged fit, which its status reports, not a physics question
        if r is None or not math.isfinite(float(p.value)) or r.contains(float(p.value)):
            continue
        out.append(
            Implausible(
                p.name,
                p.path,
                float(p.value),
                getattr(p, "unit", r.unit),
                r,
                getattr(p, "experiment", None),
            )
        )
    return tuple(out)


def implausible_lines(found: Iterable[Implausible]) -> list[str]:
    """Report lines (markdown) listing every implausible value, for the top of a report."""
    found = list(found)
    if not found:
        return []
    return [
        f"**Physically implausible: {len(found)} fitted value(s) outside the physical range** "
        "(the optimum of the data sits where no real device of this kind is; the structure, or "
        "a value held fixed in it, is likely wrong, and another parameter absorbed the misfit):",
        *[f"- {f.text}" for f in found],
    ]
