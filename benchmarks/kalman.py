"""Continuous-discrete Kalman likelihood: JAX value-and-gradient vs a plain numpy filter loop.

Default mode: a 3-state thermal model (two nodes with process noise on the heated one, plus a
random-walk ambient), 2 outputs, 2,000 irregular frames (0.5-1.5 s apart, 3 % of the values
dropped) and a heater switching between frames (every 10-60 s), 8 parameters in log space.
Times `jax.jit(jax.value_and_grad(log-likelihood))` after warm-up (best of 5 runs of 10 calls)
against a plain numpy/scipy filter that computes the value alone (Van Loan with
`scipy.linalg.expm` on every step, BLAS limited to one thread, best of 3). Both see the
same data and agree to ~1e-15.
Target: speedup = numpy_loglik_s / loglik_grad_s >= 3.

Also (`ekf_speed`): the extended Kalman filter's -log L and gradient on the shipped TCLab
two-heater record (the board with radiation, 600 frames, 12 parameters), `ekf_grad_over_value`
the gradient's cost in values, both evaluated as the fit's solver does (in its loop).
2026-11-28 (2 cores): value+gradient 102 -> 74 ms once the discretisation's doubling branch
was checkpointed and its Van Loan matrix concatenated from blocks; the same numbers to the
last bit; the fit's solve (`likelihood._newton`, 69 steps) 9.7 -> 7.2 s warm, and a
`greybox fit` of that folder with process noise 16.0 -> 12.6 s.

`--coverage N`: N replicates of the thermal RC device with a random-walk ambient (the model of
tests/test_kalman.py; 400 frames, fixed design, new noise per replicate) fitted by maximum
likelihood; reports the fraction of 95 % intervals that contain the truth, per parameter
(target 0.90-0.98), and how often the innovations pass the Ljung-Box test (p > 0.01).

`--coverage-device N`: the same through the device adapter (`greybox.fit` with `ProcessNoise` on the
built-in linear two-heater `tclab` device with process noise on the heater nodes and a
random-walk ambient shared by both sensors, 9 parameters); each replicate's record (600
irregular frames unless `--frames N`, dropped frames, a new design and new noise per seed)
comes from the independent numpy exact-discretisation simulator of
tests/test_stochastic_device.py. Reports
per parameter the fraction of the fit's 95 % intervals (`ParameterEstimate.ci95`: normal in
the fitted coordinates, log scale for the intensities and sds) that contain the truth, with
a Clopper-Pearson 95 % interval of that fraction (the fit's central-difference Hessian is
checked against forward-over-forward AD in tests/test_stochastic_device.py).

Last line: one JSON object. Run: .venv/bin/python benchmarks/kalman.py [--coverage 100]
[--coverage-device 100 [--frames 600]]
"""

import jax

jax.config.update("jax_enable_x64", True)

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import scipy.linalg as sla  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

from greybox._estimate.stochastic_fit import fit_stochastic  # noqa: E402  (the LinearGaussianSDE estimator)
from greybox.stochastic import FilterGrid, LinearGaussianSDE, log_likelihood  # noqa: E402

# ------------------------------------------------------------------------------------------
# speed: 3 states, 2 outputs, 2,000 frames
# ------------------------------------------------------------------------------------------

NAMES = ("c1_J_per_K", "c2_J_per_K", "g1_W_per_K", "g12_W_per_K", "q_node_K2_per_s",
         "q_ambient_K2_per_s", "sigma1_K", "sigma2_K")  # fmt: skip
THETA = np.array([20.0, 8.0, 0.5, 0.3, 1e-3, 1e-3, 0.05, 0.08])


SMOKE_HELP = "smallest setting (a few seconds): checks that the script still runs"

