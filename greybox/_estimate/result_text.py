"""A fit result as short text: the repr, the parameter table (`FitResult.summary`), its HTML
form for notebooks and its rows for a DataFrame. Pure (results in, text out); the readable
units (um, mW, ms) and number formats are the report's (greybox/report/_markdown.py imports
them from here, so a value reads the same in report.md, on the console and in a notebook)."""

from __future__ import annotations

import html
import re

import numpy as np

_DISPLAY = {"m": (1e6, "um"), "s": (1e3, "ms"), "m/s": (1e6, "um/s"), "W": (1e3, "mW")}
_PREFIXES = ((1e-3, "k"), (1.0, ""), (1e3, "m"), (1e6, "u"), (1e9, "n"), (1e12, "p"))
COLUMNS = ("parameter", "value", "sd", "ci95_low", "ci95_high", "unit", "verdict", "experiment")


def _leading_power(unit: str) -> bool:
    """True when the unit's leading factor carries a power (m^2/s) or is not a plain symbol:
    a prefix would then apply to the power (nm^2 is 1e-18 m^2, not 1e-9 m^2)."""
    head = re.match(r"[A-Za-z]+(\^)?", unit)
    return head is None or head.group(1) is not None


def display_unit(unit: str, value: float | None = None) -> tuple[float, str]:
    """(factor, readable unit) for an SI unit: m -> um, W -> mW, s -> ms (when `value` is
    under 1 s or not given); other units get an SI prefix when `value` is tiny or huge."""
    if unit == "s" and value is not None and np.isfinite(value) and abs(value) >= 1.0:
        return 1.0, "s"
    if unit in _DISPLAY:
        return _DISPLAY[unit]
    # Other units get an SI prefix when the number would otherwise be unreadable
    # (2.4e-7 J/K -> 240 nJ/K); not on units led by K (kK/W would mislead) or dimensionless ones.
    if (
        value is not None
        and np.isfinite(value)
        and value != 0
        and unit
        and unit[0] not in "K%1-"
        and not _leading_power(unit)
        and not 1e-2 <= abs(value) < 1e4
    ):
        for factor, prefix in _PREFIXES:
            if abs(value) * factor >= 1.0 or factor == _PREFIXES[-1][0]:
                return factor, prefix + unit
    return 1.0, unit


def fmt(x, digits: int = 4) -> str:
    """A number for a table: `digits` significant figures, "n/a" for NaN/None; an array (a
    figure per output channel) is written as its entries joined by " / "."""
    if x is not None and np.ndim(x) > 0:
        return " / ".join(fmt(v, digits) for v in np.asarray(x, dtype=float).reshape(-1))
    if x is None or not np.isfinite(x):
        return "n/a"
    return f"{x:.{digits}g}"


def estimate_texts(p) -> tuple[str, str, str]:
    """(value, 95 % interval, display unit) of a `ParameterEstimate`, in display units, with
    as many decimals as its standard error warrants (two significant digits of the se)."""
    f, unit = display_unit(p.unit, p.value)
    digits = None
    if p.se is not None and np.isfinite(p.se) and p.se * f > 0:
        digits = max(0, 1 - int(np.floor(np.log10(abs(p.se * f)))))

    def one(x):
        if x is None or not np.isfinite(x):
            return "n/a"
        return f"{x * f:.{digits}f}" if digits is not None else fmt(x * f, 5)

    ci = "n/a" if not np.all(np.isfinite(p.ci95)) else f"[{one(p.ci95[0])}, {one(p.ci95[1])}]"
    return one(p.value), ci, unit


def verdict_text(p) -> str:
    """A parameter's verdict, with "(prior)" and which bound it sits on."""
    text = p.verdict + (" (prior)" if p.prior else "")
    if p.verdict == "at bound" and getattr(p, "bound", None):
        text += f" ({p.bound})"
    return text


def fit_kind(result) -> str:
    """What the fit minimised: the simulation error, or the one-step likelihood."""
    return "one-step likelihood" if result.process_noise else "simulation-error"


def headline(result) -> str:
    """One line: status, what was fitted, how many parameters and runs, cost or log L."""
    n = len(result.parameters)
    runs = len(result.experiments)
    score = (
        f"log L {fmt(result.log_likelihood, 6)}"
        if result.process_noise
        else f"cost {fmt(result.cost, 6)}"
    )
    return (
        f"{result.status}, {fit_kind(result)} fit, {n} parameter{'s' * (n != 1)}, "
        f"{runs} run{'s' * (runs != 1)}, {score}"
    )


def short_repr(result) -> str:
    return f"<FitResult: {headline(result)}>"


def _cells(p) -> list[str]:
    value, ci, unit = estimate_texts(p)
    return [p.name, value, ci, unit if unit != "1" else "-", verdict_text(p)]


HEAD = ["parameter", "estimate", "95 % interval", "unit", "verdict"]


def summary_text(result) -> str:
    """The headline and the parameter table, aligned, in readable units."""
    rows = [HEAD, *(_cells(p) for p in result.parameters)]
    widths = [max(len(r[j]) for r in rows) for j in range(len(HEAD))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join([f"FitResult: {headline(result)}", *lines])


def summary_html(result) -> str:
    """The same as `summary_text`, as an HTML table (a notebook's rich display)."""

    def row(cells, tag):
        return "<tr>" + "".join(f"<{tag}>{html.escape(c)}</{tag}>" for c in cells) + "</tr>"

    body = "".join(row(_cells(p), "td") for p in result.parameters)
    return (
        f"<p><b>FitResult</b>: {html.escape(headline(result))}</p>"
        f"<table><thead>{row(HEAD, 'th')}</thead><tbody>{body}</tbody></table>"
    )


def parameter_rows(result) -> list[dict]:
    """One dict per parameter in SI (`COLUMNS`): value, sd, 95 % interval, unit, verdict."""
    return [
        dict(
            zip(
                COLUMNS,
                (
                    p.name,
                    float(p.value),
                    float(p.se),
                    float(p.ci95[0]),
                    float(p.ci95[1]),
                    p.unit,
                    p.verdict,
                    p.experiment,
                ),
            )
        )
        for p in result.parameters
    ]


def parameter_frame(result):
    """`parameter_rows` as a pandas DataFrame, one row per parameter (a per-run parameter
    once per run, `experiment` naming it); pandas is the `dataframe` extra."""
    from greybox._extras import import_extra

    pd = import_extra("pandas", "dataframe", "FitResult.to_dataframe")
    return pd.DataFrame(parameter_rows(result), columns=list(COLUMNS))
