"""Many devices (issue 19): batched fits equal single fits, the population model recovers a
known population and flags a planted outlier, and a Dask batch survives a killed worker."""

import dataclasses
import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import greybox
from greybox._estimate.batch import bytes_per_item, chunk_size_for, device_from_spec, fit_batch
from greybox._estimate.population import population_fit, population_from_batch
from tests.helpers import backend_compiles

SPEC = greybox.get_device("chevron_laser")
M_PER_PX = 0.645e-6
MEDIAN = {"absorptance": 0.62, "thermal.tau_s": 0.045}
OMEGA = {"absorptance": 0.08, "thermal.tau_s": 0.15}
RUNS = [(10, 200), (20, 400), (30, 600)]  # mW, ms: three short runs per device
OUTLIER = 5  # this device's time constant is 2.5x its draw


def _devices(n, seed=9):
    rng = np.random.default_rng(seed)
    model = greybox.devices.with_camera(SPEC.model(), exposure_s=10e-3, m_per_px=M_PER_PX)
    waves = [
        greybox.PulseTrain(
            p * 1e-3, per * 1e-3, n_pulses=max(1, 1200 // per), delay_s=0.1, tail_s=0.2
        )
        for p, per in RUNS
    ]
    devices, truth = [], {}
    for k in range(n):
        vals = {p: MEDIAN[p] * np.exp(OMEGA[p] * rng.normal()) for p in MEDIAN}
        if k == OUTLIER:
            vals["thermal.tau_s"] *= 2.5
        dev = greybox.parameters.set_values(model, list(vals), list(vals.values()))
        exps = []
        for j, w in enumerate(waves):
            run = greybox.parameters.set_values(
                dev, ["camera.offset_m"], [(312 + rng.uniform(-4, 4)) * M_PER_PX]
            )
            e, _ = greybox.waveforms.record(
                run,
                w,
                name=f"r{j}",
                defects=greybox.waveforms.CameraDefects(noise_m=0.05e-6),
                seed=int(rng.integers(2**31)),
            )
            exps.append(e)
        devices.append(device_from_spec(SPEC, f"dev{k:02d}", exps, model=model))
        truth[f"dev{k:02d}"] = vals
    return devices, truth


@pytest.fixture(scope="module")
def batch():
    devices, truth = _devices(14)
    progress = []
    out = fit_batch(devices, SPEC.free_parameters(), progress=progress.append)
    return devices, truth, out, progress


def test_batch_equals_single_fit(batch):
    devices, _, out, progress = batch
    assert out.groups == 1 and out.n_calls == 2  # one compiled call for starts, one refit
    assert any("chunk 1/1" in line for line in progress)
    for d in devices[:2]:
        single = greybox.fit(d.model, d.experiments, d.free)
        b = out[d.name]
        assert b.status == single.status
        for p, q in zip(b.parameters, single.parameters):
            assert p.name == q.name and p.verdict == q.verdict
            assert abs(p.value - q.value) <= 1e-6 * abs(q.value)
            assert abs(p.se - q.se) <= 1e-6 * abs(q.se)
        np.testing.assert_allclose(b.sigma, single.sigma, rtol=1e-6)
        for run in single.fit_percent:
            np.testing.assert_allclose(b.fit_percent[run], single.fit_percent[run], rtol=1e-6)
    rows = out.table()
    assert [r["device"] for r in rows] == [d.name for d in devices]
    assert {"absorptance", "absorptance:se", "thermal.tau_s:verdict", "fit%[0]:mean"} <= set(
        rows[0]
    )


def test_chunk_size_respects_memory_budget(batch):
    devices, _, _, _ = batch
    from greybox._estimate.batch import _prepare

    prepared, _ = _prepare(
        devices[:1],
        SPEC.free_parameters(),
        None,
        "huber",
        1.5,
        4.0,
        None,
        None,
        0,
        (1e-8, 1e-10, 16384),
    )
    b = bytes_per_item(prepared[0].problem)
    assert 1e4 < b < 1e9
    assert chunk_size_for(b, 10 * b, 1000) == 10
    assert chunk_size_for(b, b / 2, 1000) == 1
    # evened out: two chunks of 16,384 rather than 29,000 and a padded 3,768
    assert chunk_size_for(b, 29000 * b, 32768, 65536) == 16384
    assert chunk_size_for(b, 256 * b, 1000, 256) == 250
    # padding free (a CPU): the largest power of two within the budget, whatever the work
    assert chunk_size_for(b, 1e6 * b, 3, 64, padding_free=True) == 64
    assert chunk_size_for(b, 10 * b, 1000, 64, padding_free=True) == 8
    assert chunk_size_for(b, b / 2, 3, 64, padding_free=True) == 1


def test_a_batch_of_another_size_reuses_the_solver_and_skips_its_padding(batch):
    """On a CPU every chunk has one size whatever the batch's (its padding items skipped),
    so a batch of 3 devices after the fixture's 14 compiles no solver, and each of its
    devices gets the fixture's result bit for bit (the same compiled solve)."""
    from greybox._platform import on_accelerator

    if on_accelerator():
        pytest.skip("an accelerator sizes chunks to the work (a padding item costs a solve)")
    devices, _, out, _ = batch
    with backend_compiles() as compiled:
        small = fit_batch(devices[3:6], SPEC.free_parameters())
    assert not [n for n in compiled if "_solve_many" in n], compiled
    assert small.chunk_size == out.chunk_size
    for d in devices[3:6]:
        np.testing.assert_array_equal(small[d.name].raw, out[d.name].raw)


def test_devices_built_block_by_block_give_the_one_block_results(batch, monkeypatch):
    """On a CPU the problems are built in blocks of devices while the first ones solve
    (`_build_blocks`); their schedules are padded jointly beforehand (`_plan`), so blocks of
    5 (three waves) compile no solver beyond the fixture's one block and give its results
    bit for bit (the same compiled solve of the same padded problem)."""
    from greybox._estimate import batch as _batch
    from greybox._platform import on_accelerator

    if on_accelerator():
        pytest.skip("an accelerator builds one block (its chunk is sized from all the work)")
    devices, _, out, _ = batch
    monkeypatch.setattr(
        _batch, "_build_blocks", lambda n, *_a: [range(a, min(a + 5, n)) for a in range(0, n, 5)]
    )
    with backend_compiles() as compiled:
        blocks = fit_batch(devices, SPEC.free_parameters())
    assert not [n for n in compiled if "_solve_many" in n], compiled
    assert blocks.groups == 1 and blocks.n_calls == 6  # three waves: starts and refits each
    for d in devices:
        a, b = blocks[d.name], out[d.name]
        np.testing.assert_array_equal(a.raw, b.raw)
        np.testing.assert_array_equal(a.covariance_raw, b.covariance_raw)
        np.testing.assert_array_equal(a.residuals.p_value, b.residuals.p_value)


def _with_runs(device, **changes):
    """`device` with `changes` made to every run."""
    runs = tuple(dataclasses.replace(e, **changes) for e in device.experiments)
    return dataclasses.replace(device, experiments=runs)


def _blanked(device):
    """`device` with every reading but each run's first dropped (NaN): 3 readings for 5
    parameters (two shared, an offset per run)."""
    runs = []
    for e in device.experiments:
        y = np.full_like(e.y, np.nan)
        y[0] = e.y[0]
        runs.append(dataclasses.replace(e, y=y))
    return dataclasses.replace(device, experiments=tuple(runs))


def _first_run_noisy(device):
    """`device` whose first run alone carries a per-frame noise level."""
    first, *rest = device.experiments
    first = dataclasses.replace(first, sigma=np.full_like(first.y, 1e-7))
    return dataclasses.replace(device, experiments=(first, *rest))


@pytest.mark.parametrize(
    "spoil, sigma, message",
    [
        (_blanked, None, "valid frames cannot determine"),
        (lambda d: _with_runs(d, settings={"thermal.no_such_m": 1.0}), None, "no_such_m"),
        (lambda d: d, -1.0, "noise scale must be > 0"),
        (_first_run_noisy, None, "per-frame noise level"),
    ],
    ids=["too few readings", "unknown setting", "negative sigma", "per-frame noise mixed"],
)
def test_a_bad_device_late_in_the_batch_is_refused_before_any_solve(
    batch, monkeypatch, spoil, sigma, message
):
    """Every device's input is checked before the first solve, as one `greybox.fit` each
    would check it, though the problems are built block by block while the first blocks solve
    (`_build_blocks`): a bad last device costs no work and says which device it is."""
    from greybox._estimate import batch as _batch

    devices, _, _, _ = batch
    monkeypatch.setattr(
        _batch, "_build_blocks", lambda n, *_a: [range(a, min(a + 5, n)) for a in range(0, n, 5)]
    )
    bad = spoil(devices[-1])
    sigmas = {bad.name: sigma} if sigma is not None else None
    progress = []
    with pytest.raises(ValueError, match=message) as err:
        fit_batch([*devices[:-1], bad], SPEC.free_parameters(), sigma=sigmas,
                  progress=progress.append)  # fmt: skip
    assert str(err.value).startswith(f"{bad.name}: ")
    assert not [line for line in progress if "done" in line], progress


def test_a_bad_device_is_refused_before_a_cluster_starts(batch, monkeypatch):
    """`fit_distributed` checks every device on the client as `fit_batch` would: a bad one is
    refused by name before any worker starts (not by a worker, after its retries)."""
    from greybox._estimate import distributed as dist

    def start_client(*_a, **_k):
        raise AssertionError("a cluster was started for a batch with a bad device")

    monkeypatch.setattr(dist, "start_client", start_client)
    devices, _, _, _ = batch
    bad = _blanked(devices[3])
    with pytest.raises(ValueError, match="valid frames cannot determine") as err:
        dist.fit_distributed([*devices[:3], bad], SPEC.free_parameters(), n_workers=1)
    assert str(err.value).startswith(f"{bad.name}: ")
    # the noise an `OutputError` carries is checked as `fit_batch` reads it
    with pytest.raises(ValueError, match="noise scale must be > 0") as err:
        dist.fit_distributed(devices[:3], SPEC.free_parameters(), n_workers=1,
                             noise=greybox.OutputError(sigma=-1e-7))  # fmt: skip
    assert str(err.value).startswith(f"{devices[0].name}: ")


def test_a_batch_pauses_the_cyclic_collector_and_restores_it(batch, monkeypatch):
    """The waves are assembled with the cyclic collector off (`greybox._collector`: its walks
    of a growing heap were 0.2-0.5 s of a 512-device batch); it is on again afterwards."""
    import gc

    from greybox._estimate import batch as _batch

    seen, assemble = [], _batch._assemble_wave

    def watched(*args):
        seen.append(gc.isenabled())
        return assemble(*args)

    monkeypatch.setattr(_batch, "_assemble_wave", watched)
    devices = batch[0]
    assert gc.isenabled()
    fit_batch(devices[:2], SPEC.free_parameters())
    assert seen and not any(seen)
    assert gc.isenabled()


def test_padding_items_are_skipped_on_a_cpu():
    """`map_over_items` with `active`: the items marked False run nothing (counted by a host
    callback inside the mapped function) and come back as zeros; the others are `fn`'s."""
    from greybox._platform import map_over_items, on_accelerator

    if on_accelerator():
        pytest.skip("vmapped, padding items run with the others")
    ran = []

    def fn(x, y):
        jax.debug.callback(lambda v: ran.append(float(v)), x)
        return {"sum": x + y.sum(), "scaled": 2.0 * y}

    x = jnp.array([1.0, 2.0, 3.0, 4.0])
    y = jnp.arange(12.0).reshape(4, 3) + 1.0
    out = jax.jit(lambda x, y, a: map_over_items(fn, x, y, active=a))(
        x, y, jnp.array([True, True, True, False])
    )
    jax.effects_barrier()
    assert sorted(ran) == [1.0, 2.0, 3.0]
    np.testing.assert_array_equal(out["sum"], [7.0, 17.0, 27.0, 0.0])
    np.testing.assert_array_equal(out["scaled"][:3], 2.0 * y[:3])
    np.testing.assert_array_equal(out["scaled"][3], 0.0)


def test_a_result_survives_pickling_whole(batch):
    # results cross processes by pickle (fit_distributed), their run models as leaves only
    import pickle

    import jax

    r = batch[2].results["dev00"]
    back = pickle.loads(pickle.dumps(r))
    for f in dataclasses.fields(r):
        a, b = getattr(r, f.name), getattr(back, f.name)
        assert jax.tree_util.tree_structure(a) == jax.tree_util.tree_structure(b), f.name
        for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b), strict=True):
            assert type(x) is type(y), f.name
            if isinstance(x, np.ndarray):
                np.testing.assert_array_equal(x, y, err_msg=f.name)
            else:
                assert repr(x) == repr(y), f.name
    assert len(back.experiment_models) == len(r.experiments) > 1
    assert all(type(m) is type(r.model) for m in back.experiment_models)
    np.testing.assert_array_equal(back.predict(1), r.predict(1))
    assert back.summary() == r.summary()


