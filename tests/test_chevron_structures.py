"""Structural options of the thermal chevrons: thermal chains, an elongation lag and geometry.

The truth for the recovery test is an independent numpy/scipy simulator: the 2-node RC chain
with the elongation lag propagated by matrix-exponential ZOH on a fine grid, the exact
rigid-link kinematics, and the camera exposure averaged by the trapezoid rule (the library
uses Gauss-Legendre nodes and per-interval ZOH). The data go through an experiment folder
(experiment.toml + CSVs) and `greybox.io.load_experiment_set`, as a user's would.
"""

import math

import numpy as np
import pytest
import scipy.linalg
from scipy.special import erf

import greybox
from greybox.io import load_experiment_set

SPEC = greybox.get_device("chevron_laser")
CL = greybox.device_module("chevron_laser")
ET = greybox.get_device("electrothermal_chevron")

# Si and the thesis geometry, restated (PHYSICS.md §4, §12)
K_SI, RHO_CP = 148.0, 1.64e6
L, W, H, PAD = 3.5e-3, 20e-6, 100e-6, 200e-6
ANGLE = math.radians(2.0)
CTE = 2.6e-6
WAIST = 150e-6
G_AIR = (RHO_CP * (2 * L * W * H + PAD**2 * H) / 0.040 - 2 * K_SI * W * H / L) / (
    2 * L * W + PAD**2
)

# Truth of the 2-node + lag device (nominal: A 0.67, R 2956 / 2956 K/W, lag 10 ms)
TRUE = {
    "absorptance": 0.55,
    "thermal.resistance_K_per_W[0]": 4400.0,
    "thermal.resistance_K_per_W[1]": 2100.0,
    "thermal.lag_s": 0.004,
}
FPS, EXPOSURE_S, UM_PER_PX, NOISE_PX = 250.0, 0.002, 0.645, 0.03
DT = 1e-4  # fine grid of the reference simulator [s]
# (name, power mW, period ms, pulses); 50 % duty, 100 ms before and 200 ms after
RUNS = [("a_20mW_160ms", 20, 160, 5), ("b_30mW_60ms", 30, 60, 8)]
DELAY_MS, TAIL_MS = 100, 200


def true_matrices():
    """(A, B) of pad, beam and lag states per absorbed watt, from the closed-form geometry."""
    c = np.array([RHO_CP * PAD**2 * H, RHO_CP * 2 * L * W * H])
    r01, r1g = TRUE["thermal.resistance_K_per_W[0]"], TRUE["thermal.resistance_K_per_W[1]"]
    ga = np.array([G_AIR * PAD**2, G_AIR * 2 * L * W])
    lag = TRUE["thermal.lag_s"]
    a = np.array(
        [
            [-(1 / r01 + ga[0]) / c[0], 1 / r01 / c[0], 0.0],
            [1 / r01 / c[1], -(1 / r01 + 1 / r1g + ga[1]) / c[1], 0.0],
            [0.0, 1 / lag, -1 / lag],
        ]
    )
    return a, np.array([1 / c[0], 0.0, 0.0])


def stroke_m(theta_beam_K):
    """Exact rigid-link chevron (PHYSICS.md §6), bare shuttle."""
    dl = CTE * L * theta_beam_K
    return np.sqrt(L**2 * np.sin(ANGLE) ** 2 + 2 * L * dl + dl**2) - L * np.sin(ANGLE)


