"""Particle Gibbs (``pgas``) inferring a sensor's noise level (``noise_std`` given as a prior table)
against exact answers: the Gibbs step on its own (Geweke's joint-distribution check), and a
whole run through ``estimate.run`` against the quadrature of the Kalman marginal likelihood."""

import copy
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_pgas import _batch_se, _on_grid

import latentforce  # noqa: F401
from latentforce import estimate
from latentforce.errors import LatentForceError
from latentforce.inference import latent, noise_gibbs, particle_model, pgas_block, pgas_output
from latentforce.inference.hyper_moves import Hyper, init_proposal
from latentforce.inference.kalman import kalman_smoother
from latentforce.io.config import config_from_dict
from latentforce.io.data import Dataset
from latentforce.kernels import Matern
from latentforce.models import LatentForceModel, Sensor, StateLayout
from latentforce.priors import HalfNormal, LogNormal
from latentforce.systems import LinearSystem

PARAMS = dict(m=1.0, c=0.4, k=10.0, force_variance=1.0, force_lengthscale=0.5)
DT, T = 0.05, 120
PRIOR = {"prior": "lognormal", "mu": float(np.log(0.05)), "sigma": 1.0}  # starts (median) at 0.05
CONFIG = {
    "system": {"type": "linear", "m": 1.0, "c": 0.4, "k": 10.0},
    "force": {"kernel": "matern32", "variance": 1.0, "lengthscale": 0.5},
    "sensors": [
        {"column": "disp", "quantity": "displacement", "dof": 0, "noise_std": 0.005},
        {"column": "acc", "quantity": "acceleration", "dof": 0, "noise_std": PRIOR},
    ],
    "inference": {
        "method": "pgas",
        "particles": 32,
        "burn_in": 100,
        "iterations": 800,
        "state_every": 1,
        "chains": 4,
        "seed": 11,
    },
}


# ----- the Gibbs step on its own ---------------------------------------------------------
def test_noise_gibbs_step_keeps_the_joint_distribution():
    """Geweke: (s, y) drawn from the joint (s from its prior, y given a path and s), one
    :func:`noise_gibbs.gibbs_step`, and the moments of s' must be the prior's. A channel in a
    scaled unit (noise_scale 1e-3) with a half-normal prior, another with a lognormal, a third
    fixed, missing samples. Few observations (5 and 8), so that the prior weighs: measured by
    breaking it (largest |z| over the statistics): the Jacobian 1/(2s) of the prior on the variance
    dropped, 33; the proposal's shape n/2 instead of n/2 - 1, 55."""
    model = LatentForceModel(
        LinearSystem(),
        Matern(0),
        [
            Sensor("displacement", 0, 0.01, "d"),
            Sensor("acceleration", 0, 1e-3, "a", noise_scale=1e-3),
            Sensor("velocity", 0, 0.2, "v"),
        ],
    )
    pm = particle_model.ParticleModel(model, PARAMS, DT, initial=(0.0, 0.1))
    mask = np.ones((8, 3), bool)
    mask[[1, 4, 6], 1] = False  # five observed acceleration samples
    priors = {"noise_std_a": (HalfNormal(2.0), 1.0), "noise_std_v": (LogNormal(-1.0, 0.5), 0.3)}
    nl = noise_gibbs.noise_levels(model, priors, mask)
    assert nl.names == ("noise_std_a", "noise_std_v") and nl.channels == (1, 2) and nl.scales == (1e-3, 1.0)
    path = 0.3 * jax.random.normal(jax.random.key(1), (8, pm.n_state))
    pred = latent.predicted_observations(pm, path)

    def one(key):
        k_s, k_y, k_step = jax.random.split(key, 3)
        s = jnp.stack([HalfNormal(2.0).sample(k_s), LogNormal(-1.0, 0.5).sample(jax.random.fold_in(k_s, 1))])
        sd_si = jnp.array([0.01, s[0] * 1e-3, s[1]])
        y = pred + sd_si * jax.random.normal(k_y, pred.shape)
        od = latent.observation_density(pm, y, mask)
        var, acc = noise_gibbs.gibbs_step(k_step, nl, pm, od, path, sd_si**2)
        return s, noise_gibbs.standard_deviations(nl, var), var[0], acc

    s, s_new, var0, acc = jax.jit(jax.vmap(one))(jax.random.split(jax.random.key(0), 40000))
    assert np.all(np.asarray(var0) == 0.01**2)  # the fixed channel is left alone
    assert 0.2 < float(jnp.mean(acc)) < 0.99  # it moves, and the prior ratio rejects some
    for f in (lambda v: v, lambda v: v**2, jnp.log):
        d = np.asarray(f(s_new) - f(s))
        z = d.mean(0) / (d.std(0, ddof=1) / np.sqrt(d.shape[0]))
        assert np.all(np.abs(z) < 4.5), z
    with pytest.raises(ValueError, match="more than two observed samples"):
        noise_gibbs.noise_levels(model, priors, np.ones((8, 3), bool) & (np.arange(8) < 2)[:, None])


