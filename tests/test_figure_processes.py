"""Result figures drawn in other processes are the files drawn in this process, byte for
byte: the jobs carry plain data only (arrays, waveforms, labels, the residual analysis) and
Agg draws deterministically. Both ways are checked: `greybox.io._drawing.draw_many` (what
`greybox fit-many` does with its devices' figures, a folder per process) and
`drawing_process` (what `greybox fit` does: one process started before the fit draws half of
its figures, the estimation's while the validation runs). A job that cannot be sent to
another process is drawn here instead, and a drawing error in another process is raised
here, as it is without processes."""

import os
from pathlib import Path

import numpy as np
import pytest

import greybox
from greybox import _platform
from greybox._estimate.residuals import analyse
from greybox.io import _drawing


def _jobs(seed: int) -> list:
    """A run figure, a residuals figure, the residual tests and a correlation matrix."""
    rng = np.random.default_rng(seed)
    t = np.arange(120) / 30.0
    wave = greybox.PiecewiseConstant([0.0, 1.0, 2.5], [0.0, 0.02, 0.0], 4.0)
    model = 1e-6 * np.tanh(t)
    y = model + 2e-8 * rng.standard_normal(t.size)
    run = dict(
        name="e1",
        role="estimation",
        t_s=t,
        y=y,
        y_model=model,
        inputs=wave,
        sigma=2e-8,
        fit_percent=91.0,
        outputs=(("shuttle displacement", "m"),),
        input_labels=(("laser power", "W"),),
    )
    residuals = [("e1", "estimation", t, y, model)]
    tests = analyse([("e1", t, (y - model)[:, None], np.ones((t.size, 1), bool), None)])
    corr = np.array([[1.0, -0.3], [-0.3, 1.0]])
    return [
        ("figures/fit_e1.png", "run_figure", (), run),
        ("figures/residuals.png", "residuals_figure", (residuals,), {"sigma": 2e-8}),
        ("figures/residual_tests.png", "residual_correlation_figure", (tests,), {}),
        ("figures/correlation.png", "correlation_figure", (["a", "b"], corr), {}),
    ]


def _band_job() -> tuple:
    """`greybox simulate`'s figure: a response with its band over a pulse train."""
    from greybox._estimate.band import Band

    t = np.linspace(0.0, 1.0, 200)
    y = (1e-6 * (1 - np.exp(-t / 0.05)))[:, None]
    sd = np.full_like(y, 2e-8)
    band = Band(t, y, y - 2 * sd, y + 2 * sd, sd, sd, 0.95, False)
    wave = greybox.PiecewiseConstant([0.0, 0.1, 0.25], [0.0, 0.02, 0.0], 1.0)
    return ("simulation.png", "band_figure", (band, wave), {"title": "chevron: 20 mW"})


def _files(folder) -> dict:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in folder.rglob("*.png")}


def test_figures_drawn_in_processes_equal_those_drawn_here(tmp_path, monkeypatch):
    monkeypatch.setattr(_platform, "usable_cores", lambda: 2)  # processes even on a one-core runner
    jobs = [_jobs(seed) for seed in range(3)]
    here = [tmp_path / "here" / f"d{k}" for k in range(3)]
    there = [tmp_path / "there" / f"d{k}" for k in range(3)]
    for folder, j in zip(here, jobs):
        folder.mkdir(parents=True)
        _drawing.draw_figures(folder, j)
    for folder in there:
        folder.mkdir(parents=True)
    drawn_here = []  # folders drawn in this process (the other one imports the module afresh)
    draw = _drawing.draw_figures
    monkeypatch.setattr(
        _drawing, "draw_figures", lambda folder, j: drawn_here.append(folder) or draw(folder, j)
    )
    _drawing.draw_many(list(zip(there, jobs)))
    # two cores: one process beside this one, handed two folders at once; this one draws
    # what is left from the back
    assert drawn_here in ([], [there[2]])
    for a, b in zip(here, there):
        drawn, sent = _files(a), _files(b)
        assert sorted(drawn) == sorted(j[0] for j in jobs[0])
        assert drawn == sent


def test_a_job_that_cannot_be_sent_is_drawn_here(tmp_path, monkeypatch):
    monkeypatch.setattr(_platform, "usable_cores", lambda: 2)
    jobs = [_jobs(seed) for seed in range(3)]

    # a waveform of a class defined inside a function cannot be pickled: drawn in this process
    class LocalWave(greybox.PiecewiseConstant):
        pass

    jobs[1][0][3]["inputs"] = LocalWave([0.0, 1.0], [0.0, 0.02], 4.0)
    folders = [tmp_path / f"d{k}" for k in range(3)]
    for folder in folders:
        folder.mkdir()
    drawn_here = []
    draw = _drawing.draw_figures
    monkeypatch.setattr(
        _drawing, "draw_figures", lambda folder, j: drawn_here.append(folder) or draw(folder, j)
    )
    _drawing.draw_many(list(zip(folders, jobs)))
    assert drawn_here == folders
    for folder in folders:
        assert len(_files(folder)) == 4


