"""The internal states' start-up move (:mod:`latentforce.inference.internal_move`): it leaves the
posterior invariant (a successive-conditional check over the joint prior of path and data, on
the Bouc-Wen oscillator with a smooth force) and moves the initial hysteretic force."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from latentforce.inference import internal_move, latent, path_moves
from latentforce.inference.particle_model import ParticleModel
from latentforce.kernels import Matern
from latentforce.models import LatentForceModel, Sensor
from latentforce.systems import BoucWen, Duffing

BENCH = dict(m=2.0, c=10.0, k=5e4, alpha=5e4, beta=800.0, gamma=-1100.0, nu=1.0)
GP = dict(force_variance=2500.0, force_lengthscale=0.01)
SENSORS = [Sensor("acceleration", 0, 1.0), Sensor("displacement", 0, 2e-5)]
#: near rest, the hysteretic force's initial sd 15 N (the CLI's default start is 14.7 N here)
INITIAL = (np.zeros(3), np.diag([1e-5**2, 1e-3**2, 15.0**2]))


def _model(T, order=1):
    pm = ParticleModel(
        LatentForceModel(BoucWen(), Matern(order), SENSORS), {**BENCH, **GP}, 1.0 / 750.0, initial=INITIAL
    )
    tr = pm.transition(GP["force_variance"], GP["force_lengthscale"])
    rm = path_moves.ResidualMove(pm, T, 16, jnp.sqrt(jnp.diagonal(tr.Q)[pm.latent_layout.noise]))
    return pm, tr, rm


@pytest.mark.parametrize("order", [1, 2])
def test_the_start_up_move_keeps_the_joint_distribution_of_path_and_data(order):
    """Replicas (path, y) drawn from the model's joint prior, each path moved by the start-up move
    given its own y: if the move leaves every posterior invariant, the moved paths are again draws
    from the prior. Paired z-scores (moved minus drawn, over independent replicas) of the mean and
    the second moment of the hysteretic force at t = 0 and mid-record and of the force and its
    derivative at t = 0, Matérn-3/2 and 5/2. Measured (2026-11-28): |z| <= 2.0; the move accepted
    0.64 / 0.62 and changed r0 on 100 / 99.8 % of replicas (median change 8.9 / 0.45 N: at 5/2 the
    held force-derivative remainders tie r0, docs/nonlinear.md).
    Broken by dropping the latent's prior density from the target (likelihood alone): z = 10.9 for
    r0's second moment, 7.1 for the force's at t = 0 (and acceptance 1.0)."""
    T, N = 60, 400
    pm, tr, rm = _model(T, order)
    assert internal_move.applies(pm, rm)
    noise = jnp.asarray([s.noise_std for s in SENSORS])

    def one(key):
        k_path, k_obs, k_move = jax.random.split(key, 3)
        path = pm.path(latent.gp_prior_path(k_path, tr, T))
        clean = jax.vmap(lambda x: pm._observe(x[: pm.nm], x[pm.nm :]))(path)
        y = clean + noise * jax.random.normal(k_obs, clean.shape)
        od = latent.observation_density(pm, y, jnp.ones(y.shape, bool))
        moved, acc = internal_move.internal_move(k_move, rm, pm, od, tr, path, 6)
        return path, moved, jnp.mean(acc.astype(float))

    paths, moved, acc = jax.jit(jax.vmap(one))(jax.random.split(jax.random.key(8), N))
    paths, moved = np.asarray(paths), np.asarray(moved)
    r, u = 2, pm.nm  # the hysteretic force and the force value in the path
    assert 0.15 < float(np.mean(acc)) < 0.8, float(np.mean(acc))
    assert np.mean(np.abs(moved[:, 0, r] - paths[:, 0, r]) > 1e-6) > 0.4  # r0 moved on most replicas
    # the measured motion is held exactly
    np.testing.assert_array_equal(moved[:, :, :2], paths[:, :, :2])
    for t, col in ((0, r), (T // 2, r), (0, u), (0, u + 1)):
        a, b = moved[:, t, col], paths[:, t, col]
        scale = np.std(b)
        for d in ((a - b) / scale, (a**2 - b**2) / scale**2):
            z = np.mean(d) / (np.std(d) / np.sqrt(N) + 1e-300)
            assert abs(z) < 4.0, (t, col, z)


def test_the_start_up_move_is_skipped_without_internal_states():
    """A Duffing oscillator has no internal state: nothing to move."""
    pm = ParticleModel(LatentForceModel(Duffing(), Matern(1), SENSORS), dict(m=1.0, c=0.5, k=10.0, k3=1e3, **GP), 0.02)
    tr = pm.transition(GP["force_variance"], GP["force_lengthscale"])
    rm = path_moves.ResidualMove(pm, 30, 4, jnp.sqrt(jnp.diagonal(tr.Q)[pm.latent_layout.noise]))
    assert rm.applies and not internal_move.applies(pm, rm)


def test_the_start_up_move_is_skipped_where_the_initial_prior_ties_the_internal_states():
    """Without hysteresis (beta = gamma = 0) the default start sets r = alpha z exactly: nothing is
    left for the move (run_pgas then compiles it out). With the benchmark's hysteresis the default
    start leaves half of r0's variance free of (z, v); a user's covariance that ties r0 to z, or one
    that leaves it a little free, is read as such."""
    sys = LatentForceModel(BoucWen(), Matern(1), SENSORS)
    assert internal_move.free(ParticleModel(sys, {**BENCH, **GP}, 1.0 / 750.0))
    assert not internal_move.free(ParticleModel(sys, {**BENCH, "beta": 0.0, "gamma": 0.0, **GP}, 1.0 / 750.0))
    for eps, expected in ((0.0, False), (1e-3, True)):
        a = BENCH["alpha"]
        cov = np.array([[1e-10, 0.0, a * 1e-10], [0.0, 1e-6, 0.0], [a * 1e-10, 0.0, (1 + eps) * a**2 * 1e-10]])
        pm = ParticleModel(sys, {**BENCH, **GP}, 1.0 / 750.0, initial=(np.zeros(3), cov))
        assert internal_move.free(pm) is expected, eps
    # no internal state at all
    duff = LatentForceModel(Duffing(), Matern(1), SENSORS)
    assert not internal_move.free(ParticleModel(duff, dict(m=1.0, c=0.5, k=10.0, k3=1e3, **GP), 0.02))
