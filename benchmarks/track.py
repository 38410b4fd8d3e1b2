"""Throughput of `greybox track`'s pipeline: decode a 640x480 uncompressed grey AVI (what
scientific cameras record), track a 64x64 ROI.

Usage: .venv/bin/python benchmarks/track.py [--frames N]
The last line of output is one JSON object; ``frames_per_s`` is the end-to-end rate
(ffmpeg decode + grey conversion + registration + quality), ``track_frames_per_s`` the
registration alone on frames already in memory.
"""

import argparse
import json
import os
import platform
import tempfile
import time

import numpy as np

from greybox.io.video import iter_frames, probe, write_video
from greybox.render import render_shuttle
from greybox.tracking import (FeatureTracker, Roi, measure_sequence, reference_frame,
                              saturation_level_for, shuttle_track)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=2000)
    n = ap.parse_args().frames
    base = render_shuttle(1.5 * np.sin(np.linspace(0, 12, 200)), shape=(480, 640), seed=0)
    frames = np.resize(base.frames, (n, 480, 640))  # tile 200 rendered frames to n
    roi = Roi(288, 208, 64, 64)
    with tempfile.TemporaryDirectory() as tmp:
        path = write_video(os.path.join(tmp, "bench.avi"), frames, fps=100.0, raw=True)
        t0 = time.perf_counter()
        info = probe(path)
        chunks = iter_frames(path, info)
        first = next(chunks)
        tracker = FeatureTracker(reference_frame(first), roi,
                                 saturation_level=saturation_level_for(info.dtype))

        def all_chunks():
            yield first
            yield from chunks

        (meas,) = measure_sequence([tracker], all_chunks())
        track = shuttle_track(meas)
        e2e = time.perf_counter() - t0
    t0 = time.perf_counter()
    (meas2,) = measure_sequence([tracker], (frames[i:i + 256] for i in range(0, n, 256)))
    shuttle_track(meas2)
    only = time.perf_counter() - t0
    assert len(track.y_px) == n
    print(f"{n} frames 640x480, ROI 64x64: end-to-end {n / e2e:.0f} frames/s, "
          f"tracking only {n / only:.0f} frames/s")
    print(json.dumps({"benchmark": "track", "frames": n, "frame_px": [640, 480],
                      "roi_px": [64, 64], "frames_per_s": round(n / e2e, 1),
                      "track_frames_per_s": round(n / only, 1), "cpus": os.cpu_count(),
                      "python": platform.python_version()}))


if __name__ == "__main__":
    main()