def thermal_matrices(theta):
    """(A, B, Qc, C, R) of the two-node model; works on numpy and jax arrays alike."""
    xp = jnp if isinstance(theta, jax.Array) else np
    c1, c2, g1, g12, q_node, q_amb, s1, s2 = (theta[i] for i in range(8))
    zero = xp.zeros(())
    A = xp.stack(
        [
            xp.stack([-(g1 + g12) / c1, g12 / c1, g1 / c1]),
            xp.stack([g12 / c2, -g12 / c2, zero]),
            xp.stack([zero, zero, zero]),
        ]
    )
    B = xp.stack([1.0 / c1, zero, zero])[:, None]
    Qc = xp.diag(xp.stack([q_node, zero, q_amb]))
    C = xp.asarray([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    R = xp.diag(xp.stack([s1**2, s2**2]))
    return A, B, Qc, C, R


X0 = np.array([0.0, 0.0, 0.0])
P0 = np.diag([0.01, 0.01, 0.01])


def make_record(n_frames=2000, seed=0):
    """Irregular frames, switching heater, data from an exact simulation of the model."""
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.5, 1.5, n_frames))
    bt = np.concatenate([[0.0], np.cumsum(rng.uniform(10.0, 60.0, n_frames))])
    bt = bt[bt < t[-1]]
    lv = rng.uniform(0.0, 2.0, bt.size)  # W
    A, B, Qc, C, R = thermal_matrices(THETA)
    n = 3
    pts = np.unique(np.concatenate([[0.0], bt[(bt > 0) & (bt < t[-1])], t]))
    x = rng.multivariate_normal(X0, P0)
    out = {}
    for a, b in zip(pts[:-1], pts[1:]):
        u = lv[np.searchsorted(bt, a, side="right") - 1]
        Ad, Bd, Qd = van_loan_numpy(A, B, Qc, b - a)
        x = Ad @ x + Bd[:, 0] * u + rng.multivariate_normal(np.zeros(n), Qd, method="eigh")
        out[b] = C @ x
    y = np.array([out[tk] for tk in t]) + rng.normal(size=(n_frames, 2)) * np.sqrt(np.diag(R))
    y[rng.random(y.shape) < 0.03] = np.nan
    return t, bt, lv, y


def van_loan_numpy(A, B, Qc, h):
    n, p = B.shape
    M = np.zeros((2 * n + p, 2 * n + p))
    M[:n, :n], M[:n, n : 2 * n] = -A, Qc
    M[n : 2 * n, n : 2 * n], M[2 * n :, n : 2 * n] = A.T, B.T
    E = sla.expm(M * h)
    Ad = E[n : 2 * n, n : 2 * n].T
    Qd = Ad @ E[:n, n : 2 * n]
    return Ad, E[2 * n :, n : 2 * n].T, 0.5 * (Qd + Qd.T)


def numpy_log_likelihood(theta, t, bt, lv, y):
    """A plain numpy filter: step through switches and frames, Van Loan on every step."""
    A, B, Qc, C, R = thermal_matrices(theta)
    m, P, ll = X0.copy(), P0.copy(), 0.0
    pts = np.unique(np.concatenate([[0.0], bt[(bt > 0) & (bt < t[-1])], t]))
    frame = {tk: k for k, tk in enumerate(t)}
    for a, b in zip(pts[:-1], pts[1:]):
        u = lv[np.searchsorted(bt, a, side="right") - 1]
        Ad, Bd, Qd = van_loan_numpy(A, B, Qc, b - a)
        m = Ad @ m + Bd[:, 0] * u
        P = Ad @ P @ Ad.T + Qd
        k = frame.get(b)
        if k is None:
            continue
        ok = np.isfinite(y[k])
        if not ok.any():
            continue
        H = C[ok]
        S = H @ P @ H.T + R[np.ix_(ok, ok)]
        L = np.linalg.cholesky(S)
        v = y[k][ok] - H @ m
        W = sla.solve_triangular(L, np.column_stack([H @ P, v]), lower=True)
        w = W[:, -1]
        W = W[:, :-1]
        m = m + W.T @ w
        P = P - W.T @ W
        ll += -0.5 * w @ w - np.log(np.diag(L)).sum() - 0.5 * ok.sum() * np.log(2 * np.pi)
    return ll