def simulate_run(power_mW, period_ms, n_pulses, offset_px, rng):
    """(frame times [s], readings [px]) of one pulse-train run, independent of greybox."""
    spot_fraction = erf(math.sqrt(2) * (PAD / 2) / WAIST) ** 2  # Gaussian on the square pad
    q_on = TRUE["absorptance"] * spot_fraction * power_mW * 1e-3
    a, b = true_matrices()
    n_steps = round((DELAY_MS + n_pulses * period_ms + TAIL_MS) * 1e-3 / DT)
    t = np.arange(n_steps + 1) * DT
    # ZOH over one fine step: [x; u] -> expm of the augmented matrix
    aug = np.zeros((4, 4))
    aug[:3, :3], aug[:3, 3] = a, b
    phi = scipy.linalg.expm(aug * DT)
    step_ms = np.arange(n_steps) * DT * 1e3 + 1e-6
    on = (step_ms >= DELAY_MS) & (step_ms < DELAY_MS + n_pulses * period_ms)
    on &= ((step_ms - DELAY_MS) % period_ms) < 0.5 * period_ms
    x = np.zeros((n_steps + 1, 3))
    for k in range(n_steps):
        x[k + 1] = phi[:3, :3] @ x[k] + phi[:3, 3] * (q_on if on[k] else 0.0)
    y = stroke_m(x[:, 2])
    frames = np.arange(1, int(t[-1] * FPS) + 1) / FPS
    per_exposure = round(EXPOSURE_S / DT)
    z = []
    for tf in frames:
        k = round(tf / DT)
        z.append(np.trapezoid(y[k - per_exposure : k + 1], dx=DT) / EXPOSURE_S)
    px = np.asarray(z) / (UM_PER_PX * 1e-6) + offset_px + NOISE_PX * rng.standard_normal(len(z))
    return frames, px, a


def write_folder(folder, model_table: str):
    folder.mkdir()
    runs = []
    for name, p, period, n in RUNS:
        runs.append(
            f'[[runs]]\nname = "{name}"\nfile = "{name}.csv"\nrole = "estimation"\n'
            f'waveform = {{ type = "pulse_train", power_mW = {p}, period_ms = {period}, '
            f"duty = 0.5, n_pulses = {n}, delay_ms = {DELAY_MS}, tail_ms = {TAIL_MS} }}\n"
        )
    (folder / "experiment.toml").write_text(
        '[experiment]\ndevice = "chevron_laser"\n\n'
        f"[model]\n{model_table}\n\n"
        f"[camera]\nfps = {FPS}\nexposure_ms = {EXPOSURE_S * 1e3}\num_per_px = {UM_PER_PX}\n\n"
        '[fit]\nloss = "l2"\n\n' + "\n".join(runs)
    )


@pytest.fixture(scope="module")
def data_folders(tmp_path_factory):
    """The same synthetic CSVs in two folders: [model] 2 nodes + lag, and the default 1 node."""
    root = tmp_path_factory.mktemp("structures")
    two, one = root / "two_node", root / "one_node"
    write_folder(two, "thermal_nodes = 2\nelongation_lag = true")
    write_folder(one, "thermal_nodes = 1")
    rng = np.random.default_rng(7)
    for i, (name, p, period, n) in enumerate(RUNS):
        t, px, _ = simulate_run(p, period, n, 300.0 + 2.0 * i, rng)
        text = "t_s,y_px\n" + "".join(f"{a:.6f},{b:.5f}\n" for a, b in zip(t, px))
        for folder in (two, one):
            (folder / f"{name}.csv").write_text(text)
    return two, one


def fit_folder(folder):
    es = load_experiment_set(folder)
    return es, greybox.fit(es.model, es.estimation, es.free, **es.fit_options)


@pytest.fixture(scope="module")
def two_node_fit(data_folders):
    return fit_folder(data_folders[0])


@pytest.fixture(scope="module")
def one_node_fit(data_folders):
    return fit_folder(data_folders[1])


def true_time_constants_s():
    return np.sort(-1.0 / np.linalg.eigvals(true_matrices()[0]).real)


def test_two_node_lag_recovers_independent_truth(two_node_fit):
    es, result = two_node_fit
    assert es.options["thermal_nodes"] == 2 and es.options["elongation_lag"] is True
    assert result.converged
    assert {p.path for p in es.free} >= set(TRUE)
    z = {}
    for path, truth in TRUE.items():
        est = result.estimate(path)
        assert est.verdict == "identifiable", (path, est)
        z[path] = (est.value - truth) / est.se
        print(f"{path}: {est.value:.6g} +- {est.se:.3g} (truth {truth:g}, z = {z[path]:+.2f})")
    print("true time constants [s]:", true_time_constants_s())
    assert all(abs(v) < 3.0 for v in z.values()), z
    for run, percent in result.fit_percent.items():
        assert float(np.min(percent)) > 90.0, (run, percent)


