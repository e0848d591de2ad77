"""The RK4 substeps per sample of a nonlinear system's mechanical step, chosen per record
(``latentforce.substeps``): the count the rule picks keeps the step accurate where the default
count is unstable, the demos' systems keep their defaults, a fixed count that falls short is
warned about, and ``estimate`` applies and records the choice."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from latentforce import estimate
from latentforce import substeps as S
from latentforce.inference.particle_model import ParticleModel
from latentforce.io.config import config_from_dict
from latentforce.io.data import Dataset
from latentforce.kernels import Matern
from latentforce.models import LatentForceModel, Sensor
from latentforce.simulate import measure, simulate
from latentforce.systems import DEFAULT_BOUC_WEN_SUBSTEPS, BoucWen, Duffing, saturation

#: a smooth hysteresis loop (nu = 2) whose saturated branch relaxes fast: at 500 Hz the default
#: 4 substeps put h |lambda| at ~3.6 there, past RK4's stability bound (~2.8)
STIFF = dict(m=2.0, c=10.0, k=5e4, alpha=5e4, beta=1e3, gamma=8e2, nu=2.0)
GP = dict(force_variance=2500.0, force_lengthscale=0.02)
FS = 500.0
#: the Noël-Schoukens benchmark at its 750 Hz
BENCH = dict(m=2.0, c=10.0, k=5e4, alpha=5e4, beta=800.0, gamma=-1100.0, nu=1.0)


def _model(n, order=2):
    return LatentForceModel(BoucWen(substeps=n), Matern(order), [Sensor("velocity", 0, 0.002)])


def test_saturation_bounds_the_simulated_loop():
    """On a loading branch r' = z'(alpha - (beta + gamma)|r|^nu): |r| stays below
    (alpha / (beta + gamma))^(1/nu) from a virgin start, and reaches it under a large force."""
    sim = simulate(jax.random.key(3), _model(4), {**STIFF, **GP}, 501, 1.0 / FS, substeps=64)
    bound = float(saturation(STIFF["alpha"], STIFF["beta"], STIFF["gamma"], STIFF["nu"]))
    r = np.abs(sim.hysteretic_force)
    assert r.max() <= bound * (1 + 1e-9) and r.max() > 0.95 * bound, (r.max(), bound)
    assert np.isinf(saturation(5e4, 800.0, -1100.0, 1.0))  # the benchmark's branch stiffens


def test_the_chosen_count_keeps_the_step_accurate_where_the_default_is_unstable():
    """States of a simulated loop with the hysteretic force 0.5 N (10 % of its bound) off the path,
    as a particle cloud or a proposal puts them: the one-sample step against 512 substeps. Measured:
    at the default 4 substeps the error in r reaches 2-5x r's range (unstable), at the chosen 18
    2e-4 of it."""
    params = {**STIFF, **GP}
    n, warning = S.choose(_model(DEFAULT_BOUC_WEN_SUBSTEPS), params, 1.0 / FS, None)
    assert warning is None and n >= 3 * DEFAULT_BOUC_WEN_SUBSTEPS, n
    sim = simulate(jax.random.key(3), _model(4), params, 501, 1.0 / FS, substeps=64)
    mech = np.stack([sim.displacement[:, 0], sim.velocity[:, 0], sim.hysteretic_force[:, 0]], axis=1)
    scale = np.abs(mech).max(axis=0)
    xf = np.stack([sim.force[:, 0], np.zeros(501), np.zeros(501)], axis=1)

    def step(count, start):
        pm = ParticleModel(_model(count), params, 1.0 / FS)
        return np.asarray(jax.vmap(pm.phi)(jnp.asarray(start), jnp.asarray(xf)))

    for shift in (0.5, -0.5):
        start = mech + np.array([0.0, 0.0, shift])
        ref = step(512, start)
        err = {c: np.max(np.abs(step(c, start) - ref) / scale, axis=0) for c in (DEFAULT_BOUC_WEN_SUBSTEPS, n)}
        assert err[DEFAULT_BOUC_WEN_SUBSTEPS][2] > 0.5, err
        assert np.all(err[n] < 2e-3), err


@pytest.mark.parametrize(
    "system, params, fs, default",
    [
        (BoucWen(), {**BENCH, "force_variance": 2500.0, "force_lengthscale": 0.01}, 750.0, DEFAULT_BOUC_WEN_SUBSTEPS),
        # the Vibration 2020 Duffing case (demo duffing)
        (Duffing(), dict(m=1.0, c=20.0, k=1e4, k3=1e9, force_variance=20.0, force_lengthscale=0.1), 2048.0, 1),
    ],
    ids=["bouc-wen-benchmark", "duffing-paper"],
)
def test_the_measured_cases_keep_their_default(system, params, fs, default):
    model = LatentForceModel(system, Matern(0), [Sensor("acceleration", 0, 0.1)])
    assert S.choose(model, params, 1.0 / fs, None) == (default, None)
    # the rule scales with the step: ten times the step, more substeps
    assert S.choose(model, params, 10.0 / fs, None)[0] >= default


def test_a_fixed_count_that_falls_short_is_kept_and_warned_about_and_the_cap_says_so():
    params = {**STIFF, **GP}
    n, warning = S.choose(_model(4), params, 1.0 / FS, 4)
    assert n == 4 and "[system].substeps = 4 may be too few" in warning
    assert S.choose(_model(4), params, 1.0 / FS, 32) == (32, None)
    n, warning = S.choose(_model(4), params, 40.0 / FS, None)  # 12.5 Hz sampling: needs hundreds
    assert n == S.MAX_SUBSTEPS and "more than the 64 allowed" in warning


def _config(**system):
    return config_from_dict(
        {
            "data": {"sample_rate": FS},
            "system": {"type": "bouc-wen", **STIFF, **system},
            "force": {"kernel": "matern52", "variance": GP["force_variance"], "lengthscale": GP["force_lengthscale"]},
            "sensors": [{"column": "vel", "quantity": "velocity", "noise_std": 0.002}],
            "inference": {"method": "ekf"},
        },
        source="stiff.toml",
    )


def test_estimate_applies_the_choice_and_records_it():
    problem = _config()
    sim = simulate(jax.random.key(0), problem.model, {**STIFF, **GP}, 201, 1.0 / FS, substeps=64)
    y = np.asarray(measure(jax.random.key(1), sim, problem.model.sensors))
    dataset = Dataset(sim.time, 1.0 / FS, y, np.ones_like(y, dtype=bool), ["vel"], {})
    need = S.choose(problem.model, {**STIFF, **GP}, 1.0 / FS, None)[0]
    result, _ = estimate.run(problem, dataset)
    assert result.diagnostics["substeps"] == need > DEFAULT_BOUC_WEN_SUBSTEPS
    assert not any("substeps" in w for w in result.diagnostics.get("warnings", []))
    result, _ = estimate.run(_config(substeps=4), dataset)
    assert result.diagnostics["substeps"] == 4
    assert any("[system].substeps = 4 may be too few" in w for w in result.diagnostics["warnings"])


def test_simulate_steps_as_finely_as_the_rate_needs(tmp_path, monkeypatch):
    """``latentforce simulate`` of the stiff loop at 100 Hz (the rule asks for 90 substeps): at the 8 it
    took before, the record was NaN from its fourth sample; the rule's count keeps the loop inside its
    bound."""
    from typer.testing import CliRunner

    from latentforce.cli import app

    monkeypatch.chdir(tmp_path)
    body = "\n".join(f"{k} = {v}" for k, v in STIFF.items())
    (tmp_path / "stiff.toml").write_text(
        f'[data]\npath = "d.csv"\n[system]\ntype = "bouc-wen"\n{body}\n'
        f'[force]\nkernel = "matern52"\nvariance = 2500.0\nlengthscale = 0.02\n'
        '[[sensors]]\ncolumn = "vel"\nquantity = "velocity"\nnoise_std = 0.002\n'
    )
    out = CliRunner().invoke(
        app, ["simulate", "stiff.toml", "--out", "d.csv", "--duration", "2", "--sample-rate", "100"]
    )
    assert out.exit_code == 0, out.output
    header = (tmp_path / "d.csv").read_text().splitlines()[0].split(",")
    r = np.loadtxt(tmp_path / "d.csv", delimiter=",", skiprows=1, usecols=header.index("hysteretic_force"))
    bound = float(saturation(STIFF["alpha"], STIFF["beta"], STIFF["gamma"], STIFF["nu"]))
    assert np.all(np.isfinite(r)) and np.abs(r).max() <= bound * (1 + 1e-6), (np.abs(r).max(), bound)


def test_an_unstable_linearisation_keeps_the_count():
    """A double-well Duffing (k < 0) has no stationary sds to scale the probes by (it runs from an
    [initial] start): the rule keeps the system's count, or the config's, without a warning."""
    model = LatentForceModel(Duffing(), Matern(0), [Sensor("acceleration", 0, 0.1)])
    params = dict(m=1.0, c=20.0, k=-1e4, k3=1e9, force_variance=20.0, force_lengthscale=0.1)
    assert np.isnan(S.stiffness(model, params))
    assert S.choose(model, params, 1.0 / 2048.0, None) == (1, None)
    assert S.choose(model, params, 1.0 / 2048.0, 3) == (3, None)
    assert S.needed(model, params, 1.0 / 2048.0) == 1


def test_an_oscillation_gets_the_tighter_bound():
    """h omega = 0.8 at one substep: within the real-eigenvalue bound (1) but not the oscillation's (0.5),
    so two substeps. Over 200 samples of free vibration (25 periods) one RK4 step a sample loses 28 % of
    the amplitude to numerical damping (|R(0.8i)| = 0.9982 a step; at 0.89 it took 2 % off Silverbox's c),
    two lose 1.1 %."""
    omega, dt = 400.0, 0.8 / 400.0
    params = dict(m=1.0, c=1e-6, k=omega**2, k3=0.0, force_variance=1.0, force_lengthscale=0.1)
    model = LatentForceModel(Duffing(), Matern(0), [Sensor("acceleration", 0, 0.1)])
    assert S.choose(model, params, dt, None) == (2, None)
    assert S.stiffness(model, params) * dt < S.STEP_BOUND  # the real bound alone would keep one

    def amplitude_after(n, steps=200):
        pm = ParticleModel(LatentForceModel(Duffing(substeps=n), Matern(0), model.sensors), params, dt)
        x = jnp.array([1.0, 0.0])
        for _ in range(steps):
            x = pm.phi(x, jnp.zeros(1))
        return float(np.hypot(x[0], x[1] / omega))

    assert 1 - amplitude_after(1) > 0.2 and 1 - amplitude_after(2) < 0.02


def test_the_need_is_read_over_the_posterior_draws():
    """Draws of beta and gamma spread from the init values to the truth: the need is the stiffest
    draw's (the truth's 18), and the draw is named."""
    model = _model(DEFAULT_BOUC_WEN_SUBSTEPS)
    fixed = {k: v for k, v in {**STIFF, **GP}.items() if k not in ("beta", "gamma")}
    draws = {"beta": np.linspace(100.0, 1000.0, 10).reshape(2, 5), "gamma": np.linspace(80.0, 800.0, 10).reshape(2, 5)}
    need, at = S.needed_over_posterior(model, fixed, draws, 1.0 / FS)
    assert need == S.needed(model, {**STIFF, **GP}, 1.0 / FS) and at == {"beta": 1000.0, "gamma": 800.0}
    assert S.needed(model, {**fixed, "beta": 100.0, "gamma": 80.0}, 1.0 / FS) < need
    assert S.needed_over_posterior(model, fixed, {}, 1.0 / FS) == (DEFAULT_BOUC_WEN_SUBSTEPS, None)


def _posterior_at_truth(problem, *args):
    """What a sampler's pass returns, its beta and gamma draws at the truth (stiffer than the init)."""
    from latentforce.results import RunResult

    draws = {"beta": np.full((2, 8), STIFF["beta"]), "gamma": np.full((2, 8), STIFF["gamma"])}
    seen.append(int(problem.model.system.substeps))
    return RunResult("ekf", np.zeros(3), 1, 1, {}, {}, draws, {}, {}, [], 0.0, {}), {}