def speed(n_frames=2000, repeats=5):
    t, bt, lv, y = make_record(n_frames)
    grid = FilterGrid(t, bt, lv, t0_s=0.0)
    yj = jnp.asarray(y)

    def loglik(log_theta):
        A, B, Qc, C, R = thermal_matrices(jnp.exp(log_theta))
        return log_likelihood(LinearGaussianSDE(A, B, Qc, C, R, X0, P0), grid, yj)

    vg = jax.jit(jax.value_and_grad(loglik))
    log_theta = jnp.log(jnp.asarray(THETA))
    c0 = time.process_time()
    jax.block_until_ready(vg(log_theta))
    compile_s = time.process_time() - c0
    best, cpu = float("inf"), float("inf")
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        for _ in range(10):
            value, grad = jax.block_until_ready(vg(log_theta))
        best = min(best, (time.perf_counter() - t0) / 10)
        cpu = min(cpu, (time.process_time() - c0) / 10)
    np_best, np_cpu = float("inf"), float("inf")
    with threadpool_limits(1):  # multithreaded BLAS on 7x7 matrices only slows numpy down
        for _ in range(min(3, repeats)):
            t0, c0 = time.perf_counter(), time.process_time()
            np_value = numpy_log_likelihood(THETA, t, bt, lv, y)
            np_best = min(np_best, time.perf_counter() - t0)
            np_cpu = min(np_cpu, time.process_time() - c0)
    rel = abs(float(value) - np_value) / abs(np_value)
    print(
        f"{t.size} frames, {grid.n_steps} ZOH steps (frames + heater switches), 3 states, "
        f"2 outputs, {int(np.isnan(y).sum())} dropped values, 8 parameters; "
        f"{os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}"
    )
    print(f"log-likelihood JAX {float(value):.10f}, numpy {np_value:.10f} (rel. diff {rel:.1e})")
    print(
        f"JAX value+gradient (jit, warm): {best * 1e3:8.2f} ms wall, {cpu * 1e3:8.2f} ms CPU "
        f"(first call {compile_s:.1f} s CPU)"
    )
    print(
        f"numpy value only (1 thread)   : {np_best * 1e3:8.2f} ms wall, {np_cpu * 1e3:8.2f} ms CPU"
    )
    print(
        f"speedup: {np_best / best:.1f}x wall, {np_cpu / cpu:.1f}x CPU (target >= 3; on a shared "
        "machine the wall clock includes waiting for a core)"
    )
    return dict(
        loglik_grad_s=round(best, 6),
        numpy_loglik_s=round(np_best, 6),
        speedup=round(np_best / best, 2),
        speedup_cpu=round(np_cpu / cpu, 2),
        loglik_rel_diff=float(f"{rel:.2e}"),
        n_frames=int(t.size),
        n_steps=int(grid.n_steps),
    )


# ------------------------------------------------------------------------------------------
# coverage: the RC device with a random-walk ambient (as in tests/test_kalman.py)
# ------------------------------------------------------------------------------------------

START = dict(tau_s=15.0, gain_K_per_W=1.5, q_ambient_K2_per_s=1e-2, sigma_K=0.3, ambient0_K=0.0)


def _tests_module(name: str):
    """A module of tests/: the devices, truths and independent numpy simulators the tests use."""
    import importlib
    import sys
    from pathlib import Path

    tests = str(Path(__file__).resolve().parents[1] / "tests")
    if tests not in sys.path:
        sys.path.insert(0, tests)
    return importlib.import_module(name)


def coverage(n_reps):
    rc = _tests_module("test_kalman")  # the RC device with a random-walk ambient
    t, bt, lv = rc.rc_design(0)
    grid = FilterGrid(t, bt, lv, t0_s=0.0)
    zs, white, failed, times = [], [], 0, []
    c0 = time.perf_counter()
    for rep in range(n_reps):
        y = rc.rc_simulate(t, bt, lv, seed=1000 + rep)
        t0 = time.perf_counter()
        res = fit_stochastic(rc.rc_build, START, [(grid, y)], positive=rc.POSITIVE, throw=False)
        times.append(time.perf_counter() - t0)
        if not (res.converged and res.hessian_positive_definite):
            failed += 1
            continue
        zs.append([res.z_scores(rc.TRUE)[k] for k in rc.TRUE])
        white.append(res.records[0].whiteness[0].p_value > 0.01)
        if (rep + 1) % 10 == 0:
            print(f"  {rep + 1} replicates, {time.perf_counter() - c0:.0f} s", flush=True)
    zs = np.array(zs)
    cover = {k: float(np.mean(np.abs(zs[:, i]) < 1.959964)) for i, k in enumerate(rc.TRUE)}
    total = time.perf_counter() - c0
    print(
        f"coverage study: {n_reps} replicates, {len(zs)} converged with a positive-definite "
        f"Hessian ({failed} not), {total:.0f} s in all (first fit {times[0]:.1f} s with "
        f"compilation, median {np.median(times):.2f} s)"
    )
    print("parameter             95% coverage   mean z   sd z   (intervals in fitted coords)")
    for i, k in enumerate(rc.TRUE):
        print(f"  {k:20s}  {cover[k]:10.2f}   {zs[:, i].mean():+7.2f}  {zs[:, i].std():5.2f}")
    print(f"innovations white (Ljung-Box p > 0.01): {np.mean(white):.2f} of the fits")
    return dict(
        coverage_replicates=n_reps,
        coverage_failed=failed,
        coverage=cover,
        whiteness_pass=float(np.mean(white)),
        coverage_s=round(total, 1),
    )