def test_a_drawing_error_is_raised_here_as_without_processes(tmp_path, monkeypatch):
    monkeypatch.setattr(_platform, "usable_cores", lambda: 2)
    jobs = [_jobs(seed) for seed in range(3)]
    jobs[2].append(("figures/broken.png", "no_such_figure", (), {}))
    folders = [tmp_path / f"d{k}" for k in range(3)]
    for folder in folders:
        folder.mkdir()
    with pytest.raises(AttributeError, match="no_such_figure"):
        _drawing.draw_many(list(zip(folders, jobs)))
    assert len(_files(folders[0])) == 4 and len(_files(folders[1])) == 4


def test_the_drawing_process_shares_the_figures_and_raises_here(tmp_path, monkeypatch):
    """One process (its start is what costs): the same bytes as drawn here with the jobs
    shared out (it is handed two at once, so this process draws at most the rest), then a
    drawing error in a job it was handed raised here; the process ends with the block."""
    jobs = _jobs(0)
    (tmp_path / "here").mkdir()
    _drawing.draw_figures(tmp_path / "here", jobs)
    monkeypatch.setattr(_drawing, "spare_core", lambda: True)  # started, whatever the load
    drawn_here = []
    draw = _drawing._draw_one
    monkeypatch.setattr(
        _drawing, "_draw_one", lambda p, f, j: drawn_here.append(j) or draw(p, f, j)
    )
    with _drawing.drawing_process():
        helper = _drawing._DRAWING.get()
        assert helper is not None
        (tmp_path / "shared").mkdir()
        _drawing.draw_figures(tmp_path / "shared", jobs)
        assert 1 <= len(drawn_here) <= len(jobs) - 2
        assert _files(tmp_path / "shared") == _files(tmp_path / "here")
        broken = [("figures/broken.png", "no_such_figure", (), {}), *jobs]  # handed to it
        (tmp_path / "broken").mkdir()
        with pytest.raises(AttributeError, match="no_such_figure"):
            _drawing.draw_figures(tmp_path / "broken", broken)
    assert helper._proc.poll() is not None  # it ended with the block


def test_a_figure_drawn_beside_the_writing_is_the_one_drawn_here(tmp_path, monkeypatch):
    """`greybox simulate`: its figure goes to the drawing process while the tables are
    written, the same bytes as drawn here; an error in the block waits for the figure in
    hand (nothing is drawn into the folder after its writer has left)."""
    (tmp_path / "here").mkdir()
    _drawing.draw_figures(tmp_path / "here", [_band_job()])
    monkeypatch.setattr(_drawing, "spare_core", lambda: True)
    drawn_here = []
    draw = _drawing._draw_one
    monkeypatch.setattr(
        _drawing, "_draw_one", lambda p, f, j: drawn_here.append(j) or draw(p, f, j)
    )
    with _drawing.drawing_process():
        (tmp_path / "there").mkdir()
        with _drawing.drawing_beside(tmp_path / "there", [_band_job()]):
            (tmp_path / "there" / "simulation.csv").write_text("t_s\n")
        assert drawn_here == []  # the other process drew it
        assert _files(tmp_path / "there") == _files(tmp_path / "here")
        (tmp_path / "failed").mkdir()
        with pytest.raises(RuntimeError, match="disk full"):
            with _drawing.drawing_beside(tmp_path / "failed", [_band_job()]):
                raise RuntimeError("disk full")
        assert _files(tmp_path / "failed") == _files(tmp_path / "here")  # finished first
    with _drawing.drawing_beside(tmp_path / "alone", [_band_job()]):  # no process: here
        (tmp_path / "alone").mkdir()
    assert len(drawn_here) == 1 and _files(tmp_path / "alone") == _files(tmp_path / "here")


