"""The window move (latentforce.inference.window_move) against exact answers."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_smc import linear_problem
from test_smoother_move import _duffing

import latentforce  # noqa: F401
from latentforce.compile import jit
from latentforce.inference import latent, pgas_start, smoother_move, window_move
from latentforce.inference.kalman import kalman_smoother
from latentforce.kernels import Matern

T_LIN = 60


def _linear(order):
    prob = linear_problem(T=T_LIN, missing=True, kernel=Matern(order))
    pm, tr = prob["pm"], prob["tr"]
    od = latent.observation_density(pm, prob["y"], prob["mask"])
    ks = kalman_smoother(prob["A_d"], prob["Q_d"], prob["H"], pm.R, prob["m0f"], prob["P0"], prob["y"], prob["mask"])
    # any centre will do for a linear system: the smoother's mean moved by a smooth offset
    centre = ks.means + 0.3 * jnp.sin(jnp.linspace(0, 3, T_LIN))[:, None]
    return pm, tr, od, ks, centre


def _chains_after_window_passes(pm, tr, od, centre, start, passes, width, tail, key):
    """Every chain (rows of ``start``) moved by ``passes`` calls of the window move."""

    def moves(k, x):
        def one(x, kk):
            return window_move.window_move(kk, pm, tr, od, centre, x, width=width, tail=tail)

        return jax.lax.scan(one, x, jax.random.split(k, passes))

    return jax.vmap(moves)(jax.random.split(key, start.shape[0]), start)


def _linear_chains(order, n, passes, tail, key):
    """``(start, out, acc, ks)``: ``n`` exact draws of a linear SDOF's path (the smoother move's
    proposal, exact there), the same chains after ``passes`` window passes (windows of 16), the
    steps' acceptances, and the Kalman smoother."""
    pm, tr, od, ks, centre = _linear(order)

    @jit
    def run(key):
        k0, k1 = jax.random.split(key)
        start = jax.vmap(pm.path)(smoother_move.proposal_draws(k0, pm, tr, od, centre, n))
        return (start, *_chains_after_window_passes(pm, tr, od, centre, start, passes, 16, tail, k1))

    return (*run(key), ks)


def _sd(ks):
    return np.sqrt(np.asarray(jnp.diagonal(ks.covs, axis1=1, axis2=2)))


def _moments_agree(xs, mean, sd, rtol=0.08):
    n = xs.shape[0]
    z = (np.asarray(xs.mean(0)) - np.asarray(mean)) / (np.asarray(sd) / np.sqrt(n))
    assert np.max(np.abs(z)) < 5.0, np.max(np.abs(z))
    np.testing.assert_allclose(np.asarray(xs.std(0)), np.asarray(sd), rtol=rtol)


