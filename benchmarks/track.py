"""Throughput of `greybox track`, end to end, on a 640x480 video with a 64x64 ROI.

Usage: .venv/bin/python benchmarks/track.py [--frames N] [--smoke]

Container/codec: uncompressed 8-bit grey AVI (``rawvideo``), what scientific cameras
record and the only lossless format whose decoding is not itself the bottleneck: FFV1
(lossless, 6x smaller) must decode every full 640x480 frame at ~150 frames/s per core,
whatever the ROI; that rate is measured too (``ffv1_frames_per_s``, on fewer frames).

Measured in the same run (same machine load):
- ``frames_per_s``: `greybox track` through `greybox.cli.main` (probe + container
  timestamps, ffmpeg decode cropped to the search window, reader thread, registration,
  quality, flagging, CSV write): the honest end-to-end rate.
- ``baseline_frames_per_s``: the previous pipeline: full frames through the pipe, no
  reader thread, same tracker (``speedup`` = frames_per_s / baseline).
- ``track_frames_per_s``: registration alone on frames already in memory (whole-pixel
  batched FFT search, then scikit-image's `phase_cross_correlation` per frame for the
  sub-pixel step: ``subpixel`` in the JSON).
- ``cpu_ms_per_frame``: CPU time of the end-to-end run (all threads and the ffmpeg
  processes) per frame: unlike the wall-clock rates it does not depend on how busy the
  machine is (this one is shared: the 1-minute load average is printed and recorded at
  the start and the end, ``load_average_start``/``load_average``).
The last line of output is one JSON object.
"""

import argparse
import json
import os
import platform
import resource
import tempfile
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from greybox.cli import main as cli_main  # noqa: E402
from greybox.video import (  # noqa: E402  # noqa: E402
    FeatureTracker,
    Roi,
    iter_frames,
    measure_sequence,
    probe,
    reference_frame,
    render_shuttle,  # noqa: E402
    saturation_level_for,
    shuttle_track,
    write_video,
)

ROI = Roi(288, 208, 64, 64)


SMOKE_HELP = "smallest setting (a few seconds): checks that the script still runs"

def _cpu_s():
    """CPU seconds used so far by this process (all threads) and its waited-for children
    (the ffmpeg processes)."""
    me, kids = (resource.getrusage(w) for w in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN))
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


def _load():
    """1-minute load average (NaN where the OS has none)."""
    return os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")


def _cli_rate(path, n, out):
    """(frames/s wall clock, CPU ms per frame) of `greybox track` on ``path``."""
    c0, t0 = _cpu_s(), time.perf_counter()
    rc = cli_main(
        [
            "track",
            str(path),
            "--roi",
            f"{ROI.x},{ROI.y},{ROI.w},{ROI.h}",
            "--um-per-px",
            "0.645",
            "--out",
            str(out),
        ]
    )
    dt, cpu = time.perf_counter() - t0, _cpu_s() - c0
    rows = out.read_text().count("\n") - 1
    assert rc == 0 and rows == n, (rc, rows, n)
    return n / dt, 1e3 * cpu / n


def _baseline_rate(path, n):
    """Full frames through the pipe, decoding and tracking taking turns (no CSV)."""
    t0 = time.perf_counter()
    info = probe(path)
    chunks = iter_frames(path, info)
    first = next(chunks)
    tracker = FeatureTracker(
        reference_frame(first), ROI, saturation_level=saturation_level_for(info.dtype)
    )
    (meas,) = measure_sequence([tracker], [first, *chunks])
    shuttle_track(meas)
    dt = time.perf_counter() - t0
    assert len(meas.rho) == n
    return n / dt, tracker


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=2000)
    ap.add_argument("--ffv1-frames", type=int, default=300)
    ap.add_argument("--smoke", action="store_true", help=SMOKE_HELP)
    args = ap.parse_args()
    if args.smoke:
        args.frames, args.ffv1_frames = 20, 10
    n = args.frames
    load_start = _load()
    # 50 rendered frames (640x480 rendering is slow), tiled to n: the rate does not
    # depend on which frames repeat.
    n_render = 5 if args.smoke else 50
    base = render_shuttle(1.5 * np.sin(np.linspace(0, 12, n_render)), shape=(480, 640), seed=0)
    frames = np.resize(base.frames, (n, 480, 640))
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        raw = write_video(tmp / "bench.avi", frames, fps=100.0, raw=True)
        ffv1 = write_video(tmp / "bench_ffv1.mkv", frames[: args.ffv1_frames], fps=100.0)
        base_fps, tracker = _baseline_rate(raw, n)
        e2e_fps, cpu_ms = _cli_rate(raw, n, tmp / "run.csv")
        ffv1_fps, _ = _cli_rate(ffv1, args.ffv1_frames, tmp / "run_ffv1.csv")
    t0 = time.perf_counter()
    (meas,) = measure_sequence([tracker], (frames[i : i + 256] for i in range(0, n, 256)))
    shuttle_track(meas)
    track_fps = n / (time.perf_counter() - t0)
    load = _load()
    print(
        f"{n} frames 640x480 raw grey AVI, ROI 64x64, {os.cpu_count()} CPUs, "
        f"load average {load_start:.1f} at the start, {load:.1f} at the end"
    )
    print(
        f"  greybox track end to end (cropped decode + reader thread + CSV): {e2e_fps:.0f} frames/s"
    )
    print(
        f"  CPU time (all threads + ffmpeg): {cpu_ms:.2f} ms per frame "
        "(independent of the machine's load)"
    )
    print(
        f"  previous pipeline (full frames through the pipe, no overlap): "
        f"{base_fps:.0f} frames/s  -> speedup {e2e_fps / base_fps:.2f}x"
    )
    print(f"  tracking alone, frames in memory: {track_fps:.0f} frames/s")
    print(
        f"  FFV1 .mkv end to end ({args.ffv1_frames} frames; full-frame decode bound): "
        f"{ffv1_fps:.0f} frames/s"
    )
    print(
        json.dumps(
            {
                "benchmark": "track",
                "frames": n,
                "frame_px": [640, 480],
                "roi_px": [64, 64],
                "container": "avi",
                "codec": "rawvideo gray (uncompressed)",
                "frames_per_s": round(e2e_fps, 1),
                "baseline_frames_per_s": round(base_fps, 1),
                "speedup": round(e2e_fps / base_fps, 2),
                "track_frames_per_s": round(track_fps, 1),
                "cpu_ms_per_frame": round(cpu_ms, 3),
                "ffv1_frames_per_s": round(ffv1_fps, 1),
                "subpixel": "skimage.registration.phase_cross_correlation, upsample_factor=100",
                "cpus": os.cpu_count(),
                "load_average_start": round(load_start, 2),
                "load_average": round(load, 2),
                "python": platform.python_version(),
            }
        )
    )


if __name__ == "__main__":
    main()
