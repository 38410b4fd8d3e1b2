"""Scale-out of batched fits on Dask distributed (an edge module: it starts processes).

`fit_distributed(devices, free)` cuts the devices into tasks, each a `fit_batch` over a few
vmapped chunks of one fixed size (so every worker compiles the solver once), submits them to
a Dask cluster and gathers one `FitResult` per device:

- `scheduler="local"` (default) starts a `LocalCluster` of `n_workers` single-threaded worker
  processes (closed afterwards); an address ("tcp://host:8786") uses a running cluster;
  `client=` an existing `distributed.Client`;
- a task that raises is retried `retries` times; a task whose worker dies (killed, out of
  memory) is re-run by the scheduler on another worker (up to Dask's
  `distributed.scheduler.allowed-failures`). Results are keyed by task and device name, so a
  re-run task can neither lose nor duplicate a device: the gather checks that every device
  comes back exactly once;
- memory: the chunk size (solves per compiled call) is chosen from `memory_budget_bytes`
  per worker with `greybox._estimate.batch.bytes_per_item` (frames x runs x states x parameters x
  Jacobian), unless `chunk_size` is given;
- one machine with an accelerator: the local cluster's workers share it (each takes only
  the memory its chunks need, `worker_environment`) and each does its devices' host work
  (problem building, residual tests, assembly: interpreter work, one core per worker) on a
  core of its own, which a single process cannot (`fit_batch`'s host work is one thread);
  `worker_platform="cpu"` keeps them on the CPU;
- a local cluster's workers compile into the client's persistent compilation cache, where
  it has one (`compile_cache_settings`; the `greybox` commands keep one): every call starts
  new workers, which then load what an earlier call compiled instead of compiling again;
- device files loaded by the registry (built-in `models/`, a user's device file) are
  registered on the worker from the same folder before the devices are unpickled (a
  cluster's workers must see that folder at the same path);
- the same devices, options and seed give the same per-device results as the single-process
  `fit_batch` (to rounding: a device's padding may differ when its chunk-mates differ).

Needs the optional extra `distributed` (``pip install "dask[distributed]"``).
"""

from __future__ import annotations

import logging
import math
import os
import pickle
import sys
import time
import types
from collections.abc import Callable, Sequence

import numpy as np

from greybox._collector import collect_young, collector_paused
from greybox._estimate import batch as _batch
from greybox._estimate.fit import _unpickle_fit_result
from greybox._platform import on_accelerator, one_core

DEFAULT_WORKER_BUDGET = 1 * 1024**3  # bytes one worker's compiled call may allocate
TASKS_PER_WORKER = 8  # the client gathers a task's results in one message: with more and
# smaller tasks its gathering overlaps the fitting and the last tasks' gathering is short


def _require_distributed():
    try:
        import distributed
    except ModuleNotFoundError as err:
        raise ModuleNotFoundError(
            'greybox: Dask is not installed; pip install "dask[distributed]" (the greybox '
            "extra `distributed`) to fit on a cluster"
        ) from err
    return distributed


def device_packages(devices) -> dict:
    """{package: folder paths} of the device-file packages the devices' model classes live in.

    Device files (built-in `models/`, a user's `my_devices/x.py`) are loaded by the registry
    as namespace packages that exist only in the process that loaded them; a worker must
    register the same packages before it can unpickle such a model."""
    out = {}
    for d in devices:
        top = type(d.model).__module__.split(".")[0]
        pkg = sys.modules.get(top)
        path = getattr(pkg, "__path__", None)
        if pkg is not None and getattr(pkg, "__file__", None) is None and path is not None:
            out[top] = [str(p) for p in path]
    return out


def _register_packages(packages: dict) -> None:
    for name, path in packages.items():
        if name not in sys.modules:
            pkg = types.ModuleType(name)
            pkg.__path__ = list(path)
            pkg.__package__ = name
            sys.modules[name] = pkg


# the client's persistent compilation cache settings that a local cluster's workers take
CACHE_SETTINGS = (
    "jax_compilation_cache_dir",
    "jax_persistent_cache_min_compile_time_secs",
    "jax_compilation_cache_max_size",
)