@pytest.mark.parametrize("order", [0, 1, 2, 3])
def test_linear_window_steps_are_exact_gibbs_draws(order):
    """On a linear SDOF (displacement + acceleration, missing samples) at every Matérn order, with
    the proposal seeing the record to its end, each window step is an exact draw of the window given
    the rest: every step is accepted, chains started at exact draws of the path keep the Kalman
    smoother's per-time mean and sd, and they move (a middle sample's correlation with its start)."""
    start, out, acc, ks = _linear_chains(order, 800, 2, T_LIN, jax.random.key(order))
    _moments_agree(out, ks.means, _sd(ks), rtol=0.12)
    assert bool(np.all(np.asarray(acc)))
    assert acc.shape[-1] == window_move.n_windows(T_LIN, 16)
    corr = np.corrcoef(np.asarray(start[:, T_LIN // 2, 0]), np.asarray(out[:, T_LIN // 2, 0]))[0, 1]
    assert abs(corr) < 0.2, corr


@pytest.mark.parametrize("order", [2])
def test_window_steps_keep_the_posterior_when_the_proposal_sees_no_tail(order):
    """With no tail the proposal ignores the data after its window (its end state too free), so
    only part is accepted and the weights must make up the difference: chains at exact draws of a
    linear SDOF's path keep its mean and sd. The check has teeth: a simulation smoother whose draws
    are not the proposal the weights assume (its correction term scaled by 0.7) widened the sd by
    45 % here."""
    _, out, acc, ks = _linear_chains(order, 1200, 3, 0, jax.random.key(10 + order))
    _moments_agree(out, ks.means, _sd(ks), rtol=0.1)
    assert 0.1 < float(jnp.mean(acc)) < 0.9, float(jnp.mean(acc))


def test_windows_cover_the_record_from_any_offset():
    """The segment holds its window wherever it falls: at the record's start (negative start),
    in the middle, and at its end (the segment clipped to the record); the windows of one pass
    cover every sample."""
    pm, tr, od, ks, centre = _linear(1)
    eps = latent.whiten(tr, pm.latent(centre))
    width, length = 16, 24
    frame = jax.jit(lambda s: window_move._frame(pm, tr, od, centre, eps, s, width, length))
    for start, a_want in [(-5, 0), (20, 20), (50, T_LIN - length)]:
        fr, a = frame(start)
        t = int(a) + np.arange(length)
        want = (t >= start) & (t < start + width)
        assert int(a) == a_want
        np.testing.assert_array_equal(np.asarray(fr.win) > 0, want)
    for seed in range(20):
        starts = np.asarray(window_move.window_starts(jax.random.key(seed), T_LIN, width))
        covered = np.zeros(T_LIN, bool)
        for s in starts:
            covered[max(s, 0) : max(min(s + width, T_LIN), 0)] = True
        assert covered.all(), starts


@pytest.mark.parametrize("order", [1])
def test_duffing_windows_keep_the_posterior_and_accept_most(order):
    """A stiffening Duffing record with a displacement channel, where the expansion is not exact:
    chains near the posterior (the whole-path smoother move's 40 steps from its proposal's draws)
    keep each time's mean and sd through window steps, which, with a tail as long as the response's
    decay (64 samples here; 8 accepted 0.34), accept most of their proposals."""
    pm, tr, y, mask = _duffing(order, T=80)
    od = latent.observation_density(pm, y, mask)
    n = 600

    @jit
    def run(key):
        eks = pgas_start.extended_kalman_smoother(pm, tr, y, mask)
        centre = smoother_move.iterated_centre(pm, tr, od, eks)
        k0, k1, k2 = jax.random.split(key, 3)
        start = jax.vmap(pm.path)(smoother_move.proposal_draws(k0, pm, tr, od, centre, n))
        post, _ = jax.vmap(lambda k, x: smoother_move.smoother_move(k, pm, tr, od, centre, x, 40, betas=(1.0,)))(
            jax.random.split(k1, n), start
        )
        out, acc = _chains_after_window_passes(pm, tr, od, centre, post, 2, 16, 64, k2)
        return post, out, acc

    post, out, acc = run(jax.random.key(order))
    mean, sd = post.mean(0)[:, :2], post.std(0)[:, :2]
    _moments_agree(out[:, :, :2], mean, sd, rtol=0.12)
    assert float(jnp.mean(acc)) > 0.5, float(jnp.mean(acc))
    corr = np.corrcoef(np.asarray(post[:, 40, 0]), np.asarray(out[:, 40, 0]))[0, 1]
    assert corr < 0.5, corr


def test_the_window_move_runs_by_default_on_long_records_with_a_displacement_channel():
    """``pgas_defaults.default_window``: on a nonlinear system with a displacement channel from
    ``WINDOW_MIN_T`` samples; not on shorter records, with acceleration alone (measured not to
    gain), on a linear system (the smoother move is exact there) or without the smoother move."""
    from latentforce.inference.pgas_defaults import WINDOW_MIN_T, default_window

    on = (window_move.WIDTH, window_move.TAIL)
    pm_disp = _duffing(1, T=10)[0]
    pm_acc = _duffing(1, sensors=("acceleration",), T=10)[0]
    pm_lin = _linear(1)[0]
    assert default_window(pm_disp, WINDOW_MIN_T, 8) == on
    assert default_window(pm_disp, WINDOW_MIN_T - 1, 8) == (0, 0)
    assert default_window(pm_disp, WINDOW_MIN_T, 0) == (0, 0)
    assert default_window(pm_acc, 4 * WINDOW_MIN_T, 4) == (0, 0)
    assert default_window(pm_lin, 4 * WINDOW_MIN_T, 4) == (0, 0)
