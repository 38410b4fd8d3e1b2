"""One headline verdict for a fit, and the words that say what its intervals mean.

A fit answers several questions at once: did the optimiser reach an optimum of the data
(status), does a parameter sit on a bound, are the fitted values physically plausible
(`greybox._model.plausibility`), and do the residuals leave only noise (the whiteness test of
`greybox._estimate.residuals`). Each used to have its own line; they could disagree ("converged ...
valid" two lines above "structure misses dynamics"). `headline` combines them into one
verdict, most serious first, worded for what the 95 % intervals then mean:

1. "not valid": not converged, ran out of steps, at a bound, or diverged. The intervals mean
   nothing (the estimate is not an optimum of the data). Exit status 1.
2. "physically implausible": an optimum of the data at values no real device of this kind
   has. The intervals cover the best approximation within this structure, not physical
   values. Exit status 0, 1 with ``--strict``.
3. "structure rejected": the residual test finds structure in the misfit. The intervals cover
   the best approximation within this structure, not the physical values. Exit 0, 1 with
   ``--strict``.
4. "valid": white residuals, plausible values. The intervals cover the physical values (as
   far as the structure is right: the residual test found nothing it misses). Exit 0.

A parameter whose interval spans more than `WEAK_FACTOR` (upper / lower of the 95 %
interval) is "weakly identified", not "identifiable". For `greybox compare`: why each
candidate is not valid and what to change (`no_valid_candidate_lines`), what it means when
the residual test rejects every candidate (`all_rejected_lines`), and a ranking that never
prefers an invalid or implausible candidate (`preferred_plausible`). Pure.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Sequence

from greybox._model.plausibility import Implausible, implausible_values

WEAK_FACTOR = 10.0  # a 95 % interval wider than this factor (upper / lower): weakly identified

NOT_VALID, IMPLAUSIBLE, REJECTED, VALID = (
    "not valid",
    "physically implausible",
    "structure rejected",
    "valid",
)

# Exit status of `greybox fit` and `greybox compare`: code -> meaning. README.md's table is
# checked against this one (tests/test_verdict.py).
EXIT_STATUS = {
    0: "done: the result is written; the headline verdict (printed, and first in report.md) says "
    "whether its intervals cover the physical values or the best approximation within the "
    "structure (a rejected structure or an implausible value is reported, not an error)",
    1: "written, but the estimate is not valid (not converged, ran out of steps, a parameter "
    "at a bound, or diverged; compare: no valid candidate); with --strict also a structure "
    "the residual test rejects or a physically implausible value",
    2: "bad input or output location (one line per problem naming file, line and field; "
    "nothing written)",
    3: "a bug in greybox (traceback; please report it)",
    130: "interrupted (Ctrl-C)",
    143: "terminated (SIGTERM)",
}


def exit_status_help() -> str:
    """The exit-status paragraph of a command's --help, from `EXIT_STATUS`."""
    return "Exit status: " + "; ".join(f"{k} {v}" for k, v in EXIT_STATUS.items()) + "."


# --------------------------------------------------------------------------------------
# Identifiability: identifiable vs weakly identified


def interval_factor(ci95) -> float | None:
    """upper / lower of a 95 % interval whose ends share a sign (None otherwise: an
    interval through zero has no factor, and a location like an offset is not judged so)."""
    lo, hi = (float(v) for v in ci95)
    if not (math.isfinite(lo) and math.isfinite(hi)) or lo * hi <= 0:
        return None
    return max(abs(lo), abs(hi)) / min(abs(lo), abs(hi))


def interval_verdict(verdict: str, ci95, factor: float = WEAK_FACTOR) -> str:
    """`verdict`, or "weakly identified" instead of "identifiable" when the 95 % interval
    `ci95` spans more than `factor` (upper / lower)."""
    f = interval_factor(ci95)
    if verdict == "identifiable" and f is not None and f > factor:
        return "weakly identified"
    return verdict


def refined_verdict(estimate, factor: float = WEAK_FACTOR) -> str:
    """`interval_verdict` of a `ParameterEstimate`."""
    return interval_verdict(estimate.verdict, estimate.ci95, factor)


def with_refined_verdicts(parameters: Iterable, factor: float = WEAK_FACTOR) -> tuple:
    """`ParameterEstimate`s with `refined_verdict` applied (dataclasses.replace)."""
    return tuple(dataclasses.replace(p, verdict=refined_verdict(p, factor)) for p in parameters)


def weak_lines(parameters: Iterable, factor: float = WEAK_FACTOR) -> list[str]:
    """One line per weakly identified parameter, with its interval's factor."""
    out = []
    for p in parameters:
        if refined_verdict(p, factor) == "weakly identified":
            out.append(
                f"{p.name}: weakly identified (its 95 % interval spans a factor "
                f"{interval_factor(p.ci95):.3g} > {factor:g})"
            )
    return out


# --------------------------------------------------------------------------------------
# The headline