def compile_cache_settings() -> dict:
    """{JAX option: value} of this process's persistent compilation cache (empty where it has
    none), for the workers of a local cluster: each worker is a new process that would
    otherwise compile every program again, in every `fit_distributed` call (the cluster is
    new each time); with the client's cache a worker loads what an earlier worker, call or
    command compiled (`greybox fit-many --scheduler local` uses the command's cache)."""
    import jax

    if not jax.config.jax_compilation_cache_dir:
        return {}
    return {name: getattr(jax.config, name) for name in CACHE_SETTINGS}


def _use_compile_cache(settings: dict) -> None:
    """Worker side: the client's cache settings, unless this worker has a cache of its own
    (set before its first compile: JAX reads them then)."""
    import jax

    if settings and not jax.config.jax_compilation_cache_dir:
        for name, value in settings.items():
            jax.config.update(name, value)


def _pickled(obj) -> bytes:
    """`obj` pickled for another process of this cluster: by reference, with the standard
    pickle (2.4x faster to write than cloudpickle's by-value pickler for a chevron device),
    unless it refers to something defined in a `__main__` (a notebook's or script's model
    class or function), which the other process cannot import: then by value (cloudpickle).

    Protocol 4, not 5: protocol 5 writes each array as a buffer that unpickles into a
    memoryview and its buffer, two objects the cyclic collector tracks per array (a chevron
    result: 397 tracked objects against 139), and the client holds tens of thousands."""
    import cloudpickle

    try:
        data = pickle.dumps(obj, protocol=4)
    except (pickle.PicklingError, AttributeError, TypeError):  # e.g. a class the worker
        return cloudpickle.dumps(obj, protocol=4)  # unpickled by value from the client's __main__
    return cloudpickle.dumps(obj, protocol=4) if b"__main__" in data else data


def _fit_task(task_id: int, packages: dict, payload: bytes, cache: dict | None = None) -> tuple:
    """Worker side: float64 on, the client's compile cache (`compile_cache_settings`), the
    device packages registered, then the payload (devices, free, options) unpickled and one
    `fit_batch`; returns (task_id, (the results encoded by `_encoded_results`, seconds the
    worker spent on the task))."""
    import jax

    t0 = time.perf_counter()
    jax.config.update("jax_enable_x64", True)
    _use_compile_cache(cache or {})
    _register_packages(packages)
    devices, free, kwargs = pickle.loads(payload)
    with one_core():  # a worker is one of many on its machine: no threads of its own
        out = _batch.fit_batch(devices, free, **kwargs)
    return task_id, (_encoded_results(out.results, devices), time.perf_counter() - t0)


def _encoded_results(results: dict, devices) -> bytes:
    """Worker side: {name: FitResult} as one pickle (`_pickled`) of the results' states
    (`FitResult.__reduce__`), each without its estimation runs where they are its device's
    own, which the client holds already (a chevron result: 9 of its 35 kB).

    One pickle, because Dask would send each of the results' arrays as a frame of its own
    (~150 a chevron result), which cost the worker 2.1 ms a result to write against 1.2 ms
    for one pickle, and the client more to read."""
    runs = {d.name: d.experiments for d in devices}
    states = {}
    for name, result in results.items():
        _, (state,) = result.__reduce__()
        own, sent = runs.get(name, ()), state["experiments"]
        if len(own) == len(sent) and all(a is b for a, b in zip(own, sent, strict=True)):
            state["experiments"] = None  # the client's own: `_unpickled_results`
        states[name] = state
    return _pickled(states)


def _unpickled_results(part: tuple, runs: dict) -> tuple:
    """Client side of `_encoded_results`: ({name: FitResult}, worker seconds), each result
    given back its device's estimation runs from `runs` ({name: experiments}, the client's
    own objects, as `fit_batch` gives them).

    Its caller holds the cyclic collector paused over the whole gathering
    (`fit_distributed`); the objects just made are examined here, once, and the next task's
    are not walked with them (with the collector on between tasks, its full collections
    walked every result gathered so far, again and again as their number grew: a fifth of
    the client's time)."""
    encoded, seconds = part
    out = {}
    for name, state in pickle.loads(encoded).items():
        if state["experiments"] is None:
            state["experiments"] = runs[name]
        out[name] = _unpickle_fit_result(state)
    collect_young()
    return out, seconds


