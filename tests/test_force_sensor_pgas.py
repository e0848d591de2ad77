"""A load cell and virtual sensors under pgas (the particle methods' readout) against the exact smoother."""

import jax
import numpy as np

import latentforce  # noqa: F401  (enables float64)
from latentforce import estimate
from latentforce.inference.smc import ParticleModel
from latentforce.io.config import config_from_dict
from latentforce.io.data import Dataset
from latentforce.simulate import measure, simulate


def _config(method):
    inference = {"method": method}
    if method == "pgas":
        inference.update(particles=32, iterations=600, burn_in=100, chains=4, state_every=1, seed=3)
    return {
        "system": {"type": "linear", "m": 1.0, "c": 0.4, "k": 10.0},
        "force": {"kernel": "matern12", "variance": 1.0, "lengthscale": 0.5},
        "sensors": [
            {"column": "disp", "quantity": "displacement", "noise_std": 0.02},
            {"column": "load", "quantity": "force", "noise_std": 0.05},
        ],
        "outputs": [
            {"name": "spring", "unit": "N", "displacement": [10.0]},
            {"name": "acc", "unit": "m/s^2", "acceleration": [1.0]},
        ],
        "inference": inference,
    }


def test_pgas_with_a_load_cell_matches_the_exact_smoother():
    exact_problem = config_from_dict(_config("kalman"), source="c.toml")
    problem = config_from_dict(_config("pgas"), source="c.toml")
    model = problem.model
    params = dict(m=1.0, c=0.4, k=10.0, force_variance=1.0, force_lengthscale=0.5)
    # the particle methods' readout has the Kalman rows (load cell: the force state)
    pm = ParticleModel(model, params, 0.05)
    _, _, H_pm, _, _ = pm.linear_discrete(pm.transition(1.0, 0.5))
    H, _ = model.observation(params)
    np.testing.assert_allclose(H_pm, H, atol=1e-12)

    T, dt = 80, 0.05
    sim = simulate(jax.random.key(4), model, params, T, dt)
    y = measure(jax.random.key(5), sim, model.sensors)
    mask = np.ones(y.shape, bool)
    mask[30:50, 1] = False  # the load cell measured only part of the time
    y[~mask] = np.nan
    ds = Dataset(sim.time, dt, y, mask, ["disp", "load"], {})
    exact, _ = estimate.run(exact_problem, ds, seed=0)
    out, _ = estimate.run(problem, ds)

    # a load cell with small noise pins the force where it measured (exact and sampled)
    seen = mask[:, 1]
    for r in (exact, out):
        assert np.mean(np.abs(r.state_mean["force"][seen, 0] - y[seen, 1]) < 3 * 0.05) > 0.95
    assert exact.state_sd["force"][~seen, 0].max() > 3 * exact.state_sd["force"][seen, 0].max()
    for name in ("displacement", "force", "spring", "acc"):
        m_ex, s_ex = exact.state_mean[name][:, 0], exact.state_sd[name][:, 0]
        m, s = out.state_mean[name][:, 0], out.state_sd[name][:, 0]
        nmse = np.mean((m - m_ex) ** 2) / np.var(m_ex)
        # measured (seed 3): NMSE 1e-6 to 1e-4, mean |sd ratio - 1| 0.014 to 0.024
        assert nmse < 1e-3, (name, nmse)
        assert np.mean(np.abs(s / s_ex - 1.0)) < 0.06, (name, s / s_ex)
    # the outputs are those of the stored paths; the force spectrum from them
    p = out.path_draws
    assert p["spring"].shape == p["displacement"].shape
    np.testing.assert_allclose(p["spring"], 10.0 * p["displacement"], rtol=1e-12)
    np.testing.assert_allclose(
        out.state_mean["acc"][:, 0],
        (p["force"] - 0.4 * p["velocity"] - 10.0 * p["displacement"]).mean(axis=(0, 1))[:, 0],
        rtol=1e-9,
        atol=1e-12,
    )
    assert out.force_psd is not None and np.all(np.isfinite(out.force_psd["psd_mean"]))
    assert out.outputs == {"spring": "N", "acc": "m/s^2"}