def test_one_node_structure_misfits_the_same_data(two_node_fit, one_node_fit):
    _, two = two_node_fit
    es, one = one_node_fit
    assert isinstance(es.model.thermal, greybox.blocks.FirstOrderThermal)
    tau = one.estimate("thermal.tau_s")
    z_tau = [(tau.value - t) / tau.se for t in true_time_constants_s()]
    print("one-node tau", tau.value, "+-", tau.se, "z vs true time constants", z_tau)
    noise_m = NOISE_PX * UM_PER_PX * 1e-6
    print("residual sd [m]", one.sigma, "vs", two.sigma, "(noise", noise_m, ")")
    print("fit %", one.fit_percent, "vs", two.fit_percent)
    assert min(abs(v) for v in z_tau) > 10.0
    # the 2-node fit leaves the noise; the 1-node fit leaves several times more
    np.testing.assert_allclose(float(np.max(two.sigma)), noise_m, rtol=0.15)
    assert float(np.min(one.sigma)) > 4.0 * noise_m
    for run in two.fit_percent:
        assert float(np.max(one.fit_percent[run])) < float(np.min(two.fit_percent[run])) - 3.0


def test_library_matches_reference_simulator():
    """The loaded model at the true values reproduces the reference data (noise-free)."""
    model = SPEC.model({"thermal_nodes": 2, "elongation_lag": True})
    for path, value in TRUE.items():
        model = greybox.parameters.set_values(model, [path], [value])
    a_lib, _ = model.linear_dynamics()
    np.testing.assert_allclose(np.asarray(a_lib), true_matrices()[0], rtol=1e-12)
    fraction = float(model.target.fraction(model.spot))
    np.testing.assert_allclose(fraction, erf(math.sqrt(2) * (PAD / 2) / WAIST) ** 2, rtol=1e-9)


@pytest.mark.parametrize("length_um", [250.0, 1000.0, 3500.0, 6000.0])
def test_beam_length_sets_nominal_resistance_and_stroke(length_um):
    ell = length_um * 1e-6
    model = SPEC.model(beam_length_um=length_um)
    # one place for the length: elongation and kinematics agree
    assert model.elongation.length_m == model.kinematics.length_m == pytest.approx(ell, rel=1e-15)
    # closed form: G = 2 k w h / L + g_air (2 L w + P^2), C = rho c_p (2 L w h + P^2 h)
    g = 2 * K_SI * W * H / ell + G_AIR * (2 * ell * W + PAD**2)
    c = RHO_CP * (2 * ell * W * H + PAD**2 * H)
    np.testing.assert_allclose(float(model.thermal.resistance_K_per_W), 1 / g, rtol=1e-12)
    np.testing.assert_allclose(float(model.thermal.tau_s), c / g, rtol=1e-12)
    # small-signal stroke per watt: A F R kappa alpha L / sin(a)
    fraction = erf(math.sqrt(2) * (PAD / 2) / WAIST) ** 2
    expected = 0.67 * fraction * (1 / g) * 0.5 * CTE * ell / math.sin(ANGLE)
    np.testing.assert_allclose(float(model.static_gain_m_per_W()), expected, rtol=1e-9)
    # a 2-node chain from the same geometry: steady beam rise per pad watt, by hand
    chain = SPEC.model(beam_length_um=length_um, thermal_nodes=2).thermal
    r_beam = ell / (2 * K_SI * W * H)
    np.testing.assert_allclose(chain.resistance_K_per_W, (r_beam / 2, r_beam / 2), rtol=1e-12)
    np.testing.assert_allclose(
        chain.capacity_J_per_K, (RHO_CP * PAD**2 * H, RHO_CP * 2 * ell * W * H), rtol=1e-12
    )


def test_default_geometry_is_bit_for_bit_the_thesis_device():
    m = SPEC.model()
    assert m.thermal.tau_s == 0.040
    assert m.thermal.resistance_K_per_W == 0.040 / (RHO_CP * (2 * L * W * H + PAD**2 * H))
    assert m.thermal.resistance_K_per_W == CL.NOMINAL_RESISTANCE_K_PER_W
    assert m.kinematics.length_m == 3.5e-3 and m.kinematics.angle_rad == np.deg2rad(2.0)


def test_lengths_cannot_disagree():
    from greybox.blocks import ChevronExact

    m = SPEC.model()
    with pytest.raises(ValueError, match="beam length is stated once"):
        type(m)(
            **{
                **{f: getattr(m, f) for f in m.__dataclass_fields__},
                "kinematics": ChevronExact(length_m=250e-6, angle_rad=m.kinematics.angle_rad),
            }
        )