def test_figures_drawn_ahead_are_moved_in_unless_their_data_changed(tmp_path, monkeypatch):
    """`greybox fit`: the estimation's figures are drawn by the drawing process while the
    validation runs, into a folder of their own, then moved into the result folder, the
    same bytes as drawn here; a job whose data changed meanwhile is left to be drawn; the
    temporary folder goes with the block, also on an error."""
    jobs = _jobs(0)
    (tmp_path / "here").mkdir()
    _drawing.draw_figures(tmp_path / "here", jobs)
    here = _files(tmp_path / "here")
    with _drawing.drawing_ahead(jobs) as ahead:
        assert ahead is None  # no drawing process: nothing is drawn ahead
    monkeypatch.setattr(_drawing, "spare_core", lambda: True)
    drawn_here = []
    draw = _drawing._draw_one
    monkeypatch.setattr(
        _drawing, "_draw_one", lambda p, f, j: drawn_here.append(j) or draw(p, f, j)
    )
    final = _jobs(0)  # the writer's own jobs, made again from the same data
    rel, function, (names, corr), kwargs = final[3]
    final[3] = (rel, function, (names, 0.5 * corr + 0.5 * np.eye(2)), kwargs)
    with _drawing.drawing_process():
        with _drawing.drawing_ahead(jobs) as ahead:
            staging = ahead.folder
            (tmp_path / "result").mkdir()
            left = ahead.take(tmp_path / "result", final)
        assert [job[0] for job in left] == ["figures/correlation.png"]
        assert len(drawn_here) <= len(jobs) - 2  # it was handed two at once
        assert not staging.exists()
        assert _files(tmp_path / "result") == {k: here[k] for k in here if "correlation" not in k}
        with pytest.raises(RuntimeError, match="validation failed"):
            with _drawing.drawing_ahead(jobs) as ahead:
                staging = ahead.folder
                raise RuntimeError("validation failed")
        assert not staging.exists()


def test_no_drawing_process_without_an_idle_core(monkeypatch):
    monkeypatch.setattr(_platform, "usable_cores", lambda: 2)
    monkeypatch.setattr(_drawing.os, "getloadavg", lambda: (1.8, 1.8, 1.8))
    assert not _drawing.spare_core()
    with _drawing.drawing_process():
        assert _drawing._DRAWING.get() is None
    monkeypatch.setattr(_drawing.os, "getloadavg", lambda: (0.3, 0.3, 0.3))
    assert _drawing.spare_core()
    monkeypatch.setattr(_platform, "usable_cores", lambda: 1)
    assert not _drawing.spare_core()


def test_a_drawing_process_that_cannot_start_leaves_the_drawing_here(tmp_path, monkeypatch):
    monkeypatch.setattr(_drawing, "spare_core", lambda: True)

    def refused():
        raise OSError("no processes here")

    monkeypatch.setattr(_drawing, "_DrawingProcess", refused)
    with _drawing.drawing_process():
        assert _drawing._DRAWING.get() is None
        _drawing.draw_figures(tmp_path, _jobs(0))
    assert len(_files(tmp_path)) == 4


def test_a_script_without_a_main_guard_runs_once(tmp_path):
    """multiprocessing's spawn would import the calling script again in the drawing process,
    running its top level twice; the drawing process runs greybox's own program only."""
    import subprocess
    import sys

    script = tmp_path / "unguarded.py"
    script.write_text(
        "import pathlib\n"
        "from greybox.io import _drawing\n"
        "import test_figure_processes as t\n"
        f"with open({str(tmp_path / 'runs.txt')!r}, 'a') as f:\n"
        "    f.write('ran\\n')\n"
        "_drawing.spare_core = lambda: True\n"
        "with _drawing.drawing_process():\n"
        "    assert _drawing._DRAWING.get() is not None\n"
        f"    _drawing.draw_figures(pathlib.Path({str(tmp_path)!r}), t._jobs(0))\n"
    )
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(Path(__file__).parent), *sys.path]))
    subprocess.run([sys.executable, str(script)], check=True, env=env, timeout=300)
    assert (tmp_path / "runs.txt").read_text() == "ran\n"
    assert len(_files(tmp_path)) == 4


def test_a_drawing_process_does_not_import_jax(tmp_path):
    """What a drawing process imports (the plotting modules, and what unpickling a result's
    jobs needs, a simulation's band included) leaves JAX out: its start is ~0.35 s, not
    ~1.4 s."""
    import pickle
    import subprocess
    import sys

    (tmp_path / "jobs.pkl").write_bytes(pickle.dumps([*_jobs(0), _band_job()]))
    code = (
        "import pickle, sys\n"
        "from greybox.io import _drawing\n"
        "from greybox.report import _plots\n"
        f"pickle.loads(open({str(tmp_path / 'jobs.pkl')!r}, 'rb').read())\n"
        "print(sorted(m for m in sys.modules if m == 'jax' or m.startswith('jax.')))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
