"""Population model across devices: shared, per-device and random-effect parameters (issue 19).

Method: a **two-stage estimator with measurement-error correction** (the normal-normal
random-effects model of meta-analysis, fitted by restricted maximum likelihood).

Stage 1 fits every device on its own (`greybox._estimate.batch.fit_batch`): an estimate
theta_d and its standard error se_d per device and parameter. Stage 2, per parameter declared

- ``"random"``: on the log scale, x_d = log theta_d, s_d = se_d / theta_d (delta method),
  x_d = mu + eta_d + eps_d, eta_d ~ N(0, omega^2) (the population: log-normal with median
  exp(mu) and log-sd omega), eps_d ~ N(0, s_d^2) (stage-1 estimation error, taken as known).
  mu and omega are estimated by REML; the measurement error is thus removed from the spread
  (the raw spread of the estimates, sqrt(omega^2 + s^2), would overstate the population's).
  Standard errors: mu from the weights 1 / (omega^2 + s_d^2); omega from the observed REML
  information of log omega (delta method back to omega). Each device's standardised random
  effect is leave-one-out: z_d = (x_d - mu_(-d)) / sqrt(omega_(-d)^2 + s_d^2 + se(mu_(-d))^2),
  so a device far off cannot hide by inflating the spread it is judged against;
- ``"shared"``: the same value for every device (omega = 0): the precision-weighted mean on
  the log scale with Cochran's Q test of that homogeneity (a small p-value says the data
  contradict sharing);
- ``"fixed"``: a per-device value, reported as fitted (no pooling).

A device is flagged when |z_d| exceeds `z_limit` (3 sd, read on a Student-t with D - 2
degrees of freedom: `z_threshold`) for any random parameter, when the sum of its squared z
over the random parameters exceeds the chi-square 99.9 % quantile with that many degrees of
freedom, when its fit is not valid, or when its residual noise scale is a robust outlier
among the devices (|log sigma - median| > `z_limit` x 1.4826 MAD and a factor > 1.5 off).

Assumptions (stated in `PopulationFit.method`): stage-1 estimates are approximately normal on
the log scale with accurate standard errors; devices are independent; random effects of
different parameters are independent (diagonal Omega; their empirical correlation is
reported, not modelled); the population is log-normal. With few devices (< ~10) omega is
poorly determined and the prediction band uses a Student-t quantile with D - 1 degrees of
freedom.

A new device: its parameter is predicted at the population median exp(mu), with the 95 %
band exp(mu +- t * sqrt(omega^2 + se(mu)^2)) (the population spread plus the uncertainty of
the median).

Pure: arrays and results in, dataclasses out.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence

import numpy as np
from scipy import optimize, stats

KINDS = ("shared", "fixed", "random")
Z_LIMIT = 3.0
NOISE_RATIO = 1.5  # a device's noise scale is flagged only when this far from the median too
METHOD = (
    "two-stage: per-device fits, then a normal-normal random-effects model on the log scale "
    "fitted by REML with the stage-1 standard errors as known measurement error "
    "(assumes log-normal population, approximately normal stage-1 estimates with accurate "
    "standard errors, independent devices, independent random effects across parameters)"
)


@dataclasses.dataclass(frozen=True)
class PopulationParameter:
    """One parameter across devices.

    - `kind`: "shared", "fixed" or "random"; `values`, `se`: per device (SI), stage 1.
    - `median`, `median_se`: population median exp(mu) [SI] and its standard error (shared:
      the common value); `log_mu`, `log_mu_se`.
    - `omega`, `omega_se`: spread (sd of log theta) and its standard error (0 / NaN unless
      random); `cv`: the population's coefficient of variation sqrt(exp(omega^2) - 1).
    - `raw_log_sd`: the sd of the stage-1 log estimates (spread without the correction).
    - `z`: per device, leave-one-out standardised random effect (random), or the
      standardised deviation from the common value (shared); NaN for fixed.
    - `shrunk`: empirical-Bayes per-device values (random), else the stage-1 values.
    - `new_device`: (median, lower 95 %, upper 95 %) predicted for a new device [SI].
    - `q`, `q_p`: Cochran's Q of homogeneity and its p-value (a small p contradicts sharing).
    """

    name: str
    kind: str
    devices: tuple
    values: np.ndarray
    se: np.ndarray
    median: float
    median_se: float
    log_mu: float
    log_mu_se: float
    omega: float
    omega_se: float
    cv: float
    raw_log_sd: float
    z: np.ndarray
    shrunk: np.ndarray
    new_device: tuple
    q: float
    q_p: float


@dataclasses.dataclass(frozen=True)
class PopulationFit:
    """The population: `parameters` (name -> `PopulationParameter`), per-device `flags`
    (device -> list of reasons; empty list = belongs), `chi2` per device (sum of squared z
    over the random parameters) with its `chi2_limit`, the log-scale `random_correlation`
    (empirical, of the shrunk random effects; names in `random_names`),
    `expected_chance_flags` (how many devices of a true population the parameter tests flag
    by chance: with hundreds of devices a few flags are expected) and `method`."""

    devices: tuple
    parameters: dict
    flags: dict
    chi2: dict
    chi2_limit: float
    random_names: tuple
    random_correlation: np.ndarray
    expected_chance_flags: float = float("nan")
    method: str = METHOD

    @property
    def outliers(self) -> list:
        return [d for d, reasons in self.flags.items() if reasons]

    def new_device(self) -> dict:
        """{parameter: (median, lower 95 %, upper 95 %)} predicted for a device not yet seen
        (random: the population; shared: the common value with its interval; fixed: NaN)."""
        return {k: p.new_device for k, p in self.parameters.items()}


def z_threshold(z_limit: float, n_devices: int) -> float:
    """|z| beyond which a device is flagged: the normal tail of `z_limit` (3 sd: two-sided
    p = 0.0027) read on a Student-t with n - 2 degrees of freedom (the leave-one-out
    population is estimated from n - 1 devices), so few devices do not over-flag."""
    p = stats.norm.cdf(z_limit)
    return float(stats.t.ppf(p, max(n_devices - 2, 1)))


def _reml_negloglik(log_omega, x, s2):
    w = 1.0 / (np.exp(2 * log_omega) + s2)
    mu = np.sum(w * x) / np.sum(w)
    return 0.5 * (np.sum(np.log(1.0 / w)) + np.log(np.sum(w)) + np.sum(w * (x - mu) ** 2))


def random_effects(x, s) -> tuple[float, float, float, float]:
    """REML fit of x_d ~ N(mu, omega^2 + s_d^2): (mu, se(mu), omega, se(omega)).

    omega is searched on log scale in [1e-8, 10 * range]; at the lower end (no detectable
    spread beyond the measurement error) omega is reported 0 with NaN standard error."""
    x, s = np.asarray(x, float), np.asarray(s, float)
    s2 = s**2
    span = max(float(np.ptp(x)), float(np.median(s)), 1e-12)
    lo, hi = np.log(1e-8 * span), np.log(10 * span)
    res = optimize.minimize_scalar(
        _reml_negloglik,
        bounds=(lo, hi),
        args=(x, s2),
        method="bounded",
        options={"xatol": 1e-10},
    )
    lw = float(res.x)
    omega = float(np.exp(lw))
    w = 1.0 / (omega**2 + s2)
    mu = float(np.sum(w * x) / np.sum(w))
    mu_se = float(1.0 / np.sqrt(np.sum(w)))
    if lw < lo + 1e-3 * (hi - lo) or omega < 1e-6 * span:
        return mu, mu_se, 0.0, float("nan")
    h = 1e-3
    f0 = _reml_negloglik(lw, x, s2)
    d2 = (_reml_negloglik(lw + h, x, s2) - 2 * f0 + _reml_negloglik(lw - h, x, s2)) / h**2
    se_log = 1.0 / np.sqrt(d2) if d2 > 0 else float("nan")
    return mu, mu_se, omega, float(omega * se_log)


def _loo_z(x, s) -> np.ndarray:
    n = x.size
    z = np.full(n, np.nan)
    if n < 3:
        return z
    for d in range(n):
        keep = np.arange(n) != d
        mu, mu_se, om, _ = random_effects(x[keep], s[keep])
        z[d] = (x[d] - mu) / np.sqrt(om**2 + s[d] ** 2 + mu_se**2)
    return z


def population_fit(
    devices: Sequence[str],
    values: Mapping[str, Sequence[float]],
    standard_errors: Mapping[str, Sequence[float]],
    kinds: Mapping[str, str],
    *,
    valid: Sequence[bool] | None = None,
    noise: Sequence[float] | None = None,
    z_limit: float = Z_LIMIT,
    exclude_flagged: bool = True,
) -> PopulationFit:
    """Stage 2 of the population model from per-device estimates.

    **Arguments:**
    - `devices`: device names (D); `values[name]`, `standard_errors[name]`: (D,) stage-1
      estimates [SI, > 0 for shared/random] and standard errors.
    - `kinds[name]`: "shared", "fixed" or "random" for each parameter in `values`.
    - `valid`: per device, whether its stage-1 fit is usable (invalid ones are flagged and
      left out of the population); `noise`: per device residual noise scale (flagged when a
      robust outlier).
    - `exclude_flagged`: after flagging, re-fit the population without the flagged devices
      (their z stays leave-one-out against the others).

    **Returns:** a `PopulationFit`.
    """
    devices = tuple(devices)
    n = len(devices)
    unknown = {k: v for k, v in kinds.items() if v not in KINDS}
    if unknown:
        raise ValueError(f"kinds: {unknown} unknown; use {KINDS}")
    missing = [k for k in kinds if k not in values or k not in standard_errors]
    if missing:
        raise ValueError(f"values: no per-device estimates for {missing}")
    flags: dict = {d: [] for d in devices}
    ok = np.ones(n, bool) if valid is None else np.asarray(valid, bool)
    for d, good in zip(devices, ok):
        if not good:
            flags[d].append("fit not valid")
    if noise is not None:
        ls = np.log(np.asarray(noise, float))
        med = np.median(ls[ok])
        mad = 1.4826 * np.median(np.abs(ls[ok] - med))
        if mad > 0:
            zn = (ls - med) / mad
            for d, zz, dl in zip(devices, zn, ls - med):
                if abs(zz) > z_limit and abs(dl) > np.log(NOISE_RATIO):
                    flags[d].append(
                        f"residual noise scale x{np.exp(dl):.2f} the median device "
                        f"({zz:+.1f} robust sd)"
                    )

    def usable(name):
        v = np.asarray(values[name], float)
        s = np.asarray(standard_errors[name], float)
        good = ok & np.isfinite(v) & np.isfinite(s) & (v > 0) & (s > 0)
        return v, s, good

    # first pass: leave-one-out z for every random parameter on the usable devices
    z_of = {}
    for name, kind in kinds.items():
        v, s, good = usable(name)
        if kind in ("random", "shared") and np.sum(good) < 2:
            raise ValueError(f"{name}: fewer than two devices with a usable estimate")
        if kind == "random":
            x, sl = np.log(v[good]), s[good] / v[good]
            z = np.full(n, np.nan)
            z[good] = _loo_z(x, sl)
            z_of[name] = z
            limit = z_threshold(z_limit, int(np.sum(good)))
            for d, zz in zip(devices, z):
                if np.isfinite(zz) and abs(zz) > limit:
                    flags[d].append(f"{name}: random effect {zz:+.1f} sd from the population")
    random_names = tuple(k for k, v in kinds.items() if v == "random")
    chi2, chi2_limit = {}, float("nan")
    if random_names:
        chi2_limit = float(stats.chi2.ppf(0.999, len(random_names)))
        zz = np.array([z_of[k] for k in random_names])
        for i, d in enumerate(devices):
            c = float(np.sum(zz[:, i] ** 2))
            chi2[d] = c
            if (
                np.isfinite(c)
                and c > chi2_limit
                and not any("random effect" in f for f in flags[d])
            ):
                flags[d].append(f"chi-square {c:.1f} > {chi2_limit:.1f} over {random_names}")
    member = np.array([not flags[d] for d in devices]) if exclude_flagged else ok.copy()

    params, shrunk_re = {}, {}
    for name, kind in kinds.items():
        v, s, good = usable(name)
        use = good & member
        if kind == "fixed":
            params[name] = PopulationParameter(
                name,
                kind,
                devices,
                v,
                s,
                float("nan"),
                float("nan"),
                float("nan"),
                float("nan"),
                float("nan"),
                float("nan"),
                float("nan"),
                float("nan"),
                np.full(n, np.nan),
                v,
                (float("nan"),) * 3,
                float("nan"),
                float("nan"),
            )
            continue
        x, sl = np.log(v[use]), s[use] / v[use]
        raw_sd = float(np.std(x, ddof=1)) if x.size > 1 else float("nan")
        w0 = 1.0 / sl**2
        mu0 = float(np.sum(w0 * x) / np.sum(w0))
        q = float(np.sum(w0 * (x - mu0) ** 2))
        q_p = float(stats.chi2.sf(q, x.size - 1))
        tq = float(stats.t.ppf(0.975, max(x.size - 1, 1)))
        if kind == "shared":
            mu, mu_se, om, om_se = mu0, float(1 / np.sqrt(np.sum(w0))), 0.0, float("nan")
            xall, sall = np.log(np.where(v > 0, v, np.nan)), s / v
            z = (xall - mu) / np.sqrt(sall**2 + mu_se**2)
            shrunk = np.full(n, np.exp(mu))
            band = (np.exp(mu), np.exp(mu - 1.959964 * mu_se), np.exp(mu + 1.959964 * mu_se))
        else:
            mu, mu_se, om, om_se = random_effects(x, sl)
            z = z_of[name]
            xall, sall = np.log(np.where(v > 0, v, np.nan)), s / v
            k = om**2 / (om**2 + sall**2)
            shrunk = np.exp(mu + k * (xall - mu))
            shrunk_re[name] = np.where(use, np.log(shrunk) - mu, np.nan)
            half = tq * np.sqrt(om**2 + mu_se**2)
            band = (np.exp(mu), np.exp(mu - half), np.exp(mu + half))
        params[name] = PopulationParameter(
            name,
            kind,
            devices,
            v,
            s,
            float(np.exp(mu)),
            float(np.exp(mu) * mu_se),
            mu,
            mu_se,
            om,
            om_se,
            float(np.sqrt(np.expm1(om**2))),
            raw_sd,
            z,
            shrunk,
            tuple(float(b) for b in band),
            q,
            q_p,
        )
    if len(random_names) > 1:
        m = np.array([shrunk_re[k] for k in random_names])
        m = m[:, np.all(np.isfinite(m), axis=0)]
        if m.shape[1] > 2 and np.all(np.std(m, axis=1) > 0):
            corr = np.corrcoef(m)
        else:
            corr = np.full((len(random_names),) * 2, np.nan)
    else:
        corr = np.ones((len(random_names),) * 2)
    # devices of a true log-normal population flagged by chance on their parameters (the
    # per-parameter two-sided tail beyond z_limit, and the chi-square 0.1 % tail)
    tail = 2 * stats.norm.sf(z_limit)
    stay = (1 - tail) ** len(random_names) * (0.999 if len(random_names) > 1 else 1.0)
    expected = float(np.sum(ok) * (1 - stay))
    return PopulationFit(devices, params, flags, chi2, chi2_limit, random_names, corr, expected)


def population_from_batch(results: Mapping, kinds: Mapping[str, str], **kwargs) -> PopulationFit:
    """`population_fit` from per-device `FitResult`s (`BatchResult.results`): each named
    parameter's value and headline standard error; `valid` and the noise scale (first output)
    come from the fits."""
    devices = list(results)
    values = {k: [results[d].estimate(k).value for d in devices] for k in kinds}
    ses = {k: [results[d].estimate(k).se for d in devices] for k in kinds}
    valid = [bool(results[d].valid) for d in devices]
    noise = [float(np.atleast_1d(results[d].sigma)[0]) for d in devices]
    kwargs.setdefault("valid", valid)
    kwargs.setdefault("noise", noise)
    return population_fit(devices, values, ses, kinds, **kwargs)
