"""The force spectrum: the Matérn prior's one-sided PSD, Welch on a long GP sample, force_psd.csv."""

import csv

import jax
import numpy as np
import pytest
from scipy import integrate

import latentforce  # noqa: F401  (enables float64)
from latentforce import estimate
from latentforce.io.config import config_from_dict
from latentforce.io.data import Dataset
from latentforce.kernels import Matern
from latentforce.models import LatentForceModel, Sensor
from latentforce.results import read_results, write_results
from latentforce.simulate import gp_force
from latentforce.spectrum import prior_psd, welch_psd
from latentforce.systems import LinearSystem


@pytest.mark.parametrize("p", [0, 1, 2, 3])
def test_prior_psd_is_one_sided_and_integrates_to_the_variance(p):
    """int_0^inf G(f) df = sigma^2 (one-sided in hertz, as welch's density)."""
    kernel = Matern(p)
    variance, lengthscale = 3.7, 0.35
    total, err = integrate.quad(
        lambda f: prior_psd(kernel, variance, lengthscale, np.array([f]))[0], 0.0, np.inf, limit=200
    )
    assert abs(total - variance) < 1e-6 * variance, (total, err)


@pytest.mark.parametrize("p", [0, 1])
def test_welch_of_a_long_matern_sample_matches_the_prior_psd(p):
    """A long exact sample of the GP force: its Welch density agrees with the prior's (aliasing
    negligible below fs/10; ~255 averaged segments: ~6 % scatter per frequency)."""
    kernel = Matern(p)
    model = LatentForceModel(LinearSystem(), kernel, [Sensor("displacement", 0, 1.0)])
    params = dict(m=1.0, c=1.0, k=1.0, force_variance=2.5, force_lengthscale=0.4)
    dt, n = 0.01, 2**17
    u = np.asarray(gp_force(jax.random.key(11), model, params, n, dt))[:, 0]
    freq, psd = welch_psd(u, dt, nperseg=1024)
    band = (freq > 0.3) & (freq < 10.0)
    prior = prior_psd(kernel, 2.5, 0.4, freq[band])
    ratio = psd[band] / prior
    assert abs(np.mean(np.log(ratio))) < 0.05, np.mean(np.log(ratio))  # no bias (a factor 2 fails)
    assert np.all(np.abs(np.log(ratio)) < 0.3), ratio.min()
    # and the wrong lengthscale does not fit
    wrong = prior_psd(kernel, 2.5, 0.6, freq[band])
    assert np.mean(np.abs(np.log(psd[band] / wrong))) > 0.15


def test_force_psd_csv_and_figure(tmp_path):
    d = {
        "system": {"type": "linear", "m": 1.0, "c": 0.4, "k": 10.0},
        "force": {"kernel": "matern32", "variance": 1.0, "lengthscale": 0.5},
        "sensors": [
            {"column": "acc", "quantity": "acceleration", "noise_std": 0.2},
            {"column": "load", "quantity": "force", "noise_std": 0.1},
        ],
        "inference": {"method": "kalman"},
    }
    problem = config_from_dict(d, source="c.toml")
    T = 300
    rng = np.random.default_rng(1)
    y = rng.normal(size=(T, 2))
    ds = Dataset(np.arange(T) * 0.05, 0.05, y, np.ones((T, 2), bool), ["acc", "load"], {"force": rng.normal(size=T)})
    result, _ = estimate.run(problem, ds, seed=0)
    write_results(tmp_path / "o", result)
    with open(tmp_path / "o" / "force_psd.csv") as f:
        rows = list(csv.reader(f))
    assert rows[0] == ["frequency", "psd_mean", "psd_q05", "psd_q95", "prior_psd", "truth_psd"]
    table = np.array(rows[1:], dtype=float)
    assert table.shape == (129, 6) and np.all(np.isfinite(table))
    assert np.all(table[:, 2] <= table[:, 1]) and np.all(table[:, 1] <= table[:, 3])
    assert (tmp_path / "o" / "figures" / "force_psd.png").is_file()
    back = read_results(tmp_path / "o")
    np.testing.assert_array_equal(back.force_psd["psd_q95"], table[:, 3])
