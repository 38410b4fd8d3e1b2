"""Data-based starts of a process-noise fit's intensities (greybox/_estimate/noise_starts.py).

Truth from simulators other than greybox's:

- units: the scalar OU process of tests/ou_reference.py (numpy, exact discretisation), its
  state in K, read in units of 1e-6 per K (a state in other units than its output: the
  chevron's temperature read as a displacement). The rule the starts replaced (0.1 sd^2 / dt
  in the output's units) started q at 3.5e-18 K^2/s, 6e11 x below the truth, where the
  likelihood is flat: that fit ended there, q "not identifiable". Now: start 3.6e-6, estimate
  2.5e-6 [1.6e-6, 3.8e-6] (truth 2e-6).
- lag: the linear two-heater TCLab of tests/test_stochastic_device.py (numpy/scipy), heater
  noise 2e-3 K^2/s read through the sensors' 25 s lag. One frame alone would start it at
  1.17 K^2/s (~600x the truth): the noise shows on the sensor over the lag, not in a frame.
  Start 1.9e-3 (the old rule's, in the sensors' units, 9.8e-4).
"""

import dataclasses

import numpy as np
import pytest

import greybox
from greybox._estimate import likelihood as lik
from tests import ou_device as od
from tests import ou_reference as ou
from tests.rc_building_device import RCBuilding

GAIN = 1e-6  # reading units per K


class ScaledAir(RCBuilding):
    """The one-node building of tests/ou_device.py, its air temperature read as GAIN x Ti."""

    def output(self, x):
        return GAIN * x[:1]


def scaled_model(p):
    base = od.model(p).device
    dev = ScaledAir(**{f: getattr(base, f) for f in ("Ci", "Ce", "Ch", "Rie", "Rea", "Rih",
                       "Aw", "Ti0", "Te0", "Th0", "readout", "nodes", "outputs_read")})  # fmt: skip
    return greybox.stochastic.stochastic_device(dev, od.STRUCTURE, outputs=("Ti",))


def test_a_state_read_in_other_units_starts_at_its_own_scale_and_is_recovered():
    truth = dict(ou.TRUTH)
    y = GAIN * ou.simulate(truth, 400, seed=5)
    run = od.experiment(y)
    start = dict(truth, Ci=2 * truth["Ci"], Rea=0.6 * truth["Rea"])
    noise = greybox.ProcessNoise(od.STRUCTURE)
    su = lik.setup(scaled_model(start), [run], od.FREE, noise)
    q0 = float(su.sd.process.air)
    print("start q", q0, "truth", truth["q"])
    assert truth["q"] / 10 < q0 < 10 * truth["q"]

    res = greybox.fit(scaled_model(start), [run], od.FREE, noise=noise, n_starts=1)
    assert res.status == "converged", res.message
    est = {p.path: p for p in res.parameters}
    q = est["process.air"]
    print("q", q.value, q.ci95, q.verdict)
    assert q.verdict == "identifiable"
    assert q.ci95[0] < truth["q"] < q.ci95[1]
    sd = est["measurement.Ti"]
    assert sd.ci95[0] < GAIN * truth["sd"] < sd.ci95[1]


def test_a_lagged_state_starts_where_its_noise_shows():
    from tests import test_stochastic_device as tsd

    data = tsd.simulate_truth()
    sd = tsd.cli_model()
    free = tsd.physical_free() + greybox.stochastic.noise_parameters(sd, tsd.UNITS)
    su = lik.setup(sd, [data], free, greybox.ProcessNoise(sd.structure), n_starts=1)
    q0 = float(su.sd.process.heaters)
    print("start q_heaters", q0, "truth", tsd.NOISE["process.heaters"])
    assert tsd.NOISE["process.heaters"] / 5 < q0 < 5 * tsd.NOISE["process.heaters"]
    # an output walk shows most in one frame: a tenth of the measurement variance per frame
    dt = np.median(np.diff(data.t_s))
    sd_y = np.asarray([float(getattr(su.sd.measurement, c)) for c in ("T1", "T2")])
    assert float(su.sd.output_walk.shared) == pytest.approx(0.1 * np.min(sd_y**2) / dt, rel=1e-6)


def test_process_noise_is_labelled_in_the_states_unit():
    """A chevron's states are temperatures read as a displacement: its process intensities
    are K^2/s (the spec's `state_unit`), not the output's m^2/s; [noise] state_unit wins;
    a device that declares none gets the generic label, never the outputs' unit (which was
    m^2/s here); one unit per state labels each group by its states' shared unit."""
    from greybox.io._noise_table import NoiseTable, noise_units

    groups = (("states", (0,)),)
    chevron = greybox.get_device("chevron_laser")
    assert chevron.outputs[0].si_unit == "m"
    assert noise_units(chevron, NoiseTable(process_groups=groups))["process.states"] == "K^2/s"
    told = NoiseTable(process_groups=groups, state_unit="mK")
    assert noise_units(chevron, told)["process.states"] == "mK^2/s"
    undeclared = dataclasses.replace(chevron, state_unit=None)
    label = noise_units(undeclared, NoiseTable(process_groups=groups))["process.states"]
    assert label == "(state unit)^2/s"
    stage = dataclasses.replace(chevron, state_unit=("m", "m/s"))  # a position and a velocity
    mixed = NoiseTable(process_groups=(("x", (0,)), ("v", (1,)), ("both", (0, 1))))
    assert [noise_units(stage, mixed)[f"process.{g}"] for g in ("x", "v", "both")] == [
        "m^2/s",
        "(m/s)^2/s",
        "(state unit)^2/s",
    ]
    stage.check()
    for bad in (" ", (), ("m", "")):
        with pytest.raises(greybox.DeviceSpecError, match="state_unit"):
            dataclasses.replace(chevron, state_unit=bad).check()