@pytest.mark.parametrize(
    "spec, options",
    [
        (SPEC, {"thermal_nodes": 2, "elongation_lag": True}),
        (SPEC, {"thermal_nodes": 4}),
        (SPEC, {"thermal_nodes": 1, "elongation_lag": True}),
        (ET, {"thermal_nodes": 3, "elongation_lag": True}),
    ],
)
def test_every_listed_path_is_a_freeable_scalar(spec, options):
    model = spec.model(options)
    table = spec.parameter_table(options)
    for p in table:
        value = greybox.parameters.check_scalar_path(model, p.path)
        assert p.lower is None or p.lower <= value <= p.upper, p
    assert {f.path for f in spec.free_parameters(options)} <= {p.path for p in table}


def test_one_step_fit_frees_a_tuple_element(data_folders):
    """`thermal.capacity_J_per_K[1]` is freed like any scalar (a short fit moves it)."""
    es = load_experiment_set(data_folders[0])
    free = [
        greybox.FreeParameter("thermal.capacity_J_per_K[1]", unit="J/K", lower=1e-6, upper=1e-3),
        *(f for f in es.free if f.path == "camera.offset_m"),
    ]
    result = greybox.fit(es.model, es.estimation, free, max_steps=2, method="zoh", loss="l2")
    start = float(es.model.thermal.capacity_J_per_K[1])
    fitted = result.estimate("thermal.capacity_J_per_K[1]").value
    assert np.isfinite(fitted) and fitted != start


def test_residual_test_flags_the_wrong_structure_and_compare_prefers_the_right_one(
    data_folders, two_node_fit, one_node_fit, tmp_path
):
    """The one-node fit of two-node data says its residuals are not white; `greybox compare`
    fits both candidates from the folder and prefers the two-node structure by AIC."""
    import json
    import shutil

    from greybox.cli import main

    assert not one_node_fit[1].residuals.all_white
    assert "misses" in one_node_fit[1].residuals.verdict
    assert two_node_fit[1].residuals.all_white, two_node_fit[1].residuals.verdict
    folder = tmp_path / "candidates"
    shutil.copytree(data_folders[0], folder)
    with open(folder / "experiment.toml", "a") as fh:
        fh.write(
            '\n[[candidates]]\nname = "one node"\nmodel = { thermal_nodes = 1, '
            'elongation_lag = false }\n\n[[candidates]]\nname = "two nodes + lag"\n'
            "model = { thermal_nodes = 2, elongation_lag = true }\n"
        )
    out = tmp_path / "compare"
    assert main(["compare", str(folder), "--out", str(out), "--quiet"]) == 0
    doc = json.loads((out / "compare.json").read_text())
    assert doc["preferred"] == "two nodes + lag"
    aic = {c["name"]: c["aic"] for c in doc["candidates"]}
    assert aic["two nodes + lag"] < aic["one node"] - 100
    assert "Preferred: two nodes + lag" in (out / "compare.md").read_text()
    # every candidate carries its headline verdict; the preferred one is a usable fit
    heads = {c["name"]: c["headline"] for c in doc["candidates"]}
    assert heads["two nodes + lag"]["verdict"] == "valid", heads["two nodes + lag"]
    assert heads["one node"]["verdict"] in ("structure rejected", "physically implausible")


def test_a_structure_that_fits_worse_than_one_nested_in_it_is_flagged():
    # the larger structure contains the nested one, so its maximum likelihood is at least as
    # high: a lower value is a local optimum; different options are never nested
    from greybox._estimate.compare import CandidateScore, nested_pairs

    def cand(name, free, loglik, options=None):
        return CandidateScore(
            name, options or {"n": 1}, tuple(free), len(free), 100, loglik, 0.0, 0.0,
            {}, {}, "", "converged", True, "",
        )  # fmt: skip

    scores = [
        cand("a", ["x"], -10.0),
        cand("a+y", ["x", "y"], -12.0),  # worse than its nested candidate
        cand("a+z", ["x", "z"], -9.0),  # better: fine
        cand("other", ["x", "y"], -50.0, {"n": 2}),  # other options: not nested
    ]
    assert nested_pairs(scores) == [(1, 0)]