def test_the_verdict_waits_for_the_noise_levels():
    """A noise level whose chains sit apart keeps an otherwise converged run unconverged; the
    per-iteration record pairs it with the hyperparameters (state_every = 2)."""
    chains, blocks, k = 4, 300, 2
    rng = np.random.default_rng(0)
    theta = np.exp(0.1 * rng.standard_normal((chains, blocks, k, 1)))
    noise = 1.0 + np.arange(chains)[:, None, None, None] + 0.01 * rng.standard_normal((chains, blocks, 1, 1))
    noise = np.repeat(noise, k, axis=2)
    mon = rng.standard_normal((chains, blocks, 24, 3))
    z = np.zeros((chains, blocks))
    info = pgas_block.BlockInfo(
        theta,
        z[..., None].repeat(k, 2),
        z[..., None].repeat(k, 2),
        z,
        z,
        z,
        z,
        z,
        np.zeros((chains, blocks, 5, 1)),
        mon,
        noise,
        np.ones((chains, blocks, 1)),
        z,
        z,
        np.zeros((chains, blocks, k, 0)),  # no system parameter sampled
    )
    hyper = Hyper(PARAMS, {"force_variance": (LogNormal(0.0, 1.0), 1.0)})
    pm = SimpleNamespace(ndof=1, nforce=1, layout=StateLayout(1, 1, 1))
    sched = pgas_block.schedule(0, blocks * k, state_every=k)
    names, values = pgas_output._parameters(hyper, ("noise_std_acc",), info)
    assert names == ("force_variance", "noise_std_acc") and values.shape == (chains, blocks * k, 2)
    without = info._replace(noise=noise[..., :0], accept_noise=info.accept_noise[..., :0])
    good = pgas_output._verdict(pm, hyper, [without], sched, np.arange(24), 400.0)
    bad = pgas_output._verdict(pm, hyper, [info], sched, np.arange(24), 400.0, ("noise_std_acc",))
    assert bad["worst"][0]["name"] == "noise_std_acc" and bad["max_r_hat"] > 2 and not bad["converged"]
    assert good["max_r_hat"] < 1.05


def test_pgas_accepts_an_inferred_noise_and_refuses_too_few_samples():
    problem = config_from_dict(CONFIG)
    assert list(problem.free) == ["noise_std_acc"] and problem.inference.method == "pgas"
    d = copy.deepcopy(CONFIG)
    d["system"]["k"] = {"prior": "lognormal", "mu": 2.3, "sigma": 1.0}
    assert set(config_from_dict(d).free) == {"noise_std_acc", "k"}  # a system parameter with the noise
    values = np.full((6, 2), np.nan)
    values[:, 0] = 0.0
    values[:2, 1] = 0.0
    dataset = Dataset(np.arange(6) * DT, DT, values, np.isfinite(values), ["disp", "acc"], {})
    with pytest.raises(LatentForceError, match=r"\[\[sensors\]\]\[1\]\.noise_std \(column 'acc'\).* 2 observed"):
        estimate.run(problem, dataset)