@dataclasses.dataclass(frozen=True)
class Headline:
    """The verdict of one fit: `verdict` (one of NOT_VALID, IMPLAUSIBLE, REJECTED, VALID),
    `text` (the headline line), `intervals` (what the 95 % intervals cover), `details`
    (further lines: implausible values, weakly identified parameters, a local optimum),
    `exit_status` (with `strict` applied)."""

    verdict: str
    text: str
    intervals: str
    details: tuple = ()
    exit_status: int = 0
    implausible: tuple = ()

    @property
    def lines(self) -> list[str]:
        """Markdown lines for the top of report.md."""
        return [f"**{self.text}**", "", self.intervals, *[f"- {d}" for d in self.details]]

    def as_json(self) -> dict:
        """For params.json and compare.json: the verdict, its words and every implausible
        value."""
        return {
            "verdict": self.verdict,
            "text": self.text,
            "intervals": self.intervals,
            "details": list(self.details),
            "implausible": [f.as_json() for f in self.implausible],
            "exit_status": self.exit_status,
        }


def residuals_rejected(residuals) -> bool | None:
    """True if the residual test rejects whiteness, False if it does not, None if the test
    was not possible (too few readings) or not run."""
    if residuals is None:
        return None
    q = getattr(residuals, "q", None)
    if q is not None and not any(math.isfinite(float(v)) for v in q):
        return None
    return not bool(residuals.all_white)


def headline(
    result,
    implausible: Sequence[Implausible] = (),
    *,
    strict: bool = False,
    factor: float = WEAK_FACTOR,
) -> Headline:
    """The headline of a fit (`FitResult`-like: `status`, `valid`, `message`, `residuals`,
    `parameters`) given its implausible values (`implausible_values`).

    `strict`: a rejected structure or an implausible value makes the exit status 1."""
    implausible = tuple(implausible)
    rejected = residuals_rejected(getattr(result, "residuals", None))
    details = [f.text for f in implausible]
    details += weak_lines(getattr(result, "parameters", ()), factor)
    if result.status == "local optimum":
        details.append(
            "the given starting values stopped at a higher cost than another start; the "
            "best start's estimate is reported (it is an optimum of the data)"
        )
    if not result.valid:
        return Headline(
            NOT_VALID,
            f"Not valid ({result.status}): {result.message}",
            "The estimate is not an optimum of the data, so its standard errors and intervals "
            "mean nothing; fix what the status names and fit again.",
            tuple(details),
            1,
            implausible,
        )
    residual = {
        True: "residuals that are not white (the residual test rejects the structure)",
        False: "residuals consistent with white noise",
        None: "residual test not possible",
    }[rejected]
    if implausible or rejected:
        what = []
        if implausible:
            names = ", ".join(f.name for f in implausible)
            what.append(f"physically implausible values ({names})")
        if rejected:
            what.append(residual)
        verdict = IMPLAUSIBLE if implausible else REJECTED
        return Headline(
            verdict,
            f"{verdict.capitalize()}: an optimum of the data, with {' and '.join(what)}",
            "The intervals cover the best approximation within this structure, not the "
            "physical values of the device: "
            + (
                "the misfit is structure, not noise, so the fitted values absorb what the "
                "structure misses. "
                if rejected
                else ""
            )
            + "Revise the structure (or the values held fixed in it) before reading them as "
            "properties of the device.",
            tuple(details),
            1 if strict else 0,
            implausible,
        )
    return Headline(
        VALID,
        f"Valid: an optimum of the data, values inside their physical ranges, {residual}",
        "The intervals cover the physical values of the device, as far as the structure is "
        "right"
        + (
            " (the residual test found nothing it misses)."
            if rejected is False
            else " (the residual test could not check it: too few readings)."
        ),
        tuple(details),
        0,
        implausible,
    )


def fit_headline(result, ranges, *, strict: bool = False, factor: float = WEAK_FACTOR):
    """`headline` of a `FitResult` with its implausible values found from `ranges`
    ({path: PhysicalRange}, `greybox._model.plausibility.physical_ranges`)."""
    return headline(
        result, implausible_values(result.parameters, ranges), strict=strict, factor=factor
    )


def standard_error_text(result) -> str:
    """Which standard errors are the headline, worded for what they are.

    The Newey-West (HAC) interval allows for autocorrelated residuals; it is said to do so
    only where it is at least as wide as the Gauss-Newton one. Neither allows for the bias of
    a wrong structure."""
    if getattr(result, "se_method", "gauss-newton") != "hac":
        return (
            "the residuals are white, so the headline standard errors are the Gauss-Newton "
            "ones; the Newey-West (HAC) sandwich ones are shown beside them and should agree"
        )
    narrower = [
        p.name
        for p in result.parameters
        if math.isfinite(p.se_hac) and math.isfinite(p.se_gauss_newton)
        and p.se_hac < p.se_gauss_newton
    ]  # fmt: skip
    if narrower:
        return (
            "the residuals are not white, so the headline standard errors are the Newey-West "
            "(HAC) sandwich ones; for " + ", ".join(narrower) + " they are narrower than the "
            "Gauss-Newton ones, so they do not widen the interval for the autocorrelated "
            "misfit there. Neither allows for a wrong structure: both describe the best "
            "approximation within this structure"
        )
    return (
        "the residuals are not white, so the headline standard errors are the Newey-West "
        "(HAC) sandwich ones, wider than the Gauss-Newton ones shown beside them: they allow "
        "for the autocorrelation of the misfit, not for the bias of a wrong structure (the "
        "intervals describe the best approximation within this structure)"
    )