def run_tasks(
    fn: Callable,
    payloads: Sequence[tuple],
    *,
    client,
    retries: int = 2,
    progress: Callable[[str], None] | None = None,
    name: str = "greybox",
    decode: Callable | None = None,
) -> list:
    """Run `fn(task_id, *payload)` for every payload on `client`, each with `retries`; return
    the results in payload order (each passed through `decode` as it arrives, if given).
    `fn` must return (task_id, result); a task's result is taken once whatever its attempts,
    and a missing or repeated task id raises."""
    distributed = _require_distributed()
    say = progress or (lambda _msg: None)
    import uuid

    token = uuid.uuid4().hex[:8]
    futures = [  # submitted as each payload is built (`payloads` may build it on access)
        client.submit(fn, i, *payloads[i], retries=retries, pure=False, key=f"{name}-{token}-{i}")
        for i in range(len(payloads))
    ]
    got: dict = {}
    for k, fut in enumerate(distributed.as_completed(futures), start=1):
        task_id, result = fut.result()
        if task_id in got:
            raise RuntimeError(f"task {task_id} returned twice; results would be duplicated")
        got[task_id] = result if decode is None else decode(result)
        say(f"task {task_id + 1}/{len(payloads)} gathered ({k}/{len(payloads)} done)")
    missing = sorted(set(range(len(payloads))) - set(got))
    if missing:
        raise RuntimeError(f"tasks {missing} returned no result")
    return [got[i] for i in range(len(payloads))]


def check_scheduler(scheduler: str, timeout_s: float = 5.0) -> None:
    """Before any work: the `distributed` extra is installed, and a scheduler address is
    well formed and accepts a connection within `timeout_s` (else an `InputError` naming
    --scheduler, instead of a 30 s wait and a traceback)."""
    import socket
    from urllib.parse import urlsplit

    from greybox._extras import require_extra
    from greybox._model.errors import InputError

    require_extra("distributed", field="--scheduler", what="--scheduler")
    if scheduler == "local":
        return
    parts = urlsplit(scheduler if "://" in scheduler else f"tcp://{scheduler}")
    try:
        host, port = parts.hostname, parts.port
    except ValueError:
        host = port = None
    if parts.scheme not in ("tcp", "tls") or not host or not port:
        raise InputError(
            f"{scheduler!r} is not a scheduler address; give local or tcp://HOST:PORT",
            field="--scheduler",
        )
    try:
        socket.create_connection((host, port), timeout=timeout_s).close()
    except OSError as err:
        raise InputError(
            f"cannot reach the Dask scheduler at {host}:{port} ({err.strerror or err}); start "
            "it (dask scheduler) or use --scheduler local",
            field="--scheduler",
        ) from None


def worker_environment(platform: str | None = None) -> dict:
    """Environment of a local cluster's worker processes (those already set here win):

    - `XLA_PYTHON_CLIENT_PREALLOCATE=false`: on an accelerator, JAX's default is to take 75 %
      of its memory at the first computation, so the second of several workers sharing one
      GPU would fail; each worker takes what its chunks need (a chunk is sized by the
      per-worker `memory_budget_bytes`);
    - `platform="cpu"`: `JAX_PLATFORMS=cpu`, workers that leave the accelerator alone."""
    env = {"XLA_PYTHON_CLIENT_PREALLOCATE": "false"}
    if platform is not None:
        env["JAX_PLATFORMS"] = str(platform)
    return {k: v for k, v in env.items() if k not in os.environ}


def start_client(
    scheduler: str | None = "local", n_workers: int = 2, memory_limit="auto", platform=None
):
    """(client, cluster or None): a `LocalCluster` of `n_workers` one-thread worker processes
    for "local"/None (their JAX on `platform`, default JAX's own choice, which on a GPU
    machine is the GPU they then share: `worker_environment`), else a client of the
    scheduler at that address."""
    from greybox._log import route_dask_logs

    distributed = _require_distributed()
    route_dask_logs()  # Dask's logs go to the `greybox.dask` logger, not the terminal
    if scheduler in (None, "local"):
        cluster = distributed.LocalCluster(
            n_workers=int(n_workers),
            threads_per_worker=1,
            processes=True,
            memory_limit=memory_limit,
            dashboard_address=None,
            silence_logs=logging.ERROR,
            env=worker_environment(platform),
        )
        # results come from the workers straight, not through the scheduler, which a local
        # cluster runs in this process, so they cross its sockets once (a task's results are
        # one frame, `_encoded_results`: 0.44 -> 0.42 ms a result to gather)
        return distributed.Client(cluster, direct_to_workers=True), cluster
    return distributed.Client(scheduler, timeout="10s"), None