seen: list[int] = []


@pytest.mark.parametrize("fixed_count", [None, 6])
def test_a_posterior_stiffer_than_the_init_values_reruns_at_its_need(monkeypatch, fixed_count):
    """beta and gamma inferred from init values that need 6 substeps, their posterior at the truth,
    which needs 18: ``estimate`` reruns once at 18, records both counts and says so; a count fixed in
    the config is kept and warned about, naming the draw."""
    prior = lambda init: {"prior": "lognormal", "mu": float(np.log(500.0)), "sigma": 1.0, "init": init}  # noqa: E731
    extra = {} if fixed_count is None else {"substeps": fixed_count}
    problem = _config(beta=prior(100.0), gamma=prior(80.0), **extra)
    low = S.needed(problem.model, {**STIFF, **GP, "beta": 100.0, "gamma": 80.0}, 1.0 / FS)
    need = S.needed(problem.model, {**STIFF, **GP}, 1.0 / FS)
    assert low == 6 < need == 18
    y = np.zeros((11, 1))
    dataset = Dataset(np.arange(11) / FS, 1.0 / FS, y, np.ones_like(y, dtype=bool), ["vel"], {})
    monkeypatch.setattr(estimate, "_dispatch", lambda key, problem, *a: _posterior_at_truth(problem))
    monkeypatch.setattr(estimate, "force_spectrum", lambda *a, **k: None)
    seen.clear()
    result, _ = estimate.run(problem, dataset)
    warnings = result.diagnostics.get("warnings", [])
    if fixed_count is None:
        assert seen == [low, need] and result.diagnostics["substeps"] == need
        assert result.diagnostics["substeps_first_pass"] == low
        assert not any("may be inaccurate" in w for w in warnings), warnings
        # the second pass is said (the user sees the progress bar start again, and twice the time)
        assert any("made twice" in w and f"more than the {low}" in w and f"rerun with {need}" in w for w in warnings)
    else:
        assert seen == [fixed_count] and result.diagnostics["substeps"] == fixed_count
        assert any("beta = 1000, gamma = 800" in w and f"needs {need} RK4 substeps" in w for w in warnings), warnings


