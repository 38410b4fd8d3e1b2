"""The headline verdict's logic: order of severity, exit status, weak identification and the
words compare uses. The fits it is applied to are in tests/test_plausibility.py (a chevron
simulated by scipy); here each rule is checked on stated inputs, including the numbers of
issue 25 (an interval 0.003 to 0.641 is not "identifiable")."""

from __future__ import annotations

import types

import numpy as np
import pytest

from greybox._estimate.verdict import (
    IMPLAUSIBLE,
    NOT_VALID,
    REJECTED,
    VALID,
    WEAK_FACTOR,
    CandidateVerdict,
    all_rejected_lines,
    headline,
    interval_factor,
    no_valid_candidate_lines,
    preferred_plausible,
    refined_verdict,
    standard_error_text,
)
from greybox._model.plausibility import PhysicalRange, implausible_values, parse_physical_ranges


def estimate(name, value, ci, verdict="identifiable", **kw):
    base = dict(name=name, path=name, unit="1", value=value, ci95=ci, verdict=verdict)
    base.update(experiment=None, bound=None, se_hac=np.nan, se_gauss_newton=np.nan)
    base.update(kw)
    return types.SimpleNamespace(**base)


def residuals(white: bool, q=(5.0,)):
    return types.SimpleNamespace(all_white=white, q=np.asarray(q))


def result(status="converged", valid=True, white=True, parameters=(), q=(5.0,)):
    return types.SimpleNamespace(
        status=status, valid=valid, message=status, residuals=residuals(white, q),
        parameters=tuple(parameters),
    )  # fmt: skip


def test_interval_factor_and_weak_verdict():
    # issue 25: a two-tank interval 0.003 to 0.641 spans a factor 214: weakly identified
    wide = estimate("k", 0.05, (0.003, 0.641))
    assert interval_factor(wide.ci95) == pytest.approx(0.641 / 0.003)
    assert refined_verdict(wide) == "weakly identified"
    assert refined_verdict(estimate("k", 1.0, (0.5, 4.9))) == "identifiable"  # factor 9.8
    assert refined_verdict(estimate("k", 1.0, (0.5, 5.1))) == "weakly identified"  # 10.2
    # an interval through zero has no factor (an offset is judged by its se, not a ratio)
    assert interval_factor((-0.1, 0.2)) is None
    assert refined_verdict(estimate("o", 0.05, (-0.1, 0.2))) == "identifiable"
    assert interval_factor((-4.0, -1.0)) == 4.0
    # other verdicts are kept
    assert refined_verdict(estimate("k", 1.0, (np.nan, np.nan), "at bound")) == "at bound"
    assert WEAK_FACTOR == 10.0


def test_headline_order_and_exit_status():
    ranges = {"a": PhysicalRange("a", "1", 0.3, 1.0)}
    ok = [estimate("a", 0.6, (0.55, 0.65))]
    bad = [estimate("a", 0.02, (0.017, 0.025))]
    h = headline(result(parameters=ok))
    assert (h.verdict, h.exit_status) == (VALID, 0) and "cover the physical values" in h.intervals
    h = headline(result(white=False, parameters=ok))
    assert (h.verdict, h.exit_status) == (REJECTED, 0)
    assert "best approximation within this structure" in h.intervals
    assert headline(result(white=False, parameters=ok), strict=True).exit_status == 1
    found = implausible_values(bad, ranges)
    h = headline(result(parameters=bad), found)
    assert (h.verdict, h.exit_status) == (IMPLAUSIBLE, 0) and "a = 0.02" in h.details[0]
    assert headline(result(parameters=bad), found, strict=True).exit_status == 1
    # both problems: named together, implausible first
    h = headline(result(white=False, parameters=bad), found)
    assert h.verdict == IMPLAUSIBLE and "not white" in h.text
    # not valid trumps everything, whatever strict says
    for status in ("at bound", "not converged", "diverged"):
        h = headline(result(status=status, valid=False, parameters=bad), found)
        assert (h.verdict, h.exit_status) == (NOT_VALID, 1)
        assert "mean nothing" in h.intervals
    # a local optimum whose best start is reported is valid (exit 0), and says so
    h = headline(result(status="local optimum", parameters=ok))
    assert h.verdict == VALID and any("best start" in d for d in h.details)
    # residual test impossible: valid, and the headline says it could not check
    h = headline(result(parameters=ok, q=(np.nan,)))
    assert h.verdict == VALID and "could not check" in h.intervals


