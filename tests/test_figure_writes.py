"""Result figures are written as matplotlib's own `savefig` writes them, byte for byte, whether
the PNG is written at once or by the background writer (`png_writes_in_background`, which
compresses one figure while the next is drawn); the caller's figure keeps its resolution and
canvas; a file that cannot be written raises when the block ends, after the others are
written."""

import numpy as np
import pytest
from matplotlib.figure import Figure

from greybox.report import _plots


def _figure() -> Figure:
    """Constrained layout (as every result figure), text, lines, a band and a legend."""
    fig = Figure(figsize=(6.0, 3.5), layout="constrained")
    ax, bx = fig.subplots(1, 2)
    t = np.linspace(0.0, 2.0, 200)
    ax.plot(t, np.sin(7 * t), ".", ms=3, label="measured")
    ax.plot(t, np.sin(7 * t) * 0.9, "-", label="model")
    ax.fill_between(t, -0.2, 0.2, color="0.8")
    ax.legend(fontsize=7)
    ax.set_ylabel("shuttle displacement [um]")
    bx.vlines(np.arange(1, 20), 0.0, np.cos(np.arange(1, 20)) / 5, lw=3)
    bx.set_title("autocorrelation\n(Ljung-Box p = 0.19)", fontsize=8)
    fig.suptitle("Residuals: white", fontsize=8)
    return fig


def _savefig_bytes(tmp_path) -> bytes:
    path = tmp_path / "savefig.png"
    _figure().savefig(
        path, dpi=_plots.DPI, pil_kwargs={"compress_level": _plots.PNG_COMPRESS_LEVEL}
    )
    return path.read_bytes()


def test_png_is_the_file_savefig_writes(tmp_path):
    expected = _savefig_bytes(tmp_path)
    _plots.save_figure(_figure(), tmp_path / "now.png")
    with _plots.png_writes_in_background():
        _plots.save_figure(_figure(), tmp_path / "later.png")
        _plots.save_figure(_figure(), tmp_path / "later2", fmt="png")
    for name in ("now.png", "later.png", "later2.png"):
        assert (tmp_path / name).read_bytes() == expected, name


def test_the_figure_keeps_its_resolution_and_canvas(tmp_path):
    fig = _figure()
    dpi, canvas = fig.dpi, fig.canvas
    _plots.save_figure(fig, tmp_path / "f.png")
    assert fig.dpi == dpi != _plots.DPI
    assert fig.canvas is canvas


def test_a_file_that_cannot_be_written_raises_when_the_block_ends(tmp_path):
    with pytest.raises(FileNotFoundError):
        with _plots.png_writes_in_background():
            _plots.save_figure(_figure(), tmp_path / "missing-folder" / "a.png")
            _plots.save_figure(_figure(), tmp_path / "b.png")
    assert (tmp_path / "b.png").read_bytes() == _savefig_bytes(tmp_path)


def test_vector_formats_are_written_by_savefig(tmp_path):
    written = _plots.save_figure(_figure(), tmp_path / "f.png", fmt="svg")
    assert written == tmp_path / "f.svg"
    assert written.read_text().lstrip().startswith("<?xml")
