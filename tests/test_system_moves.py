"""The system parameters' residual-preserving move (:mod:`latentforce.inference.system_moves`): its
map keeps what the sensors measured, is a bijection, and has the volume the acceptance ratio assumes.
The move's target at a proposal is checked against the target rebuilt under the proposed model;
the whole move inside the Gibbs block is checked against the joint distribution in
``tests/test_pgas.py`` (Geweke, with-c-k3)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from latentforce.inference import latent, path_moves
from latentforce.inference.particle_model import ParticleModel
from latentforce.kernels import Matern
from latentforce.models import LatentForceModel, Sensor
from latentforce.systems import BoucWen, Duffing

BENCH = dict(m=2.0, c=10.0, k=5e4, alpha=5e4, beta=800.0, gamma=-1100.0, nu=1.0)
DUFF = dict(m=1.0, c=0.5, k=10.0, k3=1000.0)

# (system, its parameters, the force's Matérn order, sample rate, GP hyperparameters, a change of parameters)
CASES = {
    "bouc-wen-gamma-alpha": (BoucWen(), BENCH, 0, 750.0, (2500.0, 0.01), dict(gamma=-700.0, alpha=6e4)),
    "bouc-wen-mass": (BoucWen(), BENCH, 1, 750.0, (2500.0, 0.01), dict(m=2.6)),
    "bouc-wen-nu-beta": (BoucWen(), BENCH, 0, 750.0, (2500.0, 0.01), dict(nu=1.5, beta=600.0)),
    "duffing-c-k3": (Duffing(), DUFF, 1, 50.0, (1.0, 0.5), dict(c=0.8, k3=1500.0)),
    "duffing-matern52-mass": (Duffing(), DUFF, 2, 50.0, (1.0, 0.5), dict(m=1.3, k3=600.0)),
}


def _case(name, T):
    system, params, order, fs, (var, ls), change = CASES[name]
    sensors = [Sensor("acceleration", 0, 0.1), Sensor("displacement", 0, 1e-4)]
    pm = ParticleModel(
        LatentForceModel(system, Matern(order), sensors),
        {**params, "force_variance": var, "force_lengthscale": ls},
        1.0 / fs,
    )
    tr = pm.transition(var, ls)
    path = jax.jit(lambda k: pm.path(latent.gp_prior_path(k, tr, T)))(jax.random.key(4))
    y = jax.jit(jax.vmap(lambda x: pm._observe(x[: pm.nm], x[pm.nm :])))(path)
    od = latent.observation_density(pm, y, jnp.ones(y.shape, bool))
    rm = path_moves.ResidualMove(pm, T, 4, jnp.sqrt(jnp.diagonal(tr.Q)[pm.latent_layout.noise]))
    pm_x = pm.with_params(change)
    return pm, tr, path, od, rm, pm_x, pm_x.transition(var, ls)


@pytest.mark.parametrize("name", list(CASES))
def test_the_kinematic_map_keeps_the_measured_motion_and_is_a_bijection(name):
    """Rebuilt at other system parameters, the path keeps its displacements and velocities exactly
    and its accelerometer residuals (the force takes up the change of the restoring force); the
    internal (hysteretic) state follows the new model with its own within-step noise kept; the
    returned latent is the new path's under the new model; and rebuilding the new path at the old
    parameters gives the old path back (the map is a bijection for each parameter value)."""
    pm, tr, path, od, rm, pm_x, tr_x = _case(name, 120)
    c0 = jnp.zeros(rm.dim)

    @jax.jit  # one program for the three rebuilds (op by op they took 7-18 s a case)
    def rebuilds():
        build = rm.builder(pm, od, tr, path, kinematic=True)
        g0_, same_ = build(c0)
        g_, new_ = build(c0, at=(pm_x, tr_x))
        _, back_ = rm.builder(pm_x, od, tr_x, new_, kinematic=True)(c0, at=(pm, tr))
        pred = path_moves.predicted_observations
        checks = (pm.latent(path), pm_x.latent(new_), pred(pm, path)[:, rm.rows], pred(pm_x, new_)[:, rm.rows])
        return (g0_, same_, g_, new_, back_) + checks

    g0, same, g, new, back, latent_old, latent_new, acc_old, acc_new = rebuilds()
    np.testing.assert_allclose(np.asarray(same), np.asarray(path), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(np.asarray(g0), np.asarray(latent_old), rtol=1e-9, atol=1e-12)

    kin = slice(0, 2 * pm.ndof)
    np.testing.assert_array_equal(np.asarray(new[:, kin]), np.asarray(path[:, kin]))
    assert float(jnp.max(jnp.abs(new[:, pm.layout.force] - path[:, pm.layout.force]))) > 1e-6  # the force moved
    np.testing.assert_allclose(np.asarray(acc_new), np.asarray(acc_old), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(np.asarray(g), np.asarray(latent_new), rtol=1e-9, atol=1e-12)
    internal = pm.latent_layout.noise.start + np.arange(2 * pm.ndof, pm.nm)
    np.testing.assert_allclose(np.asarray(g[:, internal]), np.asarray(g0[:, internal]), rtol=1e-9, atol=1e-12)

    np.testing.assert_allclose(np.asarray(back), np.asarray(path), rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize("name", list(CASES))
def test_the_kinematic_map_has_the_volume_the_acceptance_ratio_assumes(name):
    r"""The move's acceptance ratio takes the map's Jacobian from the coordinates to the latent
    path as :math:`|\det D_S^{-1}|^T`, a function of the mass alone (module doc): the composite
    latent -> coordinates (old parameters) -> latent (new ones) must then have log-volume
    :math:`T \log(m' / m)` for an accelerometer, zero where the mass is kept. Computed here by
    differentiating the composite on a short record."""
    T = 6
    pm, tr, path, od, rm, pm_x, tr_x = _case(name, T)
    g = pm.latent(path)
    c0 = jnp.zeros(rm.dim)

    def composite(flat):
        p_ = pm.path(jnp.reshape(flat, g.shape))
        return jnp.ravel(rm.builder(pm, od, tr, p_, kinematic=True)(c0, at=(pm_x, tr_x))[0])

    J = np.asarray(jax.jit(jax.jacfwd(composite))(jnp.ravel(g)))
    sign, logdet = np.linalg.slogdet(J)
    m, m_x = pm.params["m"], pm_x.params["m"]
    assert sign != 0
    np.testing.assert_allclose(logdet, T * np.log(float(m_x) / float(m)), atol=1e-6)


def test_the_move_scores_a_proposal_under_the_proposed_model():
    """The target of an accepted step is that of the new parameters with everything rebuilt under
    them: the path's latent *and its within-step noise covariance* from the new model (the grid
    check in tests/test_pgas.py and the Geweke check cannot see the old covariance used instead:
    its bias is second order in the step; checked, both passed with it), the prior at the new
    parameters, the likelihood of the new path and the Jacobian at the new mass. Duffing,
    Matérn-5/2, m and k3 free; small steps so that some are accepted."""
    from latentforce.inference import mcmc, system_moves
    from latentforce.inference.hyper_moves import Hyper
    from latentforce.priors import LogNormal

    pm, tr, path, od, rm, _, _ = _case("duffing-matern52-mass", 120)
    params = {**DUFF, "force_variance": 1.0, "force_lengthscale": 0.5}
    free = {"m": (LogNormal(0.0, 0.5), 1.0), "k3": (LogNormal(np.log(1000.0), 0.5), 1000.0)}
    hyper = Hyper(params, free, ("m", "c", "k", "k3"))
    x0 = jnp.log(jnp.array([1.0, 1000.0]))
    s = x0.shape[0]
    rwm = mcmc.RWMState(x0, jnp.zeros(()), jnp.zeros(()), 1e-3 * jnp.eye(s), x0, jnp.eye(s), jnp.zeros(()))
    x_hyper = jnp.zeros(0)

    @jax.jit
    def run(key):
        out = system_moves.system_move(
            key, rwm, hyper, pm, rm, od, x_hyper, tr, path, 4,
            adapt=jnp.array(False), reshape_steps=jnp.array([-1]), step0=jnp.array(0), target=0.3,
        )  # fmt: skip
        r, new_path, tr_new, accepted = out
        pm_new = pm.with_params({"m": jnp.exp(r.x[0]), "k3": jnp.exp(r.x[1])})
        tr_ind = pm_new.transition(1.0, 0.5)
        ind = system_moves.system_log_target(
            hyper, pm_new, rm.at(pm_new), od, tr_ind, x_hyper, r.x, pm_new.latent(new_path), new_path
        )
        return r, accepted, ind, tr_new.Q, tr_ind.Q

    r, accepted, ind, Q_new, Q_ind = run(jax.random.key(3))
    assert bool(jnp.any(accepted)) and not bool(jnp.all(r.x == x0))
    np.testing.assert_allclose(np.asarray(Q_new), np.asarray(Q_ind), rtol=1e-12, atol=0.0)
    np.testing.assert_allclose(float(r.logdensity), float(ind), rtol=1e-10, atol=1e-8)


def test_the_move_with_the_internal_states_start_keeps_the_joint_distribution():
    """The walk on gamma and the hysteretic force's initial value together (``internal``): replicas
    of (gamma, path, data) from the joint prior (gamma ~ N(-1100, 300^2), the Bouc-Wen benchmark,
    Matérn-3/2, r0's initial sd 15 N), each moved given its own data; the moved draws must be
    draws from the same prior. Paired z-scores of the first and second moments of gamma, of r0,
    of r mid-record and of the force at t = 0. Measured (2026-11-28): |z| <= 2.0, acceptance 0.49,
    gamma and r0 moved on 95 % of replicas. Broken by dropping the first step's prior density (r0's
    and the force's initial prior) from the target: z = 6.2 for r0's second moment."""
    from latentforce.inference import mcmc, system_moves
    from latentforce.inference.hyper_moves import Hyper
    from latentforce.priors import SignedNormal

    T, N, gp = 60, 400, dict(force_variance=2500.0, force_lengthscale=0.01)
    sensors = [Sensor("acceleration", 0, 1.0), Sensor("displacement", 0, 2e-5)]
    initial = (np.zeros(3), np.diag([1e-5**2, 1e-3**2, 15.0**2]))
    pm = ParticleModel(LatentForceModel(BoucWen(), Matern(1), sensors), {**BENCH, **gp}, 1.0 / 750.0, initial=initial)
    hyper = Hyper({**BENCH, **gp}, {"gamma": (SignedNormal(-1100.0, 300.0), -1100.0)}, tuple(BENCH))
    tr0 = pm.transition(gp["force_variance"], gp["force_lengthscale"])
    rm = path_moves.ResidualMove(pm, T, 4, jnp.sqrt(jnp.diagonal(tr0.Q)[pm.latent_layout.noise]))
    noise = jnp.asarray([s.noise_std for s in sensors])
    chol = jnp.diag(jnp.array([0.4, 0.5]))  # gamma's coordinate (prior sds), r0's offset (its prior sds)
    x_hyper = jnp.zeros(0)

    def one(key):
        k_x, k_path, k_obs, k_move = jax.random.split(key, 4)
        x = jax.random.normal(k_x, (1,))
        pm_x = hyper.model_at(pm, x)
        tr = pm_x.transition(gp["force_variance"], gp["force_lengthscale"])
        path = pm_x.path(latent.gp_prior_path(k_path, tr, T))
        clean = jax.vmap(lambda s: pm_x._observe(s[: pm.nm], s[pm.nm :]))(path)
        y = clean + noise * jax.random.normal(k_obs, clean.shape)
        od = latent.observation_density(pm_x, y, jnp.ones(y.shape, bool))
        rwm = mcmc.RWMState(x, jnp.zeros(()), jnp.zeros(()), chol, jnp.zeros(2), jnp.eye(2), jnp.zeros(()))
        r, moved, _, acc = system_moves.system_move(
            k_move, rwm, hyper, pm, rm, od, x_hyper, tr, path, 6,
            adapt=jnp.array(False), reshape_steps=jnp.array([-1]), step0=jnp.array(0), target=0.3, internal=True,
        )  # fmt: skip
        return x[0], r.x[0], path, moved, jnp.mean(acc.astype(float))

    x0, x1, paths, moved, acc = (np.asarray(v) for v in jax.jit(jax.vmap(one))(jax.random.split(jax.random.key(5), N)))
    assert 0.15 < acc.mean() < 0.85, acc.mean()
    assert np.mean(x1 != x0) > 0.4 and np.mean(np.abs(moved[:, 0, 2] - paths[:, 0, 2]) > 1e-6) > 0.4
    np.testing.assert_array_equal(moved[:, :, :2], paths[:, :, :2])  # the measured motion held
    r, u = 2, pm.nm
    pairs = [(x1, x0), (moved[:, 0, r], paths[:, 0, r]), (moved[:, T // 2, r], paths[:, T // 2, r])]
    pairs.append((moved[:, 0, u], paths[:, 0, u]))
    for a, b in pairs:
        scale = np.std(b)
        for d in ((a - b) / scale, (a**2 - b**2) / scale**2):
            z = np.mean(d) / (np.std(d) / np.sqrt(N) + 1e-300)
            assert abs(z) < 4.0, z
