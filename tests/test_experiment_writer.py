"""The experiment writer is the loader's inverse: what it writes loads back unchanged."""

import numpy as np
import pytest

from greybox.io import load_experiment_set
from greybox.io._experiment_writer import (
    inline_table,
    pulse_train_description,
    run_csv,
    run_table,
)


def test_written_folder_loads_back(tmp_path):
    t = np.array([0.01, 0.04, 0.07, 0.11, 0.14, 0.18])
    y_px = np.array([300.1, 300.2, np.nan, 301.9, 302.4, 301.0])
    (tmp_path / "r1.csv").write_text(run_csv(t, {"y_px": (y_px, 4)}))
    wave = pulse_train_description(12.5, 50.0, n_pulses=3, delay_ms=20.0)
    toml = (
        '[experiment]\ndevice = "chevron_laser"\n\n[camera]\nfps = 30\nexposure_ms = 5\n'
        "um_per_px = 0.5\n\n" + run_table("r1", "estimation", wave)
    )
    (tmp_path / "experiment.toml").write_text(toml)
    fitset = load_experiment_set(tmp_path)
    (e,) = fitset.estimation
    np.testing.assert_allclose(e.t_s, t)
    np.testing.assert_allclose(e.y[:, 0], y_px * 0.5e-6)  # px -> m with the camera scale
    assert np.isnan(e.y[2, 0])
    # the waveform round-trips: 12.5 mW on for 25 ms every 50 ms after a 20 ms delay
    np.testing.assert_allclose(
        e.inputs(np.array([0.01, 0.03, 0.05, 0.08])), [0, 12.5e-3, 0, 12.5e-3]
    )


def test_inline_table_quotes_setting_paths_and_rejects_ragged_columns():
    assert inline_table({"type": "logged"}) == '{ type = "logged" }'
    assert inline_table({"spot.x_m": 3e-05}) == '{ "spot.x_m" = 3e-05 }'
    with pytest.raises(ValueError, match="y_px: 2 values for 3 frame times"):
        run_csv([0.0, 0.1, 0.2], {"y_px": ([1.0, 2.0], 4)})