# ----- a whole run against the exact posterior ----------------------------------------------
def _record(sd_acc):
    """A draw from the sampler's own discrete model (the joint stationary start) with the
    acceleration noise ``sd_acc``; a few acceleration samples missing."""
    model = config_from_dict(CONFIG).model
    pm = particle_model.ParticleModel(model, PARAMS, DT)
    A, Q, H, m0, P0 = (np.asarray(a) for a in pm.linear_discrete(pm.transition(1.0, 0.5)))
    rng = np.random.default_rng(5)
    x, ys = rng.multivariate_normal(m0, P0), []
    for _ in range(T):
        ys.append(H @ x + rng.standard_normal(2) * np.array([0.005, sd_acc]))
        x = A @ x + rng.multivariate_normal(np.zeros(len(x)), Q)
    y = np.array(ys)
    y[40:46, 1] = np.nan
    return y, (A, Q, H, m0, P0)


def test_pgas_noise_level_matches_the_exact_posterior_end_to_end():
    """Linear SDOF, displacement (noise fixed) and acceleration (noise inferred, lognormal
    prior), force hyperparameters fixed, T = 120, acceleration noise 5 % of its RMS, a sweep per iteration.
    Through ``estimate.run``: the noise level's posterior mean and second moment within 5 Monte-Carlo
    standard errors (batch means) of the quadrature of p(y | s) p(s) (the Kalman marginal
    likelihood of the same discrete model on a grid of log s), the states' posterior mean
    against the smoother averaged over that posterior; the 90 % interval holds the truth, and
    ``noise_std_acc`` comes out as a parameter with its R-hat, ESS and acceptance."""
    model = config_from_dict(CONFIG).model
    pm = particle_model.ParticleModel(model, PARAMS, DT)
    _, (_, _, H, _, P0) = _record(1.0)
    truth = 0.05 * float(np.sqrt(H[1] @ P0 @ H[1]))
    y, (A, Q, H, m0, P0) = _record(truth)
    mask = np.isfinite(y)
    yz = jnp.asarray(np.where(mask, y, 0.0))
    prior = LogNormal(PRIOR["mu"], PRIOR["sigma"])

    def R(u):
        return jnp.diag(jnp.array([0.005**2, 0.0]) + jnp.array([0.0, 1.0]) * jnp.exp(2.0 * u))

    def quadrature(u):  # log p(y | s) p(s) of u = log s (its density), the smoother's first two moments
        sm = kalman_smoother(A, Q, H, R(u[0]), m0, P0, yz, mask)
        log_post = sm.log_likelihood + prior.log_prob(jnp.exp(u[0])) + u[0]
        return jnp.concatenate(
            [log_post[None], sm.means.ravel(), (jnp.diagonal(sm.covs, axis1=1, axis2=2) + sm.means**2).ravel()]
        )

    g = np.log(truth) + np.linspace(-2.5, 1.0, 176)
    grid = _on_grid(quadrature, jnp.asarray(g)[:, None], chunk=176)
    w = np.exp(grid[:, 0] - grid[:, 0].max())
    assert max(w[0], w[-1]) < 1e-6  # the grid holds the mass
    w /= w.sum()
    exact = np.array([np.sum(w * np.exp(g)), np.sum(w * np.exp(2 * g))])
    mom = np.einsum("k,ktn->tn", w, grid[:, 1:].reshape(len(g), 2, T, -1).transpose(0, 2, 1, 3).reshape(len(g), T, -1))
    n = pm.n_state
    state_mean, state_sd = mom[:, :n], np.sqrt(mom[:, n:] - mom[:, :n] ** 2)

    dataset = Dataset(np.arange(T) * DT, DT, y, mask, ["disp", "acc"], {})
    result, _ = estimate.run(config_from_dict(CONFIG), dataset)
    draws = result.param_draws["noise_std_acc"]  # (chains, stored paths): paired with the paths
    assert draws.shape[0] == 4 and draws.shape[1] >= 100
    x = np.stack([draws, draws**2], axis=-1)
    est = x.reshape(-1, 2).mean(0)
    se = _batch_se(x)
    assert np.all(np.abs(est - exact) < 5 * se), (est, exact, se)
    sd_est, sd_exact = np.sqrt(est[1] - est[0] ** 2), np.sqrt(exact[1] - exact[0] ** 2)
    assert abs(sd_est / sd_exact - 1) < 0.15, (sd_est, sd_exact)
    for name, i in [("displacement", 0), ("velocity", 1), ("force", 2)]:
        mean, sd = result.state_mean[name][:, 0], result.state_sd[name][:, 0]
        assert np.mean((mean - state_mean[:, i]) ** 2) / np.var(state_mean[:, i]) < 0.002, name
        assert np.mean(np.abs(sd / state_sd[:, i] - 1.0)) < 0.1, name
    summary = result.param_summary["noise_std_acc"]
    assert summary["q05"] < truth < summary["q95"], (summary, truth)
    assert summary["r_hat"] < 1.05 and summary["ess_bulk"] > 100, summary
    assert result.point_estimate["noise_std_acc_mean"] == pytest.approx(summary["mean"])
    acc = result.diagnostics["acceptance_noise"]["noise_std_acc"]
    assert len(acc) == 4 and min(acc) > 0.5
    # the run's verdict over the states too: the slowest are the states at t = 0 (R-hat 1.05-1.09
    # over three seeds with the residual move's derivatives held, 1.10-1.18 with them following
    # the force value, ESS 20-70 of 3200 sweeps), whose mean and sd are checked against the exact
    # answer above; this bounds a sampler that has lost its way
    assert result.convergence["max_r_hat"] < 1.25