def test_distributed_chunks_fill_the_worker_budget_only_on_an_accelerator(batch):
    from greybox._estimate import batch as _batch
    from greybox._estimate.distributed import TASKS_PER_WORKER, plan

    devices = batch[0] * 800  # 11,200 devices over 4 workers, 1 GiB each
    free = SPEC.free_parameters()
    cpu = plan(devices, free, n_workers=4, memory_budget_bytes=1024**3)
    gpu = plan(devices, free, n_workers=4, memory_budget_bytes=1024**3, accelerator=True)
    b = gpu[2]
    # one solve after another on a CPU: chunks of at most 64, evened out over the devices a
    # task holds (2,800 a worker, TASKS_PER_WORKER tasks each); a vmapped chunk on a shared
    # accelerator: as many solves as a task holds and the worker's 1 GiB allows
    per_task = 2800 // TASKS_PER_WORKER
    assert cpu[0] == chunk_size_for(b, 1024**3, per_task, _batch.MAX_CHUNK) <= 64
    assert gpu[0] == chunk_size_for(b, 1024**3, per_task, _batch.MAX_CHUNK_ACCELERATOR)
    assert gpu[0] == min(per_task, 1024**3 // b)
    assert gpu[0] * b <= 1024**3 and gpu[1] % gpu[0] == 0 and cpu[1] % cpu[0] == 0


def test_local_workers_share_an_accelerator_without_taking_its_memory(monkeypatch):
    from greybox._estimate.distributed import worker_environment

    monkeypatch.delenv("XLA_PYTHON_CLIENT_PREALLOCATE", raising=False)
    monkeypatch.delenv("JAX_PLATFORMS", raising=False)
    assert worker_environment() == {"XLA_PYTHON_CLIENT_PREALLOCATE": "false"}
    assert worker_environment("cpu")["JAX_PLATFORMS"] == "cpu"
    monkeypatch.setenv("XLA_PYTHON_CLIENT_PREALLOCATE", "true")  # the user's own setting wins
    assert worker_environment() == {}


def test_a_cluster_returns_what_the_batch_returns(batch):
    pytest.importorskip("distributed")
    from greybox._estimate.distributed import fit_distributed, start_client

    devices, _, out, _ = batch
    client, cluster = start_client("local", n_workers=1, platform="cpu")
    try:
        dist = fit_distributed(devices[:6], SPEC.free_parameters(), client=client, n_workers=1)
    finally:
        client.close()
        cluster.close()
    assert list(dist.results) == [d.name for d in devices[:6]]
    assert len(dist.worker_s) > 1 and all(s > 0 for s in dist.worker_s)  # several tasks
    # each result holds its device's own runs, as the batch's do (they do not travel back)
    assert all(dist.results[d.name].experiments is d.experiments for d in devices[:6])
    for name, r in dist.results.items():
        np.testing.assert_allclose(r.raw, out.results[name].raw, rtol=1e-9)
        assert r.status == out.results[name].status
        np.testing.assert_allclose(r.predict(0), out.results[name].predict(0), rtol=1e-9)


def test_a_class_of_the_clients_main_travels_by_value(monkeypatch):
    # a notebook's or script's model class lives in its __main__, which a worker cannot
    # import: a payload that refers to it is pickled by value; anything else by reference
    import pickle
    import sys
    import types

    from greybox._estimate.distributed import _pickled

    main = types.ModuleType("__main__")
    monkeypatch.setitem(sys.modules, "__main__", main)
    main.NotebookDevice = type("NotebookDevice", (), {"__module__": "__main__", "k": 2.0})
    data = _pickled([main.NotebookDevice(), 1.0])
    del main.NotebookDevice  # as in a worker's own __main__
    device, x = pickle.loads(data)
    assert type(device).__name__ == "NotebookDevice" and device.k == 2.0 and x == 1.0
    assert _pickled((1.0, "x")) == pickle.dumps((1.0, "x"), protocol=4)


def test_a_worker_keeps_its_host_work_to_one_core(monkeypatch):
    # 15 Dask workers on 16 cores, each spreading its residual tests' shuffles over threads,
    # had them twice as slow as one process alone: a worker's task runs inside `one_core`
    from greybox import _platform
    from greybox._estimate.residuals import SHUFFLE_THREADS_MAX, shuffle_threads

    sixteen = lambda _pid: set(range(16))  # noqa: E731
    monkeypatch.setattr(_platform.os, "sched_getaffinity", sixteen, raising=False)
    assert shuffle_threads() == min(SHUFFLE_THREADS_MAX, 15) > 1
    with _platform.one_core():
        assert _platform.usable_cores() == 1 and shuffle_threads() == 1
    assert shuffle_threads() == min(SHUFFLE_THREADS_MAX, 15)


def test_population_recovers_median_spread_and_flags_outlier(batch):
    devices, truth, out, _ = batch
    kinds = {"absorptance": "random", "thermal.tau_s": "random"}
    pop = population_from_batch(out.results, kinds)
    assert pop.outliers == [f"dev{OUTLIER:02d}"]
    members = [d.name for d in devices if d.name not in pop.outliers]
    for path, p in pop.parameters.items():
        assert abs(p.log_mu - np.log(MEDIAN[path])) < 3 * p.log_mu_se
        assert abs(p.omega - OMEGA[path]) < 3 * p.omega_se
        # the spread of the 13 true values themselves (sampling varies it by ~20 %): the
        # measurement-error correction recovers it, the raw spread of the estimates overstates
        realised = np.std([np.log(truth[d][path]) for d in members], ddof=1)
        assert abs(p.omega - realised) < 3 * p.omega_se
        lo, hi = p.new_device[1:]
        assert lo < MEDIAN[path] < hi
    # shared: a parameter that truly differs between devices fails the homogeneity test
    shared = population_from_batch(out.results, {"thermal.tau_s": "shared"})
    assert shared.parameters["thermal.tau_s"].q_p < 1e-3


def test_population_fit_is_calibrated_on_known_estimates():
    rng = np.random.default_rng(3)
    z = []
    for _ in range(100):
        theta = 0.6 * np.exp(0.1 * rng.normal(size=30))
        se = theta * rng.uniform(0.02, 0.08, 30)
        est = theta * np.exp(rng.normal(size=30) * se / theta)
        p = population_fit(range(30), {"a": est}, {"a": se}, {"a": "random"}).parameters["a"]
        z.append([(p.log_mu - np.log(0.6)) / p.log_mu_se, (p.omega - 0.1) / p.omega_se])
    z = np.array(z)
    assert np.all(np.abs(z.mean(axis=0)) < 0.4) and np.all(np.abs(z.std(axis=0) - 1) < 0.3)


def test_dask_worker_killed_mid_batch_loses_and_duplicates_nothing(tmp_path):
    pytest.importorskip("distributed")
    from greybox._estimate.distributed import run_tasks, start_client

    marker = tmp_path / "killed"

    def task(task_id, marker_path, value):
        if task_id == 1 and not Path(marker_path).exists():
            Path(marker_path).touch()
            os._exit(1)  # the worker process dies on the first attempt
        return task_id, value * 2

    client, cluster = start_client("local", n_workers=2)
    try:
        preallocate = client.run(lambda: os.environ.get("XLA_PYTHON_CLIENT_PREALLOCATE"))
        out = run_tasks(task, [(str(marker), v) for v in range(5)], client=client, retries=1)
    finally:
        client.close()
        cluster.close()
    if "XLA_PYTHON_CLIENT_PREALLOCATE" not in os.environ:  # workers got `worker_environment`
        assert set(preallocate.values()) == {"false"}
    assert marker.exists()  # a worker really died
    assert out == [0, 2, 4, 6, 8]  # every task exactly once, in order