def _binomial_ci(k: int, n: int) -> tuple:
    from scipy.stats import binomtest

    ci = binomtest(int(k), int(n)).proportion_ci(confidence_level=0.95, method="exact")
    return float(ci.low), float(ci.high)


def coverage_device(n_reps, n_frames: int = 600):
    import greybox

    T = _tests_module("test_stochastic_device")  # the independent numpy simulator and truth

    truth = T.TRUTH | T.NOISE
    names = list(truth)
    inside, zs, white, failed, times = [], [], [], 0, []
    c0 = time.perf_counter()
    for rep in range(n_reps):
        with threadpool_limits(1):
            data = T.simulate_truth(seed=2000 + rep, n=n_frames)
        sd = T.cli_model()
        free = T.physical_free() + greybox.stochastic.noise_parameters(sd, T.UNITS)
        t0 = time.perf_counter()
        res = greybox.fit(sd, [data], free, noise=greybox.ProcessNoise(sd.structure), n_starts=1)
        times.append(time.perf_counter() - t0)
        cov_ok = np.all(np.isfinite(np.diag(res.covariance_raw)))
        if res.status != "converged" or not cov_ok:
            failed += 1
            print(f"  replicate {rep}: {res.status} ({res.message}); left out", flush=True)
            continue
        est = {p.path: p for p in res.parameters}
        inside.append([est[k].ci95[0] <= truth[k] <= est[k].ci95[1] for k in names])
        z = res.z_scores(truth)
        zs.append([z[k] for k in names])
        white.append(all(r.white for r in res.runs))
        if (rep + 1) % 10 == 0:
            print(f"  {rep + 1} replicates, {time.perf_counter() - c0:.0f} s", flush=True)
    inside, zs = np.array(inside), np.array(zs)
    n_ok = len(inside)
    total = time.perf_counter() - c0
    print(
        f"device-adapter coverage: {n_reps} replicates of the two-heater TCLab with heater "
        f"process noise and a shared ambient random walk ({n_frames} frames each), {n_ok} "
        f"converged ({failed} not), {total:.0f} s (first fit {times[0]:.1f} s with compilation, "
        f"median {np.median(times):.2f} s)"
    )
    print("parameter               95% coverage  [binomial 95% CI]    mean z   sd z")
    cover, cis = {}, {}
    for i, k in enumerate(names):
        hits = int(inside[:, i].sum())
        cover[k] = hits / n_ok
        cis[k] = _binomial_ci(hits, n_ok)
        print(
            f"  {k:22s}  {cover[k]:6.3f}  [{cis[k][0]:.3f}, {cis[k][1]:.3f}]   "
            f"{zs[:, i].mean():+6.2f}  {zs[:, i].std():5.2f}"
        )
    all_in = int(inside.sum())
    pooled = all_in / inside.size
    print(
        f"pooled over parameters: {pooled:.3f} (target 0.90-0.98); innovations white "
        f"(Ljung-Box p > 0.01, both outputs): {np.mean(white):.2f} of the fits"
    )
    return dict(
        device_coverage_replicates=n_reps,
        device_coverage_frames=n_frames,
        device_coverage_failed=failed,
        device_coverage=cover,
        device_coverage_ci95={k: [round(a, 4), round(b, 4)] for k, (a, b) in cis.items()},
        device_coverage_pooled=round(pooled, 4),
        device_whiteness_pass=float(np.mean(white)),
        device_coverage_s=round(total, 1),
    )