def _check_on_client(devices, free, kw) -> None:
    """`fit_batch`'s checks of the batch's settings and of every device
    (`_batch.checked_devices`), with `fit_batch`'s keyword arguments `kw` (those of a
    least-squares fit: a process-noise batch is left to its workers, as before)."""
    from greybox._estimate.noise_models import ProcessNoise

    if isinstance(kw.get("noise"), ProcessNoise):
        return
    loss, sigma, _, _ = _batch.output_error_settings(
        kw.get("noise"), kw.get("loss", "huber"), kw.get("sigma"), None, None
    )
    _batch.checked_devices(devices, free, kw.get("method"), loss, sigma, kw.get("n_starts"))


def plan(
    devices,
    free,
    *,
    n_workers: int,
    chunk_size=None,
    memory_budget_bytes=None,
    accelerator: bool = False,
    **kw,
):
    """(chunk size, devices per task, estimated bytes per solve) for a distributed batch.

    Each task holds whole chunks; there are at least `TASKS_PER_WORKER` tasks per worker when
    the devices allow, so a dead worker costs little, the load balances and the client's
    gathering keeps pace. Workers on an `accelerator` take chunks as large as a task and their
    memory budget allow (a vmapped chunk is one set of kernels: small chunks pay the per-call
    and per-step launches many times); on a CPU, at most `_batch.MAX_CHUNK`. The budget per
    worker is `memory_budget_bytes`, by default `worker_budget`."""
    budget = (
        worker_budget(n_workers, accelerator)
        if memory_budget_bytes is None
        else memory_budget_bytes
    )
    prepared, groups = _batch._prepare(
        devices[:1],
        tuple(devices[0].free or free),
        kw.get("method"),
        kw.get("loss", "huber"),
        kw.get("huber_c", 1.5),
        kw.get("student_nu", 4.0),
        kw.get("sigma"),
        kw.get("n_starts"),
        kw.get("seed", 0),
        (
            kw.get("solver_rtol", 1e-8),
            kw.get("solver_atol", 1e-10),
            kw.get("solver_max_steps", 16384),
        ),
    )
    b = _batch.bytes_per_item(prepared[0].problem)
    starts = len(prepared[0].starts)
    per_worker = math.ceil(len(devices) / max(int(n_workers), 1))
    if chunk_size is None:
        most = _batch.MAX_CHUNK_ACCELERATOR if accelerator else _batch.MAX_CHUNK
        task_solves = max(per_worker // TASKS_PER_WORKER, 1) * starts
        chunk_size = _batch.chunk_size_for(b, budget, task_solves, most)
    chunk_devices = max(1, int(chunk_size) // starts)
    n_tasks = max(1, math.ceil(len(devices) / chunk_devices))
    n_tasks = max(n_tasks, min(len(devices), TASKS_PER_WORKER * int(n_workers)))
    per_task = math.ceil(len(devices) / n_tasks)
    per_task = math.ceil(per_task / chunk_devices) * chunk_devices
    return int(chunk_size), int(per_task), int(b)


def fit_distributed(
    devices: Sequence,
    free,
    *,
    scheduler: str | None = "local",
    n_workers: int = 2,
    client=None,
    worker_platform: str | None = None,
    chunk_size: int | None = None,
    memory_budget_bytes: float | None = None,
    retries: int = 2,
    progress: Callable[[str], None] | None = None,
    **fit_kwargs,
) -> _batch.BatchResult:
    """`greybox._estimate.batch.fit_batch` on a Dask cluster: the same arguments and result.

    **Other arguments:** `scheduler` ("local" or an address), `n_workers` (local cluster),
    `client` (an existing Client; then `scheduler` is ignored), `worker_platform` (the JAX
    platform of the workers: None, JAX's choice, which on a machine with a GPU is that GPU,
    shared by the local cluster's workers while each runs its own host work on its own core;
    "cpu" keeps them off it; a cluster given by `client` or an address is taken to be of
    CPUs unless this says otherwise), `chunk_size` / `memory_budget_bytes` (per worker;
    default 1 GiB, or, for workers on an accelerator of this machine, its share of the
    accelerator memory: `worker_budget`), `retries` per task, `progress`.

    The result's `worker_s` holds the seconds each task spent on its worker (unpickling,
    fitting), so that the cluster's own overhead is the wall time less that work. A device
    `fit_batch` would refuse is refused here, by name, before a cluster starts.
    """
    devices = list(devices)
    free = tuple(free)
    say = progress or (lambda _msg: None)
    _batch.check_names(devices)
    names = [d.name for d in devices]
    # every device checked here, as `fit_batch` checks it: a bad one is refused by name
    # before a cluster starts, not by a worker after its retries (the other tasks' work lost)
    _check_on_client(devices, free, fit_kwargs)
    own = client is None
    local = own and scheduler in (None, "local")
    if worker_platform is not None:
        accelerator = worker_platform != "cpu"
    else:  # a local cluster's workers see this machine's devices
        accelerator = local and on_accelerator()
    chunk, per_task, b = plan(
        devices,
        free,
        n_workers=n_workers,
        chunk_size=chunk_size,
        memory_budget_bytes=memory_budget_bytes,
        accelerator=accelerator,
        **fit_kwargs,
    )
    tasks = [devices[i : i + per_task] for i in range(0, len(devices), per_task)]
    say(
        f"{len(devices)} devices in {len(tasks)} tasks of up to {per_task}, chunks of "
        f"{chunk} solves (~{chunk * b / 1e6:.0f} MB per worker)"
    )
    cluster = None
    if own:
        client, cluster = start_client(scheduler, n_workers, platform=worker_platform)
    try:
        kwargs = dict(fit_kwargs, chunk_size=chunk)
        packages = device_packages(devices)
        cache = compile_cache_settings() if local else {}  # a remote worker's folders differ
        runs = {d.name: d.experiments for d in devices}
        with collector_paused():  # the results' objects: `_unpickled_results`
            parts = run_tasks(
                _fit_task,
                _LazyPayloads(tasks, lambda t: (packages, _pickled((t, free, kwargs)), cache)),
                client=client,
                retries=retries,
                progress=say,
                name="greybox-fit",
                decode=lambda part: _unpickled_results(part, runs),
            )
    finally:
        if own:
            client.close()
            if cluster is not None:
                cluster.close()
    results: dict = {}
    for part, _ in parts:
        for name, r in part.items():
            if name in results:
                raise RuntimeError(f"{name}: fitted twice; results would be duplicated")
            results[name] = r
    missing = [n for n in names if n not in results]
    if missing:
        raise RuntimeError(f"devices {missing} came back without a result")
    ordered = {n: results[n] for n in names}
    n_calls = int(np.sum([math.ceil(len(t) / max(chunk, 1)) for t in tasks]))
    worker_s = tuple(float(seconds) for _, seconds in parts)
    return _batch.BatchResult(ordered, 1, chunk, n_calls, b, worker_s=worker_s)


class _LazyPayloads(Sequence):
    """Task payloads built on access: a task is pickled just before it is submitted, so the
    first tasks run while the client pickles the rest (32,768 devices take seconds)."""

    def __init__(self, tasks, build):
        self.tasks, self.build = tasks, build

    def __len__(self):
        return len(self.tasks)

    def __getitem__(self, i):
        return self.build(self.tasks[i])


def worker_budget(n_workers: int, accelerator: bool) -> float:
    """Bytes one worker's compiled call may allocate: on an accelerator of this machine
    (the local cluster's workers share it), an even share of what one chunk may take there
    (`_batch.device_budget`: half its free memory), so that chunks are as large as the card
    allows (each chunk's Levenberg-Marquardt loop waits on the card once a step, a wait that
    the workers' turns on a shared card lengthen); else `DEFAULT_WORKER_BUDGET`."""
    if accelerator and on_accelerator():
        return _batch.device_budget()[0] / max(int(n_workers), 1)
    return DEFAULT_WORKER_BUDGET