# --------------------------------------------------------------------------------------
# Compare: why candidates are not valid, when the residual test rejects them all


@dataclasses.dataclass(frozen=True)
class CandidateVerdict:
    """What `compare` needs to say about one candidate: its name, headline, the parameters on
    a bound ((name, side, bound value)) and its implausible values."""

    name: str
    headline: Headline
    status: str
    message: str
    at_bound: tuple = ()
    residual_rejected: bool | None = None

    @property
    def usable(self) -> bool:
        """May be preferred: a valid fit with physically plausible values."""
        return self.headline.verdict not in (NOT_VALID, IMPLAUSIBLE)


def _bound_of(result, name: str, path: str, side: str):
    for p in getattr(result, "free", ()):
        if p.path == path:
            return getattr(p, side if side in ("lower", "upper") else "lower", None)
    return None


def candidate_verdict(name: str, result, ranges, *, factor: float = WEAK_FACTOR):
    """A `CandidateVerdict` for a fitted candidate (`FitResult`-like) and its physical
    ranges ({path: PhysicalRange})."""
    pinned = tuple(
        (p.name, p.bound or "", _bound_of(result, p.name, p.path, p.bound or ""))
        for p in result.parameters
        if p.verdict == "at bound"
    )
    return CandidateVerdict(
        name,
        fit_headline(result, ranges, factor=factor),
        result.status,
        result.message,
        pinned,
        residuals_rejected(getattr(result, "residuals", None)),
    )


def why_not_usable(v: CandidateVerdict) -> str:
    """Why candidate `v` cannot be preferred and what to change (one line)."""
    if v.at_bound:
        where = "; ".join(
            f"{n} on its {side} bound"
            + ("" if b is None else f" {b:g}")
            + f": {'lower' if side == 'lower' else 'raise'} that bound in the candidate's "
            "free list if the device's physics allows it, fix the parameter at a known value, "
            "or change the structure"
            for n, side, b in v.at_bound
        )
        return f"{v.name}: at bound: {where}"
    if v.headline.verdict == NOT_VALID:
        fix = {
            "not converged": "raise [fit] max_steps or n_starts, or start nearer (initial)",
            "ran out of steps": "raise [fit] max_steps, or start nearer (initial)",
            "diverged": "check the starting values and the bounds",
        }.get(v.status, "see its status message")
        return f"{v.name}: {v.status} ({v.message}): {fix}"
    if v.headline.verdict == IMPLAUSIBLE:
        what = "; ".join(f.text for f in v.headline.implausible)
        return (
            f"{v.name}: physically implausible: {what}: fix those parameters at known values "
            "or give them priors, or change the structure; if the device is of another "
            "material or geometry, state its ranges in [physical_ranges]"
        )
    return f"{v.name}: usable ({v.headline.verdict})"


def no_valid_candidate_lines(verdicts: Sequence[CandidateVerdict]) -> list[str]:
    """When no candidate can be preferred: for each, why (which bound, which verdict) and
    what to change. Empty when at least one is usable."""
    if any(v.usable for v in verdicts):
        return []
    return [
        "**No candidate gave a valid, physically plausible fit**; none is preferred. For each:",
        "",
        *[f"- {why_not_usable(v)}" for v in verdicts],
    ]


def all_rejected_lines(verdicts: Sequence[CandidateVerdict], rule: str = "aic") -> list[str]:
    """When the residual test rejects every candidate that could be preferred: the test
    cannot tell the structures apart, so the ranking rests on the information criterion
    alone. Empty otherwise."""
    usable = [v for v in verdicts if v.usable]
    if not usable or not all(v.residual_rejected for v in usable):
        return []
    return [
        f"**The residual test rejects every candidate** ({len(usable)} of {len(verdicts)} "
        "usable): it cannot tell these structures apart, and each candidate's intervals "
        "cover its best approximation, not the physical values. The ranking rests on what "
        f"can still discriminate, {rule.upper()} on the estimation runs; validation fit % is "
        "shown beside it and never used to choose.",
    ]


def preferred_plausible(scores: Sequence, verdicts: Sequence[CandidateVerdict], rule="aic"):
    """The score with the lowest `rule` criterion among the usable candidates (valid fit,
    physically plausible values), matched to `verdicts` by name; None if none is usable."""
    usable = {v.name for v in verdicts if v.usable}
    ok = [
        s for s in scores if s.name in usable and s.valid and math.isfinite(getattr(s, rule))
    ]  # fmt: skip
    return min(ok, key=lambda s: getattr(s, rule)) if ok else None