@pytest.mark.slow
def test_pgas_with_an_inferred_noise_restored_in_process_draws_the_same(tmp_path):
    """Stopped after its second checkpoint and restored from the file, a run inferring a noise
    level (its chains' noise variances are part of the saved state) draws what the
    uninterrupted run drew, noise levels, hyperparameters and paths, bit for bit."""
    from test_resume import _DyingCheckpoint, _Killed

    from latentforce import checkpoint as ckpt
    from latentforce.inference.pgas import run_pgas

    problem = config_from_dict(CONFIG)
    y, _ = _record(0.1)
    free = {
        "noise_std_acc": (LogNormal(PRIOR["mu"], PRIOR["sigma"]), 0.05),
        "force_variance": (LogNormal(0.0, 1.0), 1.0),
    }

    def run(checkpoint=None):
        return run_pgas(
            jax.random.key(5),
            problem.model,
            dict(problem.fixed),
            free,
            y,
            np.isfinite(y),
            DT,
            particles=16,
            iterations=30,
            burn_in=10,
            chains=2,
            chunk_blocks=10,
            checkpoint=checkpoint,
        )

    reference = run()
    with pytest.raises(_Killed):
        run(_DyingCheckpoint(tmp_path, 2))
    meta, saved = ckpt.read_checkpoint(tmp_path)
    assert saved.done == 20 and not saved.finished and "state.noise_var" in saved.arrays
    resumed = run(ckpt.Checkpoint(tmp_path, {"seed": 0}, every=3600.0, saved=saved, sampler="pgas"))
    assert set(reference.theta) == {"force_variance", "noise_std_acc"}
    for name in reference.theta:
        assert np.array_equal(reference.theta[name], resumed.theta[name]), name
    assert np.array_equal(reference.trajectories, resumed.trajectories)
    assert np.array_equal(reference.log_likelihood, resumed.log_likelihood)
    assert not np.all(reference.theta["noise_std_acc"] == 0.05)  # it moved


