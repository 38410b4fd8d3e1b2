"""`greybox track` end to end on rendered videos, and its bad-input contract (exit 2)."""

import numpy as np
import pytest

from greybox.cli import main
from greybox.io._video import probe, read_frames, write_image_stack, write_video
from greybox.video._render import render_markers, render_shuttle

REST = 8


@pytest.fixture(scope="module")
def shuttle():
    traj = np.concatenate([np.zeros(REST), np.linspace(0.0, 3.3, 16)])
    return render_shuttle(traj, seed=21, bad_frames={15: "glare"})


def _read_csv(path):
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    rows = [line.split(",") for line in lines[1:]]
    return header, {h: [r[i] for r in rows] for i, h in enumerate(header)}


@pytest.mark.parametrize("suffix", [".avi", ".mp4", "stack"])
def test_track_video_and_stack_end_to_end(tmp_path, shuttle, suffix, capsys):
    if suffix == "stack":
        src = tmp_path / "frames"
        write_image_stack(src, shuttle.frames)
        fps_args = ["--fps", "20"]
    else:
        src = write_video(tmp_path / f"run{suffix}", shuttle.frames, fps=20.0)
        fps_args = []  # the container's timestamps
    out = tmp_path / "runs" / "run1.csv"
    rc = main(
        [
            "track",
            str(src),
            "--roi",
            "32,16,64,64",
            "--um-per-px",
            "0.645",
            "--ref-frames",
            str(REST),
            "--out",
            str(out),
            *fps_args,
        ]
    )
    assert rc == 0
    header, cols = _read_csv(out)
    assert header == ["t_s", "y_px", "y_um", "quality", "reason", "sigma_px", "sigma_um"]
    t = np.array(cols["t_s"], float)
    np.testing.assert_allclose(t, np.arange(len(t)) / 20.0, atol=1e-6)
    y = np.array(cols["y_px"], float)
    good = np.array(cols["reason"]) == ""
    assert list(np.flatnonzero(~good)) == [15] and cols["reason"][15] == "glare"
    assert np.isnan(y[15]) and cols["y_um"][15] == "nan"
    err = (y - shuttle.truth_px)[good]
    assert np.sqrt(np.mean(err**2)) <= 0.05
    np.testing.assert_allclose(np.array(cols["y_um"], float)[good], 0.645 * y[good], atol=1e-4)
    assert "1 flagged (glare 1)" in capsys.readouterr().out


def test_without_scale_writes_px_columns_only(tmp_path, shuttle):
    src = write_video(tmp_path / "run.avi", shuttle.frames[:12], fps=10.0)
    out = tmp_path / "o.csv"
    assert main(["track", str(src), "--roi", "32,16,64,64", "--out", str(out)]) == 0
    assert out.read_text().splitlines()[0] == "t_s,y_px,quality,reason,sigma_px"


def test_two_features_cli(tmp_path):
    n = 16
    k = np.arange(n)
    heading = 0.01 * np.clip(k - REST, 0, None)
    centre = np.stack([80 + 0.5 * np.clip(k - REST, 0, None), np.full(n, 60.0)], 1)
    d = np.stack([np.cos(heading), np.sin(heading)], 1) * 30.0
    seq = render_markers(np.stack([centre - d, centre + d], 1), seed=22)
    src = write_video(tmp_path / "robot.mkv", seq.frames, fps=25.0)
    out = tmp_path / "robot.csv"
    rc = main(
        [
            "track",
            str(src),
            "--roi",
            "34,44,32,32",
            "--roi2",
            "94,44,32,32",
            "--um-per-px",
            "0.5",
            "--ref-frames",
            str(REST),
            "--out",
            str(out),
        ]
    )
    assert rc == 0
    header, cols = _read_csv(out)
    assert header == [
        "t_s",
        "f1_x_px",
        "f1_y_px",
        "f2_x_px",
        "f2_y_px",
        "x_um",
        "y_um",
        "heading_rad",
        "quality",
        "reason",
        "sigma_px",
    ]
    np.testing.assert_allclose(np.array(cols["heading_rad"], float), heading, atol=0.002)
    np.testing.assert_allclose(
        np.array(cols["x_um"], float), 0.5 * (centre[:, 0] - 80.0), atol=0.025
    )


def _bad(tmp_path, capsys, argv, *names):
    out = tmp_path / "bad.csv"
    rc = main(["track", *argv, "--out", str(out)])
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert len(err.splitlines()) == 1 and err.startswith("greybox track: error:")
    for name in names:
        assert name in err, err
    assert not out.exists()
    assert not list(tmp_path.glob(".bad.csv.partial-*"))
    return err