def test_every_implausible_value_is_reported_together():
    table = [
        types.SimpleNamespace(path=p, unit="1", physical_range=r, description="", lower=None,
                              upper=None)
        for p, r in (("a", (0.3, 1.0)), ("b", (1.0, 2.0)), ("c", (None, 0.0)))
    ]  # fmt: skip
    from greybox._model.plausibility import physical_ranges

    ranges = physical_ranges(table, {"b": (0.0, 10.0)})
    est = [estimate("a", 0.1, (0, 1)), estimate("b", 5.0, (4, 6)), estimate("c", 3.0, (2, 4))]
    found = implausible_values(est, ranges)
    assert [f.path for f in found] == ["a", "c"]  # b's override accepts 5
    assert not implausible_values([estimate("a", float("nan"), (0, 1))], ranges)  # diverged
    assert [f.side for f in found] == ["below", "above"]
    assert ranges["b"].source == "experiment.toml"
    overrides, problems = parse_physical_ranges({"a": [0.5, "x"], "zz": [1, 2]}, table)
    assert overrides == {} and [k for k, _ in problems] == ["a", "zz"]
    overrides, problems = parse_physical_ranges({"a": [0.5, float("inf")]}, table)
    assert overrides == {"a": (0.5, None)} and not problems


def test_hac_wording_never_claims_to_allow_for_misfit_when_narrower():
    narrower = estimate("tau", 0.11, (0.109, 0.111), se_hac=0.0004, se_gauss_newton=0.0006)
    wider = estimate("tau", 0.11, (0.10, 0.12), se_hac=0.006, se_gauss_newton=0.002)
    text = standard_error_text(types.SimpleNamespace(se_method="hac", parameters=[narrower]))
    assert "narrower than the Gauss-Newton" in text and "allow for the autocorr" not in text
    text = standard_error_text(types.SimpleNamespace(se_method="hac", parameters=[wider]))
    assert "wider than the Gauss-Newton" in text and "not for the bias" in text


def _cv(name, verdict, *, at_bound=(), rejected=False, status="converged", implausible=()):
    head = headline(result(status=status, valid=verdict != NOT_VALID, white=not rejected))
    head = type(head)(verdict, head.text, head.intervals, (), head.exit_status, implausible)
    return CandidateVerdict(name, head, status, status, at_bound, rejected)


def test_compare_says_why_no_candidate_is_usable_and_what_to_change():
    vs = [
        _cv("one node", NOT_VALID, at_bound=(("alpha1", "lower", 0.003),), status="at bound"),
        _cv("lag", NOT_VALID, status="not converged"),
    ]
    lines = no_valid_candidate_lines(vs)
    assert "No candidate gave a valid" in lines[0]
    assert "alpha1 on its lower bound 0.003: lower that bound" in lines[2]
    assert "raise [fit] max_steps" in lines[3]
    assert not no_valid_candidate_lines([*vs, _cv("ok", VALID)])


def test_compare_says_when_the_residual_test_rejects_every_candidate():
    vs = [_cv("a", REJECTED, rejected=True), _cv("b", REJECTED, rejected=True)]
    lines = all_rejected_lines(vs, "bic")
    assert "rejects every candidate" in lines[0] and "BIC" in lines[0]
    assert "never used to choose" in lines[0]
    assert not all_rejected_lines([vs[0], _cv("c", VALID)])


def test_compare_never_prefers_an_implausible_candidate_with_the_lowest_aic():
    # the implausible candidate has the lowest AIC (and BIC), and one not valid the next:
    # the preferred one is the lowest-criterion candidate among the usable ones
    def score(name, aic, valid=True):
        return types.SimpleNamespace(name=name, aic=aic, bic=aic + 5.0, valid=valid)

    implausible = (types.SimpleNamespace(name="alpha", text="alpha = -3 < 0"),)
    vs = [
        _cv("too good", IMPLAUSIBLE, implausible=implausible),
        _cv("pinned", NOT_VALID, at_bound=(("alpha", "lower", 0.0),), status="at bound"),
        _cv("rejected", REJECTED, rejected=True),
        _cv("plain", VALID),
    ]
    scores = [score("too good", -500.0), score("pinned", -400.0, valid=False),
              score("rejected", -300.0), score("plain", -200.0)]  # fmt: skip
    assert preferred_plausible(scores, vs, "aic").name == "rejected"
    assert preferred_plausible(scores, vs, "bic").name == "rejected"
    assert preferred_plausible(scores[:2], vs[:2]) is None
    assert "physically implausible: alpha = -3 < 0" in no_valid_candidate_lines(vs[:2])[2]