@pytest.mark.slow
def test_gibbs_block_with_an_inferred_noise_keeps_the_joint_distribution():
    """Geweke's joint check of the whole Gibbs block (:func:`pgas_block.make_block`: sweep,
    smoother, low-frequency and residual-preserving moves, the noise step) on the stiffening Duffing model
    of tests/test_pgas.py with the acceleration noise inferred: (s, x, y) from the joint prior,
    three blocks given y, and the paired differences of statistics of (s, x, y) must have mean
    zero within 4.5 standard errors over 2000 draws. Unbroken: |z| <= 2.3 over the 11 statistics;
    the sweep given the configured R instead of the chain's own: 9.2. About 45 s: slow."""
    from test_pgas import _JOINT_NOISE, _JOINT_PARAMS, _JOINT_T, _joint_model

    from latentforce.compile import jit
    from latentforce.inference import path_moves, pgas_start

    T = _JOINT_T
    pm, mask = _joint_model()
    prior = LogNormal(float(np.log(_JOINT_NOISE[1])), 0.3)
    nl = noise_gibbs.NoiseLevels(("noise_std_a",), (1,), (prior,), (1.0,), (_JOINT_NOISE[1],))
    hyper = Hyper(_JOINT_PARAMS, {})
    tr = pm.transition(1.0, 0.5)
    basis = path_moves.lowfreq_basis(T, 8)
    rm = path_moves.ResidualMove(pm, T, 8, jnp.sqrt(jnp.diagonal(tr.Q)[pm.nfx :]))
    sched = pgas_block.schedule(0, 3, thin_draws=1)
    block = pgas_block.make_block(
        pm,
        hyper,
        sched,
        rm,
        basis,
        np.array([0, T - 1]),
        np.array([0, T // 2]),
        particles=16,
        lowfreq_steps=5,
        residual_steps=20,
        noise=nl,
    )
    nq = 2 * pm.ndof + pm.nforce

    def draw(key):
        k_s, k_path, k_noise, k_chain = jax.random.split(key, 4)
        s = prior.sample(k_s)
        sd = jnp.array([_JOINT_NOISE[0], s])
        x = pm.path(latent.gp_prior_path(k_path, tr, T))
        y = jnp.where(mask, latent.predicted_observations(pm, x) + sd * jax.random.normal(k_noise, (T, 2)), jnp.nan)
        od = latent.observation_density(pm, y, mask)
        eks = pgas_start.extended_kalman_smoother(pm, tr, y, mask)
        rwm = init_proposal(hyper, lambda x_: jnp.zeros(()), jnp.zeros(0))  # no hyperparameter is free
        state = pgas_block.ChainState(
            k_chain,
            x,
            rwm,
            rwm,
            path_moves.lowfreq_init(pm, od, path_moves.LowFrequencyFrame(tr, basis), eks),
            path_moves.residual_init(rm, pm, od, tr, eks),
            tr,
            jnp.zeros((), jnp.int32),
            jnp.zeros((T, nq)),
            jnp.zeros((T, nq)),
            jnp.zeros(()),
            jnp.zeros((sched.n_draws + 1, T, pm.n_state)),
            jnp.asarray(sched.thin, jnp.int32),
            sd**2,
            eks,  # the smoother move's centre (its noise covariance: the chain's own)
        )
        return state, pgas_block.BlockData(y, mask, od, jnp.zeros((T, nq)))

    @jit
    def run(keys):
        states, data = jax.vmap(draw)(keys)
        end, info = jax.lax.scan(
            lambda s, b: jax.vmap(block, (0, None, 0))(s, b, data), states, jnp.arange(sched.n_blocks, dtype=jnp.int32)
        )
        return states, end, data, info

    states, end, data, info = run(jax.random.split(jax.random.key(3), 2000))

    def stats(st, y):
        x, sd = st.reference, jnp.sqrt(st.noise_var)
        u, z = x[:, pm.nm], x[:, 0]
        r = (jnp.nan_to_num(y) - latent.predicted_observations(pm, x)) / sd * mask
        return jnp.array(
            [
                sd[1],
                sd[1] ** 2 * 100,
                jnp.log(sd[1]),
                jnp.mean(u),
                jnp.mean(u**2),
                jnp.mean(z),
                jnp.mean(z**2),
                x[0, 0],
                x[0, 1],
                jnp.sum(r[:, 0] ** 2) / jnp.sum(mask[:, 0]),
                jnp.sum(r[:, 1] ** 2) / jnp.sum(mask[:, 1]),
            ]
        )

    d = np.asarray(jax.vmap(stats)(end, data.y) - jax.vmap(stats)(states, data.y))
    assert float(jnp.mean(info.accept_noise)) > 0.5
    assert float(jnp.mean(info.accept_smoother)) > 0.1  # the smoother move, at the chain's noise, moves
    assert np.all(np.asarray(end.noise_var[:, 0]) == _JOINT_NOISE[0] ** 2)
    assert np.mean(np.asarray(end.noise_var[:, 1]) != np.asarray(states.noise_var[:, 1])) > 0.9
    z = d.mean(0) / (d.std(0, ddof=1) / np.sqrt(d.shape[0]))
    assert np.all(np.abs(z) < 4.5), np.round(z, 1)