def test_bad_inputs_exit_2_without_csv(tmp_path, shuttle, capsys):
    video = str(write_video(tmp_path / "ok.avi", shuttle.frames[:6], fps=10.0))
    missing = str(tmp_path / "missing.avi")
    _bad(tmp_path, capsys, [missing, "--roi", "32,16,64,64"], missing, "no such file")
    junk = tmp_path / "junk.mp4"
    junk.write_text("not a video")
    _bad(tmp_path, capsys, [str(junk), "--roi", "32,16,64,64"], str(junk), "cannot be read")
    _bad(tmp_path, capsys, [video, "--roi", "100,16,64,64"], video, "--roi", "outside")
    _bad(tmp_path, capsys, [video, "--roi", "1,2,3"], "--roi", "X,Y,W,H")
    for scale in ("0", "-0.645"):
        _bad(
            tmp_path,
            capsys,
            [video, "--roi", "32,16,64,64", "--um-per-px", scale],
            "--um-per-px",
            "positive",
        )
    one = str(write_video(tmp_path / "one.avi", shuttle.frames[:1], fps=10.0))
    _bad(tmp_path, capsys, [one, "--roi", "32,16,64,64"], one, "at least two")
    stack = tmp_path / "stack"
    write_image_stack(stack, shuttle.frames[:4])
    _bad(tmp_path, capsys, [str(stack), "--roi", "32,16,64,64"], "--fps", str(stack))


def test_video_io_round_trip_is_lossless(tmp_path):
    frames16 = np.random.default_rng(0).integers(0, 65535, (5, 24, 40)).astype(np.uint16)
    frames8 = (frames16 >> 8).astype(np.uint8)
    for path, frames, raw in (
        (tmp_path / "a.mkv", frames16, False),
        (tmp_path / "a.mp4", frames8, False),
        (tmp_path / "raw.avi", frames8, True),
    ):
        write_video(path, frames, fps=12.5, raw=raw)
        got, info = read_frames(path)
        np.testing.assert_array_equal(got, frames)
        assert info.dtype == frames.dtype and info.fps == 12.5
        np.testing.assert_allclose(info.timestamps_s, np.arange(5) / 12.5, atol=1e-3)
    write_image_stack(tmp_path / "tif", frames16, suffix=".tif")
    got, info = read_frames(tmp_path / "tif")
    np.testing.assert_array_equal(got, frames16)
    assert probe(tmp_path / "tif").kind == "stack"


def test_decoder_crop_is_exact_for_every_codec(tmp_path):
    """ffmpeg's crop (odd offsets included, chroma-subsampled H.264 included) returns
    exactly the pixels of the whole decoded frames."""
    from greybox.io._video import iter_frames

    rng = np.random.default_rng(1)
    frames16 = rng.integers(0, 65535, (7, 30, 44)).astype(np.uint16)
    frames8 = (frames16 >> 8).astype(np.uint8)
    for path, frames, raw in (
        (tmp_path / "a.mkv", frames16, False),
        (tmp_path / "a.mp4", frames8, False),
        (tmp_path / "raw.avi", frames8, True),
    ):
        write_video(path, frames, fps=10.0, raw=raw)
        got = np.concatenate(list(iter_frames(path, crop=(5, 3, 21, 17), chunk=3)))
        np.testing.assert_array_equal(got, frames[:, 3:20, 5:26])
        assert got.dtype == frames.dtype
    with pytest.raises(ValueError, match="outside"):
        next(iter_frames(tmp_path / "a.mkv", crop=(30, 0, 20, 10)))


def test_prefetch_keeps_order_reraises_and_stops_early():
    import threading

    from greybox._model.errors import InputError
    from greybox.io._video import prefetch

    assert list(prefetch(iter(range(50)), depth=3)) == list(range(50))

    def broken():
        yield 1
        raise InputError("video decoding failed", file="x.avi")

    got = []
    with pytest.raises(InputError, match="decoding failed"):
        for item in prefetch(broken()):
            got.append(item)
    assert got == [1]
    closed = threading.Event()

    def endless():
        try:
            while True:
                yield 0
        finally:
            closed.set()  # the reader closes its source when the consumer stops

    gen = prefetch(endless())
    next(gen)
    gen.close()
    assert closed.is_set()
    assert not any(t.name == "greybox-prefetch" for t in threading.enumerate())


def test_out_obeys_the_output_contract(tmp_path, shuttle, capsys):
    """A user's file is never overwritten (unless --force), a folder is refused before any
    decoding, nothing partial is left, and an earlier track CSV is replaced."""
    src = str(write_video(tmp_path / "run.avi", shuttle.frames[:8], fps=10.0))
    argv = ["track", src, "--roi", "32,16,64,64", "--out"]
    mine = tmp_path / "notes.csv"
    mine.write_text("t_s,y_um\n0,1\n")
    assert main([*argv, str(mine)]) == 2
    assert mine.read_text() == "t_s,y_um\n0,1\n" and "--force" in capsys.readouterr().err
    folder = tmp_path / "results"
    folder.mkdir()
    assert main([*argv, str(folder)]) == 2 and not any(folder.iterdir())
    assert main([*argv, str(mine), "--force"]) == 0
    assert mine.read_text().startswith("t_s,y_px,quality")
    assert main([*argv, str(mine)]) == 0  # an earlier track result is ours to replace
    assert not list(tmp_path.glob(".*partial*"))


def test_a_missing_video_extra_names_the_pip_install(tmp_path, capsys, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)  # as if not installed
    rc = main(["track", str(tmp_path / "v.avi"), "--roi", "1,1,8,8"])
    err = capsys.readouterr().err
    assert rc == 2 and 'pip install "greybox[video]"' in err and "Traceback" not in err