TCLAB = Path(__file__).resolve().parents[1] / "experiments" / "tclab" / "two_heaters"
TCLAB_NOISE = (  # the process-noise structure of experiments/tclab/stochastic.md
    '\n[noise]\nprocess = { heaters = [0, 1] }\ndisturbances = ["ambient_random_walk"]\n'
)


def ekf_speed(n_frames=600, repeats=3):
    """The extended Kalman filter's -log L and its gradient on a real record: the shipped
    TCLab two-heater folder (the board with radiation, so the filter is extended: 4 local
    linearisations per step, each a Van Loan discretisation) with the process noise of
    experiments/tclab/stochastic.md, its first `n_frames` estimation frames, at the start
    values, as `greybox.fit` evaluates them (its compile options). The gradient's cost in
    evaluations of the value alone (`ekf_grad_over_value`) is the figure that does not
    depend on the machine: reverse mode through the filter's scan."""
    import shutil
    import tempfile

    from greybox._compile import jit
    from greybox._estimate import likelihood as lik
    from greybox.io import load_experiment_set
    from greybox.io._noise_table import noise_model

    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "two_heaters"
        shutil.copytree(TCLAB, folder)
        for name in ("estimation.csv", "validation.csv"):
            lines = (folder / name).read_text().splitlines()
            (folder / name).write_text("\n".join(lines[: n_frames + 1]) + "\n")
        toml = folder / "experiment.toml"
        text = toml.read_text().split("# Candidate structures")[0]
        text = text.replace('method = "adaptive"\n', "").replace('loss = "l2"\n', "")
        toml.write_text(text.replace("[fit]\n", '[fit]\nnoise_model = "process"\n') + TCLAB_NOISE)
        fs = load_experiment_set(folder)
    model, noise, noise_free = noise_model(fs.noise, fs.model, fs.spec)
    su = lik.setup(model, fs.estimation, [*fs.free, *noise_free], noise)
    assert su.sd.use_ekf, "the board with radiation needs the extended filter"
    raw = jnp.asarray(su.raw0)
    calls = 5

    def in_a_loop(f):
        """`calls` evaluations of `f` inside one compiled loop, the objective an argument:
        as the fit's solver evaluates it (one pass of its while loop each; compiled at the
        top level of a program instead, XLA schedules the same gradient differently)."""

        def run(r, obj):
            def body(i, acc):
                out = f(obj, r + 1e-12 * i)
                return acc + jax.tree.leaves(out)[-1]

            return jax.lax.fori_loop(0, calls, body, jnp.zeros_like(r))

        return jit(run)

    value = in_a_loop(lambda obj, r: jnp.broadcast_to(obj.data_nll(r), r.shape))
    grad = in_a_loop(lambda obj, r: jax.value_and_grad(obj.data_nll)(r))
    jax.block_until_ready((value(raw, su.obj), grad(raw, su.obj)))

    def best_of(f):
        best = float("inf")
        for _ in range(repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(f(raw, su.obj))
            best = min(best, (time.perf_counter() - t0) / calls)
        return best

    v_s, g_s = best_of(value), best_of(grad)
    print(
        f"EKF (TCLab board with radiation, {n_frames} frames, {su.sd.n_states} states, "
        f"{raw.size} parameters): value {v_s * 1e3:.1f} ms, value+gradient {g_s * 1e3:.1f} ms "
        f"({g_s / v_s:.1f} values)"
    )
    return dict(
        ekf_value_s=round(v_s, 6), ekf_grad_s=round(g_s, 6), ekf_grad_over_value=round(g_s / v_s, 2)
    )


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--coverage", type=int, default=0, metavar="N", help="replicates")
    parser.add_argument(
        "--coverage-device", type=int, default=0, metavar="N",
        help="replicates (greybox.fit, ProcessNoise)",
    )
    parser.add_argument(
        "--frames", type=int, default=600, metavar="N", help="frames per --coverage-device record"
    )
    parser.add_argument("--smoke", action="store_true", help=SMOKE_HELP)
    args = parser.parse_args()
    out = speed(200, 1) if args.smoke else speed()
    out |= ekf_speed(60, 1) if args.smoke else ekf_speed()
    if args.coverage:
        out |= coverage(args.coverage)
    if args.coverage_device:
        out |= coverage_device(args.coverage_device, args.frames)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
