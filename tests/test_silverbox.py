"""The Silverbox demo (real data): the bundled copy of the benchmark, the inversion baselines,
the configs, the figures, and ``demo silverbox --quick`` end to end."""

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from latentforce.cli import app
from latentforce.demos import silverbox as sb
from latentforce.io.config import config_from_dict

ORIGINAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "silverbox" / "SNLS80mV.csv"
ORIGINAL_SHA256 = "ae62d5a91230c10f76e6dd02c8a4fac3c9d4d8a95fbf50e87cb0c4885003e0f1"


def test_the_bundled_copy_is_the_benchmark():
    u, y = sb.load()
    assert u.shape == y.shape == (131_072,)
    assert abs(u.mean()) < 1e-12 and abs(y.mean()) < 1e-12
    if not ORIGINAL.is_file():
        pytest.skip(f"the original file is not beside the repository ({ORIGINAL})")
    raw = ORIGINAL.read_bytes()
    assert hashlib.sha256(raw).hexdigest() == ORIGINAL_SHA256
    d = np.genfromtxt(ORIGINAL, delimiter=",", skip_header=1)[:, :2]
    # float32 of a 5-significant-digit text: relative to the signal's range, below 1e-7
    np.testing.assert_allclose(u, d[:, 0] - d[:, 0].mean(), rtol=0, atol=1e-7 * np.ptp(d[:, 0]))
    np.testing.assert_allclose(y, d[:, 1] - d[:, 1].mean(), rtol=0, atol=1e-7 * np.ptp(d[:, 1]))


def test_the_windows_are_where_the_benchmark_says():
    """The calibration sits inside the first multisine realisation (input active throughout),
    the arrow windows inside the arrow, with amplitude growing low -> mid -> high."""
    u, _ = sb.load()
    cal = u[sb.CALIBRATION_START : sb.CALIBRATION_START + sb.CALIBRATION]
    blocks = cal[: len(cal) // 64 * 64].reshape(-1, 64)
    assert np.all(np.std(blocks, axis=1) > 0.005)  # no zero-input gap inside
    rms = [np.std(u[s : s + sb.WINDOW]) for s in (sb.ARROW["low"], sb.ARROW["mid"], sb.ARROW["high"])]
    assert rms[0] < rms[1] < rms[2]
    assert sb.ARROW["high"] + sb.WINDOW + sb.MARGIN < 40_502  # before the gap that ends the arrow


def test_the_fft_inversion_is_exact_for_a_band_limited_signal():
    """u = m y'' + c y' + k y + k3 y^3 from y: exact (to round-off) with FFT derivatives for a
    periodic band-limited y; central differences carry their known O((w dt)^2) error."""
    n, dt = 1024, 1.0 / sb.FS
    t = np.arange(n) * dt
    rng = np.random.default_rng(0)
    y, v, a = np.zeros(n), np.zeros(n), np.zeros(n)
    for j in rng.choice(np.arange(5, 300), 20, replace=False):  # periodic in the window, below 175 Hz
        w, ph, amp = 2 * np.pi * j / (n * dt), rng.uniform(0, 2 * np.pi), rng.uniform(0.005, 0.02)
        y += amp * np.sin(w * t + ph)
        v += amp * w * np.cos(w * t + ph)
        a -= amp * w**2 * np.sin(w * t + ph)
    p = {"m": 5.3e-6, "c": 2.2e-4, "k": 1.0, "k3": 3.5}
    u = p["m"] * a + p["c"] * v + p["k"] * y + p["k3"] * y**3
    from latentforce.results import nmse

    assert nmse(u, sb.inversion(y, p, spectral=True)) < 1e-12
    central = nmse(u, sb.inversion(y, p, spectral=False))
    assert 0.01 < central < 50.0
    # the baseline rows score the window only, computed with the record around it
    rows = sb._baseline_rows("w", y, slice(200, 800), u[200:800], p)
    assert [r[1] for r in rows] == ["inversion, central differences", "inversion, FFT derivatives"]
    assert float(rows[1][2]) < 0.01


def test_the_configs_are_valid():
    for linear in (False, True):
        problem = config_from_dict(sb.calibration_config(linear, seed=3), source="calibration.toml")
        names = {"m", "c", "k", "force_variance", "force_lengthscale", "noise_std_u", "noise_std_y"}
        assert set(problem.free) == names | (set() if linear else {"k3"})
        assert {s.quantity for s in problem.model.sensors} == {"force", "displacement"}
    mon = sb.monitoring_config("../calibration/", False, seed=0)
    assert mon["system"]["k3"] == {"prior": "posterior", "from": "../calibration/"}
    assert mon["sensors"][0]["noise_std"]["param"] == "noise_std_y" and "initial" not in mon
    # an arrow window starts in motion: given its output, the Duffing's first state is wide
    y = 0.1 * np.sin(2 * np.pi * 70.0 * np.arange(512) / sb.FS)
    mon = sb.monitoring_config("../calibration/", False, seed=0, y=y)
    assert mon["initial"]["sd"][0] == pytest.approx(3 * 0.1 / np.sqrt(2), rel=0.01)
    # (the velocity by central differences: 8 % low at 70 Hz against 610 Hz)
    assert mon["initial"]["sd"][1] == pytest.approx(3 * 0.1 * 2 * np.pi * 70.0 / np.sqrt(2), rel=0.1)
    assert "initial" not in sb.monitoring_config("../calibration-linear/", True, seed=0, y=y)


@pytest.fixture(scope="module")
def quick_demo(tmp_path_factory):
    root = tmp_path_factory.mktemp("silverbox")
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(root)
        result = CliRunner().invoke(app, ["demo", "silverbox", "--quick", "--out", "d"])
    assert result.exit_code == 0, result.output
    return root / "d", result.output


def test_the_quick_demo_calibrates_then_recovers_the_measured_input(quick_demo):
    out, text = quick_demo
    for folder in ("calibration", "calibration-linear", "arrow-high", "arrow-high/linear"):
        summary = json.loads((out / folder / "summary.json").read_text())
        assert isinstance(summary["converged"], bool), folder
        assert (out / folder / "posterior.nc").is_file(), folder
    cal = json.loads((out / "calibration" / "summary.json").read_text())
    assert {"m", "c", "k", "k3", "noise_std_u", "noise_std_y"} <= set(cal["parameters"])
    mon = json.loads((out / "arrow-high" / "summary.json").read_text())
    assert set(mon["diagnostics"]["carried_priors"]) >= {"[system].m", "[system].k3"}
    assert "force" in mon["nmse"]  # scored against the measured input
    assert not any("no sensor measures the force" in w for w in mon["diagnostics"].get("warnings", []))
    assert not any("start in motion" in w for w in mon["diagnostics"].get("warnings", []))  # [initial] given
    table = (out / "silverbox.md").read_text()
    for row in ("Duffing, ukf", "linear, kalman-mcmc", "inversion, FFT derivatives"):
        assert row in table
    for fig in ("input_high.png", "restoring_force.png"):
        assert (out / "figures" / fig).stat().st_size > 10_000, fig
    # a sane identification of the circuit: resonance near 70 Hz, static gain near 1
    med = {n: cal["parameters"][n]["median"] for n in ("m", "k")}
    assert 60 < np.sqrt(med["k"] / med["m"]) / (2 * np.pi) < 80
    assert 0.8 < med["k"] < 1.2