@pytest.mark.parametrize("fixed_count", [None, 6])
def test_a_posterior_within_the_rerun_bound_keeps_the_count_without_a_word(monkeypatch, fixed_count):
    """beta and gamma 4x their init values at the posterior: the accuracy bound asks for 12 substeps
    against the 6 used, but h |lambda| stays within RERUN_BOUND (6 would do there), so the first pass
    stands, no rerun, no warning (a rerun doubles the user's time; short of that bound it measured no
    change). 6x (14 needed, 7 within the bound) reruns at the accuracy bound's 14."""
    prior = lambda init: {"prior": "lognormal", "mu": float(np.log(500.0)), "sigma": 1.0, "init": init}  # noqa: E731
    extra = {} if fixed_count is None else {"substeps": fixed_count}
    problem = _config(beta=prior(100.0), gamma=prior(80.0), **extra)
    y = np.zeros((11, 1))
    dataset = Dataset(np.arange(11) / FS, 1.0 / FS, y, np.ones_like(y, dtype=bool), ["vel"], {})
    monkeypatch.setattr(estimate, "force_spectrum", lambda *a, **k: None)
    for factor, expected in ((4.0, [6]), (6.0, [6] if fixed_count else [6, 14])):
        at = {**STIFF, **GP, "beta": 100.0 * factor, "gamma": 80.0 * factor}
        assert S.needed(problem.model, at, 1.0 / FS) > 6  # past the accuracy bound either way

        def dispatch(key, problem, *a, factor=factor):
            from latentforce.results import RunResult

            draws = {"beta": np.full((2, 8), 100.0 * factor), "gamma": np.full((2, 8), 80.0 * factor)}
            seen.append(int(problem.model.system.substeps))
            return RunResult("ekf", np.zeros(3), 1, 1, {}, {}, draws, {}, {}, [], 0.0, {}), {}

        monkeypatch.setattr(estimate, "_dispatch", dispatch)
        seen.clear()
        result, _ = estimate.run(problem, dataset)
        warned = any("may be inaccurate" in w for w in result.diagnostics.get("warnings", []))
        assert seen == expected and result.diagnostics["substeps"] == expected[-1], (factor, seen)
        assert warned == (factor == 6.0 and fixed_count is not None), (factor, result.diagnostics)
        twice = any("made twice" in w for w in result.diagnostics.get("warnings", []))
        assert twice == (len(expected) == 2), (factor, result.diagnostics)


