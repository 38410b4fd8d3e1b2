"""Writing a designed experiment as an experiment.toml ready to record into (the inverse of
the loader for a `greybox.design.Design`)."""

from __future__ import annotations

from collections.abc import Sequence

from greybox._model.freeparams import FreeParameter
from greybox.design._design import Design, DesignedRun
from greybox.io._experiment_writer import inline_table, run_table


def experiment_toml(
    design: Design,
    *,
    device: str,
    free: Sequence[FreeParameter],
    m_per_px: float,
    description: str = "",
    default_free: Sequence[str] = (),
) -> str:
    """experiment.toml text for recording the design: [experiment], [camera], [fit] and one
    [[runs]] table per run (CSV files named after the runs, to be recorded)."""

    c = design.constraints
    entries = []
    for p in free:
        if p.path in default_free:
            entries.append(f'"{p.path}"')
            continue
        d = {"path": p.path}
        for key in ("lower", "upper", "prior_median", "prior_log_sd", "scale"):
            v = getattr(p, key)
            if v is not None:
                d[key] = float(v)
        if p.per_experiment:
            entries.append(inline_table(d).replace(" }", ", per_run = true }"))
        else:
            entries.append(inline_table(d))
    text = (
        f"# Designed experiment ({design.criterion}-optimal"
        f"{', Bayesian' if design.bayesian else ''}) written by greybox design.\n"
        "# Record one CSV per run (t_s, y_px) under the names below, then run `greybox fit`.\n"
        f"# {design.verdict}.\n\n"
        "[experiment]\n"
        f'device = "{device}"\n'
        f'description = "{description or "designed runs"}"\n\n'
        "[camera]\n"
        f"fps = {c.fps:g}\n"
        f"exposure_ms = {c.exposure_s * 1e3:g}\n"
        f"um_per_px = {m_per_px * 1e6:g}\n\n"
        "[fit]\n"
        f"free = [{', '.join(entries)}]\n\n"
    )
    return text + "\n".join(_run_toml(r) for r in design.runs)


def _run_toml(run: DesignedRun) -> str:
    """One [[runs]] table; list-valued waveform keys (steps) are written as TOML arrays."""

    lists = {k: v for k, v in run.description.items() if isinstance(v, list)}
    scalars = {k: v for k, v in run.description.items() if not isinstance(v, list)}
    text = run_table(run.name, "estimation", scalars)
    if not lists:
        return text
    arrays = ", ".join(f"{k} = [{', '.join(f'{float(x):g}' for x in v)}]" for k, v in lists.items())
    return text.replace(inline_table(scalars), inline_table(scalars)[:-2] + ", " + arrays + " }")


# ---------------------------------------------------------------------- inverse design