def test_a_rerun_that_fails_leaves_the_first_pass_with_a_warning(monkeypatch):
    """The rerun at the posterior's need is a second full run: when it raises, the first pass (minutes
    of sampling) is still the user's result, with a warning naming the failure and the counts."""
    prior = lambda init: {"prior": "lognormal", "mu": float(np.log(500.0)), "sigma": 1.0, "init": init}  # noqa: E731
    problem = _config(beta=prior(100.0), gamma=prior(80.0))
    y = np.zeros((11, 1))
    dataset = Dataset(np.arange(11) / FS, 1.0 / FS, y, np.ones_like(y, dtype=bool), ["vel"], {})

    def dispatch(key, problem, *a):
        if seen:
            seen.append(int(problem.model.system.substeps))
            raise np.linalg.LinAlgError("Matrix is not positive definite")
        return _posterior_at_truth(problem)

    monkeypatch.setattr(estimate, "_dispatch", dispatch)
    monkeypatch.setattr(estimate, "force_spectrum", lambda *a, **k: None)
    seen.clear()
    result, _ = estimate.run(problem, dataset)
    assert seen == [6, 18] and result.diagnostics["substeps"] == 6
    assert "substeps_first_pass" not in result.diagnostics
    (warning,) = [w for w in result.diagnostics.get("warnings", []) if "RK4 substeps" in w]
    assert "the rerun at its need failed (LinAlgError: Matrix is not positive definite)" in warning
    assert "needs 18 RK4 substeps" in warning and "than the 6 this run used" in warning
