"""Blocked particle Gibbs (latentforce.inference.pgas) against exact answers."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_smc import linear_problem

import latentforce  # noqa: F401
from latentforce.compile import jit
from latentforce.inference import hyper_moves, latent, path_moves, pgas, pgas_start, smc, smoother_move, window_move
from latentforce.inference.kalman import kalman_smoother
from latentforce.kernels import Matern
from latentforce.models import LatentForceModel, Sensor
from latentforce.priors import LogNormal
from latentforce.systems import Duffing


@pytest.fixture(scope="module")
def linear_run():
    prob = linear_problem(T=100, missing=True)
    ks = kalman_smoother(
        prob["A_d"], prob["Q_d"], prob["H"], prob["pm"].R, prob["m0f"], prob["P0"], prob["y"], prob["mask"]
    )
    out = pgas.run_pgas(
        jax.random.key(3, impl="rbg"),
        prob["model"],
        prob["params"],
        {},
        prob["y"],
        prob["mask"],
        prob["dt"],
        particles=32,
        iterations=1200,
        burn_in=100,
        chains=4,
        initial=(0.0, 0.1),
    )
    return prob, ks, out


def test_pgas_matches_kalman_smoother(linear_run):
    """Linear SDOF, fixed hyperparameters: PGAS per-time mean and sd vs the exact smoother."""
    prob, ks, out = linear_run
    km = np.asarray(ks.means)
    ksd = np.sqrt(np.asarray(jnp.diagonal(ks.covs, axis1=1, axis2=2)))
    for name, i in [("displacement", 0), ("velocity", 1), ("force", 2)]:
        mean, sd = out.state_mean[name][:, 0], out.state_sd[name][:, 0]
        nmse = np.mean((mean - km[:, i]) ** 2) / np.var(km[:, i])
        assert nmse < 0.01 * 0.2, (name, nmse)  # well under 1 %
        ratio = sd / ksd[:, i]
        assert np.mean(np.abs(ratio - 1.0)) < 0.1, (name, ratio)
        # pointwise: within a few Monte-Carlo errors (ESS >= ~500 per time point here)
        assert np.all(np.abs(mean - km[:, i]) < 6 * ksd[:, i] / np.sqrt(300)), name


def test_pgas_mixes_everywhere(linear_run):
    _, _, out = linear_run
    rhat = out.diagnostics["rhat"]
    assert len(rhat) >= 5
    assert max(rhat.values()) < 1.05, rhat  # includes t = 0
    assert min(out.diagnostics["switch_rate"]) > 0.2  # ancestor sampling is alive
    assert out.trajectories.shape[:2] == (4, 200)
    assert np.all(np.isfinite(out.log_likelihood))


# 5/2 slow-marked to keep CI's time (each order compiles its own sampler, 70-95 s under load); 3/2 and
# 7/2 run, and tests/test_smoother_move.py checks the move that makes these sweeps exact at every order
@pytest.mark.parametrize("order", [1, pytest.param(2, marks=pytest.mark.slow), 3])
def test_pgas_matches_kalman_smoother_for_smooth_forces_from_the_stationary_start(order):
    """Matérn-3/2, 5/2, 7/2 on the linear SDOF, the default (joint stationary) initial state:
    PGAS per-time mean and sd vs the exact smoother of the same model and start, and the
    ancestor sampling alive (the state form's switch rate was 0.10 at 3/2 and 0.00 at 7/2)."""
    prob = linear_problem(T=100, missing=True, kernel=Matern(order))
    pm = smc.ParticleModel(prob["model"], prob["params"], prob["dt"])  # stationary start
    tr = pm.transition(1.0, 0.5)
    A_d, Q_d, H, m0, P0 = pm.linear_discrete(tr)
    nm = pm.nm
    assert np.max(np.abs(np.asarray(P0)[:nm, nm:])) > 1e-3 * np.sqrt(np.max(np.diag(np.asarray(P0))[:nm]))  # joint
    ks = kalman_smoother(A_d, Q_d, H, pm.R, m0, P0, prob["y"], prob["mask"])
    out = pgas.run_pgas(
        jax.random.key(3, impl="rbg"),
        prob["model"],
        prob["params"],
        {},
        prob["y"],
        prob["mask"],
        prob["dt"],
        particles=32,
        iterations=500,
        burn_in=100,
        chains=4,
    )
    km = np.asarray(ks.means)
    ksd = np.sqrt(np.asarray(jnp.diagonal(ks.covs, axis1=1, axis2=2)))
    for name, i in [("displacement", 0), ("velocity", 1), ("force", 2)]:
        mean, sd = out.state_mean[name][:, 0], out.state_sd[name][:, 0]
        nmse = np.mean((mean - km[:, i]) ** 2) / np.var(km[:, i])
        assert nmse < 0.005, (name, nmse)  # the bar: 0.5 %
        ratio = sd / ksd[:, i]
        assert np.mean(np.abs(ratio - 1.0)) < 0.1, (name, ratio)
    assert min(out.diagnostics["switch_rate"]) > 0.3, out.diagnostics["switch_rate"]
    assert max(out.diagnostics["rhat"].values()) < 1.05, out.diagnostics["rhat"]
    # the moves' acceptances: the smoother move's proposals are exact draws on a linear system (every one
    # accepted); the moves the block does not make (no residual-preserving steps on a linear system, no
    # joint or system move without sampled parameters) list none rather than reading as never accepted
    assert len(out.diagnostics["acceptance_smoother"]) == 4
    assert min(out.diagnostics["acceptance_smoother"]) > 0.999, out.diagnostics["acceptance_smoother"]
    for move in ("residual", "joint", "system", "internal", "window"):
        assert out.diagnostics[f"acceptance_{move}"] == [], (move, out.diagnostics[f"acceptance_{move}"])


# slow-marked for CI's time (96 s on 2026-12-02's slow 2-core machine);
# MDOF through pgas against the exact smoother stays in CI as
# test_elements.py's switched-off frame
@pytest.mark.slow
def test_pgas_matches_kalman_smoother_two_dof():
    """A 2-DOF chain, force at DOF 0, accelerometers on both DOFs and missing samples: PGAS
    (with the residual-preserving move solving on the accelerometer that sees the force)
    against the exact smoother of the same discrete model, hyperparameters fixed."""
    from latentforce.systems import LinearSystem

    M = np.diag([1.0, 0.5])
    K = np.array([[30.0, -10.0], [-10.0, 10.0]])
    params = dict(M=M, C=0.02 * K + 0.1 * M, K=K, force_variance=1.0, force_lengthscale=0.5)
    model = LatentForceModel(
        LinearSystem(ndof=2, force_dofs=(0,)),
        Matern(0),
        [Sensor("acceleration", 0, 0.05), Sensor("acceleration", 1, 0.05)],
    )
    dt, T = 0.05, 80
    pm = smc.ParticleModel(model, params, dt, initial=(0.0, 0.1))
    rm = path_moves.ResidualMove(pm, T, 8, jnp.ones(pm.nm))
    assert rm.applies and list(rm.rows) == [0]
    A_d, Q_d, H, m1, P1 = (np.asarray(a) for a in pm.linear_discrete(pm.transition(1.0, 0.5)))
    rng = np.random.default_rng(2)
    x, ys = rng.multivariate_normal(m1, P1), []
    for _ in range(T):
        ys.append(H @ x + 0.05 * rng.normal(size=2))
        x = A_d @ x + rng.multivariate_normal(np.zeros(pm.n_state), Q_d)
    y = np.array(ys)
    mask = np.ones(y.shape, bool)
    mask[20:26, 0] = False
    y[~mask] = np.nan
    ks = kalman_smoother(A_d, Q_d, H, pm.R, m1, P1, jnp.asarray(y), jnp.asarray(mask))
    out = pgas.run_pgas(
        jax.random.key(5, impl="rbg"),
        model,
        params,
        {},
        y,
        mask,
        dt,
        particles=32,
        iterations=600,
        burn_in=100,
        chains=4,
        initial=(0.0, 0.1),
        residual_steps=60,  # the move under test (a linear system's default is none)
    )
    km = np.asarray(ks.means)
    ksd = np.sqrt(np.asarray(jnp.diagonal(ks.covs, axis1=1, axis2=2)))
    for name, cols in [("displacement", (0, 1)), ("velocity", (2, 3)), ("force", (4,))]:
        for j, i in enumerate(cols):
            mean, sd = out.state_mean[name][:, j], out.state_sd[name][:, j]
            nmse = np.mean((mean - km[:, i]) ** 2) / np.var(km[:, i])
            assert nmse < 0.01 * 0.2, (name, j, nmse)
            assert np.mean(np.abs(sd / ksd[:, i] - 1.0)) < 0.1, (name, j)
    assert max(out.diagnostics["rhat"].values()) < 1.05, out.diagnostics["rhat"]
    assert min(out.diagnostics["acceptance_residual"]) > 0.05


def test_default_residual_steps_follow_the_model():
    """60 residual-preserving steps a block on an SDOF nonlinear system, 60 / ndof on an MDOF one,
    none on a linear system or with a displacement (or strain) channel while the smoother move runs;
    the smoother move 8 steps with such a channel on a nonlinear system, else 4."""
    from latentforce.systems import Element, LinearSystem, NonlinearMDOF, ShearFrame

    gp = dict(force_variance=1.0, force_lengthscale=0.5)
    sensors = [Sensor("acceleration", 0, 0.1)]
    duffing = smc.ParticleModel(
        LatentForceModel(Duffing(), Matern(1), sensors), dict(m=1.0, c=0.2, k=10.0, k3=50.0, **gp), 0.05
    )
    frame_params = {f"{kind}_{i}": v for kind, v in (("m", 1.0), ("c", 2.0), ("k", 2e3)) for i in range(3)}
    frame = smc.ParticleModel(
        LatentForceModel(NonlinearMDOF(ShearFrame(3, force_dofs=(2,)), [Element("cubic", (1, 0))]), Matern(0), sensors),
        {**frame_params, "element0_k3": 1e5, **gp},
        0.01,
    )
    two_dof = smc.ParticleModel(
        LatentForceModel(LinearSystem(ndof=2, force_dofs=(0,)), Matern(0), sensors),
        dict(M=np.eye(2), C=0.1 * np.eye(2), K=np.array([[30.0, -10.0], [-10.0, 10.0]]), **gp),
        0.05,
        initial=(0.0, 0.1),
    )
    assert pgas.default_residual_steps(duffing, 4) == 60
    assert frame.ndof == 3 and pgas.default_residual_steps(frame, 4) == 20
    assert pgas.default_residual_steps(two_dof, 4) == 0
    assert pgas.default_residual_steps(two_dof, 0) == 30  # no smoother move: the path moves are the sweep's help
    # a displacement (or strain) channel pins the move's direction: none while the smoother move runs
    for quantity in ("displacement", "strain"):
        extra = Sensor(quantity, 0, 0.01, coefficients=(1.0,)) if quantity == "strain" else Sensor(quantity, 0, 0.01)
        pinned = smc.ParticleModel(
            LatentForceModel(Duffing(), Matern(1), [*sensors, extra]), dict(m=1.0, c=0.2, k=10.0, k3=50.0, **gp), 0.05
        )
        assert pgas.default_residual_steps(pinned, 4) == 0
        assert pgas.default_residual_steps(pinned, 0) == 60
        assert pgas.default_smoother_steps(pinned) == 8  # the smoother move renews the path there
    velocity = smc.ParticleModel(
        LatentForceModel(Duffing(), Matern(1), [*sensors, Sensor("velocity", 0, 0.01)]),
        dict(m=1.0, c=0.2, k=10.0, k3=50.0, **gp),
        0.05,
    )
    assert pgas.default_residual_steps(velocity, 4) == 60  # a velocity channel leaves the offset free
    assert pgas.default_smoother_steps(velocity) == pgas.default_smoother_steps(duffing) == 4
    assert pgas.default_smoother_steps(two_dof) == 4  # linear: its first step is an exact draw


def _batch_se(draws, batches=20):
    """Monte-Carlo standard error of the mean of ``draws`` ``(chains, n, k)`` by batch means."""
    C, n, k = draws.shape
    bm = draws[:, : n // batches * batches].reshape(C, batches, -1, k).mean(axis=2).reshape(-1, k)
    return bm.std(axis=0, ddof=1) / np.sqrt(bm.shape[0])


# slow-marked for CI's time (117 s on 2026-12-02's slow 2-core machine);
# the hyperparameter moves stay in CI against grid posteriors
# (test_hyperparameter_mh_matches_grid_posterior, test_noncentred_mh_matches_grid_posterior) and
# the whole block by the Geweke test below
@pytest.mark.slow
def test_gibbs_with_free_hyperparameters_matches_exact_marginal_posterior():
    """The whole blocked Gibbs sampler with both hyperparameters free (every move on:
    centred and non-centred MH, low-frequency and residual-preserving moves, adaptation)
    on a linear SDOF against the exact answer of the same discrete model: p(theta | y) by
    quadrature of the Kalman marginal likelihood on a log-space grid, and the states'
    moments as the smoother's averaged over that posterior."""
    from latentforce.inference.kalman import log_likelihood

    prob = linear_problem(T=100, missing=True)
    pm, y, mask = prob["pm"], prob["y"], prob["mask"]
    free = {"force_variance": (LogNormal(0.0, 1.0), 2.0), "force_lengthscale": (LogNormal(-0.5, 1.0), 1.0)}
    hyper = hyper_moves.Hyper(prob["params"], free)

    def discrete(x):
        return pm.linear_discrete(pm.transition(*hyper.values(x)))

    def log_post(x):  # density of x = log(theta), the prior written out (not the sampler's)
        A, Q, H, m1, P1 = discrete(x)
        log_prior = sum(prior.log_prob(jnp.exp(x[i])) + x[i] for i, (prior, _) in enumerate(free.values()))
        return log_likelihood(A, Q, H, pm.R, m1, P1, y, mask) + log_prior

    g = np.linspace(-4.0, 3.0, 71)  # spacing 0.1 against posterior sds of about 0.5
    G1, G2 = np.meshgrid(g, g, indexing="ij")
    X = jnp.stack([G1.ravel(), G2.ravel()], axis=1)
    lp = _on_grid(log_post, X).reshape(G1.shape)
    w = np.exp(lp - lp.max())
    assert max(w[0].max(), w[-1].max(), w[:, 0].max(), w[:, -1].max()) < 1e-5  # the grid holds the mass
    w /= w.sum()
    exact_mean = np.array([np.sum(w * G1), np.sum(w * G2)])
    exact_m2 = np.array([np.sum(w * G1**2), np.sum(w * G2**2)])

    def moments(x):
        A, Q, H, m1, P1 = discrete(x)
        s = kalman_smoother(A, Q, H, pm.R, m1, P1, y, mask)
        return jnp.concatenate([s.means, jnp.diagonal(s.covs, axis1=1, axis2=2) + s.means**2], axis=1)

    keep = w.ravel() > 1e-5 * w.max()
    wk = w.ravel()[keep] / w.ravel()[keep].sum()
    mom = np.einsum("k,ktn->tn", wk, _on_grid(moments, X[keep], chunk=512).reshape(int(keep.sum()), 100, -1))
    n = pm.n_state
    state_mean, state_sd = mom[:, :n], np.sqrt(mom[:, n:] - mom[:, :n] ** 2)

    out = pgas.run_pgas(
        jax.random.key(4, impl="rbg"),
        prob["model"],
        prob["params"],
        free,
        y,
        mask,
        prob["dt"],
        particles=32,
        iterations=1000,
        burn_in=200,
        state_every=2,
        chains=4,
        mh_steps=2,
        residual_steps=20,
        initial=(0.0, 0.1),
    )
    x = np.log(np.stack([out.theta[k] for k in hyper.names], axis=-1))  # (chains, draws, 2)
    assert np.all(np.abs(x.reshape(-1, 2).mean(0) - exact_mean) < 5 * _batch_se(x)), (x.mean((0, 1)), exact_mean)
    assert np.all(np.abs((x**2).reshape(-1, 2).mean(0) - exact_m2) < 5 * _batch_se(x**2)), (
        (x**2).mean((0, 1)),
        exact_m2,
    )
    assert max(out.diagnostics["rhat"].values()) < 1.1, out.diagnostics["rhat"]
    for name, i in [("displacement", 0), ("velocity", 1), ("force", 2)]:
        mean, sd = out.state_mean[name][:, 0], out.state_sd[name][:, 0]
        assert np.mean((mean - state_mean[:, i]) ** 2) / np.var(state_mean[:, i]) < 0.01 * 0.2, name
        assert np.mean(np.abs(sd / state_sd[:, i] - 1.0)) < 0.1, name


def _grid_problem():
    model = LatentForceModel(Duffing(), Matern(0), [Sensor("acceleration", 0, 0.1)])
    params = dict(m=1.0, c=0.2, k=10.0, k3=50.0, force_variance=1.0, force_lengthscale=0.5)
    pm = smc.ParticleModel(model, params, 0.05)
    free = {"force_variance": (LogNormal(0.0, 1.0), 1.0), "force_lengthscale": (LogNormal(-0.5, 1.0), 0.5)}
    hyper = hyper_moves.Hyper(params, free)
    g = latent.gp_prior_path(jax.random.key(0), pm.transition(1.0, 0.5), 200)
    return pm, hyper, g


def _on_grid(f, X, chunk=4096):
    """``vmap(f)`` over the rows of ``X`` in chunks: one vmapped batch of 1e5 transitions stalled
    XLA's CPU runtime (batches above ~30000, jax 0.10.2); chunks of a few thousand take milliseconds."""
    fv = jit(jax.vmap(f))
    Xp = jnp.concatenate([X, jnp.zeros((-X.shape[0] % chunk, X.shape[1]))])
    return np.concatenate([np.asarray(fv(Xp[i : i + chunk])) for i in range(0, Xp.shape[0], chunk)])[: X.shape[0]]


def _grid_moments(pm, hyper, xf):
    """Posterior mean and sd of theta given the path by quadrature on a log-space grid."""
    g = np.linspace(-5.0, 6.0, 321)
    G1, G2 = np.meshgrid(g, g, indexing="ij")
    X = jnp.stack([G1.ravel(), G2.ravel()], axis=1)
    lt = _on_grid(lambda x: hyper.log_target(pm, x, xf), X).reshape(G1.shape)
    w = np.exp(lt - lt.max())
    assert w[0].max() < 1e-8 and w[-1].max() < 1e-8 and w[:, 0].max() < 1e-8 and w[:, -1].max() < 1e-8
    w /= w.sum()
    T1, T2 = np.exp(G1), np.exp(G2)
    mean = np.array([np.sum(w * T1), np.sum(w * T2)])
    sd = np.sqrt(np.array([np.sum(w * T1**2), np.sum(w * T2**2)]) - mean**2)
    return mean, sd


def test_hyper_log_target_is_log_space_density():
    """The target is the density of x = log(theta): prior + Jacobian + GP path density."""
    pm, hyper, xf = _grid_problem()
    x = jnp.array([0.3, -0.9])
    th = np.exp(np.asarray(x))
    lp = float(LogNormal(0.0, 1.0).log_prob(th[0]) + LogNormal(-0.5, 1.0).log_prob(th[1])) + float(x.sum())
    ref = lp + float(hyper_moves.gp_path_log_density(pm, th[0], th[1], xf))
    assert abs(float(hyper.log_target(pm, x, xf)) - ref) < 1e-9
    assert np.allclose(hyper.values(x), th)


def test_hyperparameter_mh_matches_grid_posterior():
    """Adaptive MH (shape resets + scale during burn-in, frozen after) vs 2-D quadrature, given a path.

    After burn-in the kernel is a plain RWM with a fixed proposal, so its
    draws must match the grid posterior: mean and sd of each parameter
    within 5 Monte-Carlo standard errors (batch means over 4 chains).
    """
    pm, hyper, xf = _grid_problem()
    burn, n = 3000, 20000
    schedule = jnp.asarray(hyper_moves.adaptation_schedule(burn))
    assert len(schedule) >= 4 and int(schedule[-1]) < burn

    def log_target(x):
        return hyper.log_target(pm, x, xf)

    @jit
    def chain(key):
        k0, k1 = jax.random.split(key)
        # a dispersed start, away from the mode
        x0 = hyper.to_unconstrained(jnp.array([1.0, 0.5])) + jax.random.normal(k0, (2,))
        state = hyper_moves.init_proposal(hyper, log_target, x0)

        def step(s, inp):
            k, i = inp
            s, info = hyper_moves.mh_step(k, s, log_target, adapt=i < burn, reshape=jnp.any(i == schedule), target=0.38)
            return s, (s.x, info.accepted)

        s, (xs, accs) = jax.lax.scan(step, state, (jax.random.split(k1, burn + n), jnp.arange(burn + n)))
        return s, xs[burn:], accs[burn:]

    states, xs, accs = jax.vmap(chain)(jax.random.split(jax.random.key(1), 4))
    theta = np.exp(np.asarray(xs))  # (chains, n, 2)
    exact_mean, exact_sd = _grid_moments(pm, hyper, xf)
    # the proposal was adapted to the posterior's shape and then frozen
    cov = np.asarray(jax.vmap(hyper_moves.proposal_covariance)(states))
    assert np.all(np.isfinite(cov)) and np.all(np.linalg.eigvalsh(cov) > 0)
    # Monte-Carlo error by batch means (4 chains x 25 batches)
    se = _batch_se(theta, 25)
    assert np.all(np.abs(theta.reshape(-1, 2).mean(0) - exact_mean) < 5 * se), (theta.mean((0, 1)), exact_mean, se)
    se2 = _batch_se(theta**2, 25)
    second = (theta**2).reshape(-1, 2).mean(0)
    assert np.all(np.abs(second - (exact_sd**2 + exact_mean**2)) < 5 * se2 + 1e-12), (second, exact_sd, exact_mean)
    acc = float(np.mean(accs))
    assert 0.2 < acc < 0.6, acc


def test_adaptation_schedule():
    assert hyper_moves.adaptation_schedule(0) == ()
    assert hyper_moves.adaptation_schedule(10) == ()
    s = hyper_moves.adaptation_schedule(1000)
    assert s == tuple(sorted(s)) and s[0] >= 9 and s[-1] < 1000


@pytest.mark.slow
def test_duffing_gibbs_runs_and_converges():
    """Full blocked Gibbs on a short Duffing problem: finite output, hyperparameter R-hat; the window
    move made in every block (forced on: by default it waits for 2 048 samples) and reported."""
    model = LatentForceModel(Duffing(), Matern(0), [Sensor("displacement", 0, 0.01), Sensor("acceleration", 0, 0.1)])
    params = dict(m=1.0, c=0.2, k=10.0, k3=50.0, force_variance=1.0, force_lengthscale=0.5)
    pm = smc.ParticleModel(model, params, 0.02, initial=(0.0, 0.01))
    path = pm.path(latent.gp_prior_path(jax.random.key(5), pm.transition(1.0, 0.5), 200))
    xf = path[:, 2:]
    y = jax.vmap(lambda x: pm._observe(x[:2], x[2:]))(path)
    y = y + jax.random.normal(jax.random.key(6), y.shape) * jnp.array([0.01, 0.1])
    free = {"force_variance": (LogNormal(0.0, 1.0), 2.0), "force_lengthscale": (LogNormal(-0.5, 1.0), 1.0)}
    out = pgas.run_pgas(
        jax.random.key(0, impl="rbg"),
        model,
        params,
        free,
        y,
        jnp.isfinite(y),
        0.02,
        particles=32,
        iterations=4000,
        burn_in=1000,
        state_every=2,
        chains=4,
        mh_steps=2,
        initial=(0.0, 0.01),
        window=64,
    )
    assert np.all(np.isfinite(out.state_mean["force"]))
    assert max(out.diagnostics["rhat"].values()) < 1.1, out.diagnostics["rhat"]
    accepted = out.diagnostics["acceptance_window"]
    assert len(accepted) == 4 and min(accepted) > 0.1, accepted
    force_nmse = np.mean((out.state_mean["force"][:, 0] - xf[:, 0]) ** 2) / np.var(xf[:, 0])
    assert force_nmse < 0.2


def test_whiten_colour_and_observation_density():
    """Innovations round-trip; the masked observation log-likelihood vs a direct sum."""
    pm, hyper, g = _grid_problem()
    tr = pm.transition(1.3, 0.4)
    eps = latent.whiten(tr, g)
    assert np.allclose(latent.colour(tr, eps), g, atol=1e-10)
    path = pm.path(g)
    y = np.asarray(jax.vmap(lambda x: pm._observe(x[:2], x[2:]))(path)) + 0.05
    mask = np.ones_like(y, dtype=bool)
    mask[::7] = False
    od = latent.observation_density(pm, np.where(mask, y, np.nan), mask)
    sd = float(np.sqrt(pm.R[0, 0]))
    direct = np.sum(mask * (-0.5 * (0.05 / sd) ** 2 - np.log(sd) - 0.5 * np.log(2 * np.pi)))
    assert abs(float(latent.observation_log_likelihood(pm, od, path)) - direct) < 1e-8
    # the non-centred target at the path's own theta rebuilds the same path
    x = hyper.to_unconstrained(jnp.array([1.3, 0.4]))
    lt, (g_rebuilt, rebuilt, _) = hyper_moves.noncentred_log_target(hyper, pm, od, x, eps)
    assert np.allclose(rebuilt, path, atol=1e-10)
    assert np.allclose(g_rebuilt, g, atol=1e-10)
    assert abs(float(lt) - (direct + float(hyper.log_prior(x)))) < 1e-6


def test_noncentred_mh_matches_grid_posterior():
    """The adaptive kernel on the non-centred target (innovations fixed) vs 2-D quadrature."""
    pm, hyper, g = _grid_problem()
    g = g[:60]
    path = pm.path(g)
    y = np.asarray(jax.vmap(lambda x: pm._observe(x[:2], x[2:]))(path))
    y = y + 0.1 * np.asarray(jax.random.normal(jax.random.key(2), y.shape))
    od = latent.observation_density(pm, y, np.ones_like(y, dtype=bool))
    eps = latent.whiten(pm.transition(1.0, 0.5), g)

    def log_target(x):
        return hyper_moves.noncentred_log_target(hyper, pm, od, x, eps)[0]

    burn, n = 1000, 6000
    schedule = jnp.asarray(hyper_moves.adaptation_schedule(burn))

    @jit
    def chain(key):
        state = hyper_moves.init_proposal(hyper, log_target, jnp.zeros(2))

        def step(s, inp):
            k, i = inp
            s, info = hyper_moves.mh_step(k, s, log_target, adapt=i < burn, reshape=jnp.any(i == schedule), target=0.38)
            return s, s.x

        return jax.lax.scan(step, state, (jax.random.split(key, burn + n), jnp.arange(burn + n)))[1][burn:]

    theta = np.exp(np.asarray(jax.vmap(chain)(jax.random.split(jax.random.key(3), 4))))
    # the posterior is sharp here: a fine grid around the draws (the edge check guards its extent)
    lx = np.log(theta).reshape(-1, 2)
    lo, hi = lx.min(0), lx.max(0)
    g1, g2 = (np.linspace(lo[i] - 0.6 * (hi[i] - lo[i]), hi[i] + 0.6 * (hi[i] - lo[i]), 201) for i in range(2))
    G1, G2 = np.meshgrid(g1, g2, indexing="ij")
    X = jnp.stack([G1.ravel(), G2.ravel()], axis=1)
    lt = _on_grid(log_target, X).reshape(G1.shape)
    w = np.exp(lt - lt.max())
    assert max(w[0].max(), w[-1].max(), w[:, 0].max(), w[:, -1].max()) < 1e-8
    w /= w.sum()
    exact = np.array([np.sum(w * np.exp(G1)), np.sum(w * np.exp(G2))])
    se = _batch_se(theta)
    assert np.all(np.abs(theta.reshape(-1, 2).mean(0) - exact) < 5 * se), (theta.mean((0, 1)), exact, se)


def _check_move_against_gaussian(move, record, init, start, burn, n, exact_mean, exact_sd):
    """Four chains of a path move ``move(key, rwm, path, block) -> (rwm, path, accepted)`` from
    ``start(key)``; the recorded functionals ``record(rwm, path)`` must have the exact mean and
    mean-square error within 5 Monte-Carlo standard errors (batch means), and the acceptance
    must be near the adapted target."""

    @jit
    def chain(key):
        def block(carry, inp):
            rwm, path = carry
            k, b = inp
            rwm, path, accs = move(k, rwm, path, b)
            return (rwm, path), (record(rwm, path), jnp.mean(accs.astype(float)))

        keys = jax.random.split(jax.random.fold_in(key, 1), burn + n)
        return jax.lax.scan(block, (init, start(key)), (keys, jnp.arange(burn + n)))[1]

    f, acc = jax.vmap(chain)(jax.random.split(jax.random.key(7), 4))
    f, acc = np.asarray(f)[:, burn:], np.asarray(acc)[:, burn:]
    assert 0.1 < acc.mean() < 0.5, acc.mean()
    se = _batch_se(f, 25)
    assert np.all(np.abs(f.reshape(-1, 2).mean(0) - exact_mean) < 5 * se), (f.mean((0, 1)), exact_mean, se)
    sq = (f - exact_mean) ** 2
    ms = sq.reshape(-1, 2).mean(0)
    assert np.all(np.abs(ms - exact_sd**2) < 5 * _batch_se(sq, 25)), (np.sqrt(ms), exact_sd)


def test_lowfreq_move_matches_exact_conditional():
    """The low-frequency move alone, from dispersed starts, vs its exact Gaussian target.

    Acceleration only (the displacement channel masked out), fixed theta. With
    the high-frequency innovations eps_perp held fixed the move samples the
    low-frequency coordinates w; the model being linear, their conditional
    posterior is Gaussian, and its mean and covariance follow exactly from
    the gradient and Hessian of the (quadratic) log target, which the
    Gauss-Newton proposal shape of ``lowfreq_init`` must equal. The chains' mean
    and sd of the force's time average and of the initial displacement must
    match within 5 Monte-Carlo standard errors (batch means).
    """
    prob = linear_problem(T=60, missing=False)
    pm, tr = prob["pm"], prob["tr"]
    mask = np.asarray(prob["mask"]).copy()
    mask[:, 0] = False  # acceleration only
    od = latent.observation_density(pm, prob["y"], mask)
    frame = path_moves.LowFrequencyFrame(tr, path_moves.lowfreq_basis(60, 8))
    g_start = 2.0 * latent.gp_prior_path(jax.random.key(4), tr, 60)
    start = pm.path(g_start.at[0, pm.nfx :].set(jnp.array([0.3, -1.0]) - pm.mech0_mean))
    w_start, eps_perp = path_moves.lowfreq_coordinates(pm, frame, start)
    assert np.allclose(path_moves.lowfreq_path(pm, frame, eps_perp, w_start), start, atol=1e-9)

    def functionals(w):
        path = path_moves.lowfreq_path(pm, frame, eps_perp, w)
        return jnp.array([jnp.mean(path[:, pm.nm]), path[0, 0]])

    # exact conditional: the log target is quadratic in w
    lt = lambda w: path_moves.lowfreq_log_target(pm, od, frame, eps_perp, w)[0]  # noqa: E731
    w0 = jnp.zeros_like(w_start)
    prec = -np.asarray(jit(jax.hessian(lt))(w0))
    cov = np.linalg.inv(prec)
    w_mean = np.asarray(w0) + cov @ np.asarray(jit(jax.grad(lt))(w0))
    J = np.asarray(jit(jax.jacfwd(functionals))(w0))
    exact_mean = np.asarray(functionals(jnp.asarray(w_mean)))
    exact_sd = np.sqrt(np.diag(J @ cov @ J.T))

    burn, n, steps = 200, 2000, 5
    # the Gauss-Newton shape is computed at a different, dispersed path (exact here: the model is linear)
    init = path_moves.lowfreq_init(pm, od, frame, pm.path(latent.gp_prior_path(jax.random.key(9), tr, 60)))
    assert np.allclose(np.asarray(init.cov), cov, rtol=1e-6, atol=1e-10)

    def move(k, rwm, path, b):
        return path_moves.lowfreq_move(
            k, rwm, pm, od, frame, path, steps, adapt=b < burn, step0=b * steps, reshape_steps=jnp.asarray((-1,))
        )

    _check_move_against_gaussian(
        move,
        lambda rwm, path: functionals(rwm.x),
        init,
        lambda key: path_moves.lowfreq_path(pm, frame, eps_perp, w_start + 0.5 * jax.random.normal(key, w_start.shape)),
        burn,
        n,
        exact_mean,
        exact_sd,
    )


# Matérn-5/2 slow-marked to keep CI's time (about 65 s under load); ½ and 7/2 (acceleration only) and
# 3/2 (with displacement) run
@pytest.mark.parametrize(
    "kernel,acc_only",
    [(Matern(0), True), (Matern(1), False), pytest.param(Matern(2), False, marks=pytest.mark.slow), (Matern(3), True)],
)
def test_residual_move_matches_exact_conditional(kernel, acc_only):
    """The residual-preserving move alone, from dispersed starts, vs its exact Gaussian target.

    Linear SDOF at fixed theta; acceleration samples 10-14 missing (the map
    keeps a virtual residual there). Matérn-1/2 with acceleration only, and
    Matérn-3/2 (the force's derivative state following the force value) with the displacement
    channel too, whose residuals the move changes. The model being linear, the
    map from the move's coordinates c to the path is affine, so the log target
    is quadratic in c: its exact mean and covariance follow from its gradient
    and Hessian, which the Gauss-Newton shape of ``residual_init`` must equal.
    The chains' mean and mean-square error of the force's time average and of
    the initial displacement must match within 5 Monte-Carlo standard errors.
    """
    T = 60
    prob = linear_problem(T=T, missing=True, kernel=kernel)
    pm, tr = prob["pm"], prob["tr"]
    mask = np.asarray(prob["mask"]).copy()
    if acc_only:
        mask[:, 0] = False
    od = latent.observation_density(pm, prob["y"], mask)
    rm = path_moves.ResidualMove(pm, T, 8, jnp.sqrt(jnp.diagonal(tr.Q)[pm.nfx :]))
    assert rm.applies and list(rm.rows) == [1] and list(rm.cols) == [0]
    g_start = 2.0 * latent.gp_prior_path(jax.random.key(4), tr, T)
    start = pm.path(g_start.at[0, pm.nfx :].set(jnp.array([0.3, -1.0]) - pm.mech0_mean))
    build = rm.builder(pm, od, tr, start)
    c0 = jnp.zeros(rm.dim)
    assert np.allclose(build(c0)[1], start, atol=1e-9)
    # the map keeps the acceleration residuals
    moved = build(jax.random.normal(jax.random.key(1), (rm.dim,)))[1]
    resid = lambda x: prob["y"][:, 1] - jax.vmap(pm._observe)(x[:, : pm.nm], x[:, pm.nm :])[:, 1]  # noqa: E731
    assert np.allclose(np.where(mask[:, 1], resid(moved) - resid(start), 0.0), 0.0, atol=1e-9)
    if pm.nfx > 1:
        # and the remainders of the derivative states' innovations after the force prior's
        # filter gains on the force value (ResidualMove), not the derivative states themselves
        K = np.asarray(path_moves._value_gains(tr, pm.latent_layout.force, np.array([0]), np.arange(1, pm.nfx), T))

        def remainders(x):
            f = pm.latent_layout.force
            xf = np.asarray(pm.latent(x))[:, f]
            e = np.concatenate([xf[:1], xf[1:] - xf[:-1] @ np.asarray(tr.A)[f, f].T])
            return e[:, 1:] - np.einsum("tbu,tu->tb", K, e[:, :1])

        np.testing.assert_allclose(remainders(moved), remainders(start), atol=1e-9 * np.abs(remainders(start)).max())
        assert not np.allclose(moved[:, pm.nm + 1 :], start[:, pm.nm + 1 :])
    assert np.max(np.abs(moved[:, 0] - start[:, 0])) > 1e-3

    def functionals(path):
        return jnp.array([jnp.mean(path[:, pm.nm]), path[0, 0]])

    lt = lambda c: path_moves.residual_log_target(tr, pm, od, build, c)[0]  # noqa: E731
    prec = -np.asarray(jit(jax.hessian(lt))(c0))
    cov = np.linalg.inv(prec)
    c_mean = cov @ np.asarray(jit(jax.grad(lt))(c0))

    # independently: the path's density under the linear-Gaussian state-space model
    # (linear_discrete), which the move's target must equal up to a constant
    def state_space_density(c):
        x = build(c)[1]
        A_d, Q_d, H = prob["A_d"], prob["Q_d"], prob["H"]
        lq = lambda r, S: -0.5 * r @ jnp.linalg.solve(S, r)  # noqa: E731
        lp = lq(x[0] - prob["m0f"], prob["P0"]) + jnp.sum(jax.vmap(lq, (0, None))(x[1:] - x[:-1] @ A_d.T, Q_d))
        r = (jnp.nan_to_num(prob["y"]) - x @ H.T) * mask
        return lp - 0.5 * jnp.sum(r**2 / jnp.diag(pm.R))

    prec_ss = -np.asarray(jit(jax.hessian(state_space_density))(c0))
    # Matérn-7/2: the state-space form solves with Q_d of condition 2e20 (3e17 at 5/2, 5e12
    # at 3/2: the force states and the within-step noise are driven by one white noise), so
    # the two agree to 8e-5 there, not 1e-5
    rtol = 1e-5 if pm.nfx < 4 else 3e-4
    np.testing.assert_allclose(prec_ss, prec, rtol=rtol, atol=1e-6 * np.abs(prec).max())
    np.testing.assert_allclose(
        np.linalg.solve(prec_ss, np.asarray(jax.grad(state_space_density)(c0))),
        c_mean,
        atol=rtol * np.sqrt(np.diag(cov)).max(),
    )
    J = np.asarray(jit(jax.jacfwd(lambda c: functionals(build(c)[1])))(c0))
    exact_mean = np.asarray(functionals(build(jnp.asarray(c_mean))[1]))
    exact_sd = np.sqrt(np.diag(J @ cov @ J.T))
    # the Gauss-Newton shape, computed at another path, is the exact covariance (linear model)
    init = path_moves.residual_init(rm, pm, od, tr, pm.path(latent.gp_prior_path(jax.random.key(9), tr, T)))
    assert np.allclose(np.asarray(init.cov), cov, rtol=1e-6, atol=1e-10 * np.abs(cov).max())

    burn, n, steps = 200, 2000, 5

    def move(k, rwm, path, b):
        return path_moves.residual_move(k, rwm, rm, pm, od, tr, path, steps, adapt=b < burn)

    _check_move_against_gaussian(
        move,
        lambda rwm, path: functionals(path),
        init,
        lambda key: build(3.0 * jnp.sqrt(jnp.diag(cov)) * jax.random.normal(key, (rm.dim,)) + c_mean)[1],
        burn,
        n,
        exact_mean,
        exact_sd,
    )


def test_residual_move_is_skipped_without_a_force_channel():
    """Displacement sensors only: no channel sees the force, so there is nothing to solve for."""
    model = LatentForceModel(Duffing(), Matern(0), [Sensor("displacement", 0, 1e-4)])
    params = dict(m=1.0, c=20.0, k=1e4, k3=1e9, force_variance=20.0, force_lengthscale=0.1)
    pm = smc.ParticleModel(model, params, 1 / 2048)
    assert not path_moves.ResidualMove(pm, 64, 8, jnp.ones(2)).applies


def test_lowfreq_basis_is_orthonormal_dct():
    B = np.asarray(path_moves.lowfreq_basis(50, 12))
    assert B.shape == (50, 13)  # 12 DCT modes and the first innovation
    assert np.allclose(B.T @ B, np.eye(13), atol=1e-12)
    assert np.allclose(B[:, 0], 1 / np.sqrt(50))
    assert np.linalg.norm(B @ (B.T @ np.eye(50)[0]) - np.eye(50)[0]) < 1e-12
    assert path_moves.lowfreq_basis(5, 16).shape == (5, 5)


def _duffing_acceleration_record(order):
    """The acceleration-only Duffing record of the start tests (1 % noise) and run_pgas's base
    path on it: ``(pm, tr, od, eks, base)``, ``base`` Gauss-Newton from the extended smoother's
    mean (a path of the model, :func:`test_the_chains_start_from_a_path_of_the_model`)."""
    from latentforce.simulate import simulate

    T, dt = 256, 1 / 2048
    params = dict(m=1.0, c=20.0, k=1e4, k3=1e9, force_variance=20.0, force_lengthscale=0.1)
    model = LatentForceModel(Duffing(), Matern(order), [Sensor("acceleration", 0, 1.0)])
    acc = np.asarray(simulate(jax.random.key(0), model, params, T, dt).acceleration)
    sd = 0.01 * np.sqrt(np.mean(acc**2))
    y = jnp.asarray(acc + sd * np.random.default_rng(1).normal(size=acc.shape))
    mask = jnp.ones(y.shape, bool)
    pm = smc.ParticleModel(LatentForceModel(Duffing(), Matern(order), [Sensor("acceleration", 0, sd)]), params, dt)
    tr = pm.transition(20.0, 0.1)
    od = latent.observation_density(pm, y, mask)
    eks = pgas_start.extended_kalman_smoother(pm, tr, y, mask)
    base = smoother_move.iterated_centre(pm, tr, od, eks, smoother_move.CENTRE_ITERATIONS)
    return pm, tr, od, eks, base


# slow-marked for CI's time (42 s, 2026-12-01); the chains' starts are also checked by
# test_the_chains_start_from_a_path_of_the_model and tests/test_pgas_start.py
@pytest.mark.slow
def test_dispersed_start_fits_data_and_spreads_the_slow_directions():
    """Chain starts (``dispersed_start``) on the acceleration-only Duffing case.

    Each start must still fit every acceleration sample (its log target no
    more than 4q below its base path's, q the number of moved coordinates: a
    Gaussian 2-sd move costs 2 per informed coordinate; a draw the nonlinearity
    puts further down is pulled back), and the starts must spread the weakly
    observed force mean as the Gauss-Newton posterior with the data's
    information quartered (``pgas_start.dispersal_cov``; sample variance of 64
    starts within chi-square bounds). The earlier
    start, prior-scale noise on the latent path, failed the first check by
    about 1e6.
    """
    pm, tr, od, _, base = _duffing_acceleration_record(0)
    T = base.shape[0]
    frame = path_moves.LowFrequencyFrame(tr, path_moves.lowfreq_basis(T, 16))
    rwm_lf = path_moves.lowfreq_init(pm, od, frame, base)
    q = rwm_lf.x.shape[0]
    starts = jit(jax.vmap(lambda k: pgas_start.dispersed_start(k, pm, frame, rwm_lf, base, od)))(
        jax.random.split(jax.random.key(5), 64)
    )
    w, eps_perp = path_moves.lowfreq_coordinates(pm, frame, base)

    def log_target(p):  # in the low-frequency coordinates, the rest of the path held
        w_p = path_moves.lowfreq_coordinates(pm, frame, p)[0]
        return path_moves.lowfreq_log_target(pm, od, frame, eps_perp, w_p)[0]

    lt, lt_base = np.asarray(jax.vmap(log_target)(starts)), float(log_target(base))
    assert np.all(lt > lt_base - 4 * q - 1e-6), (lt.min(), lt_base)
    # a shape that ignores the data (the prior's): full steps fall far down the posterior, and the
    # halvings pull every start back within the bound
    keys = jax.random.split(jax.random.key(6), 8)
    wide = rwm_lf._replace(cov=jnp.eye(q))
    pulled = jit(jax.vmap(lambda k: pgas_start.dispersed_start(k, pm, frame, wide, base, od)))(keys)
    lt_pulled = np.asarray(jax.vmap(log_target)(pulled))
    assert np.all(lt_pulled > lt_base - 4 * q - 1e-6), (lt_pulled.min(), lt_base)
    full = jax.vmap(lambda k: path_moves.lowfreq_path(pm, frame, eps_perp, w + jax.random.normal(k, w.shape)))(keys)
    moved = np.abs(np.asarray(pulled) - np.asarray(base)).max(axis=(1, 2))
    assert np.all(moved > 1e-3 * np.abs(np.asarray(full) - np.asarray(base)).max(axis=(1, 2)))  # pulled back, not home
    assert np.min(np.asarray(jax.vmap(log_target)(full))) < lt_base - 4 * q  # what the halvings prevent
    grad = jax.grad(lambda w_: jnp.mean(path_moves.lowfreq_path(pm, frame, eps_perp, w_)[:, pm.nm]))(w)
    S = pgas_start.dispersal_cov(rwm_lf.cov, 2.0)
    expected_var = float(grad @ S @ grad)  # linearised: the map is nearly linear over 2 sd
    ratio = float(np.var(np.asarray(starts[:, :, pm.nm]).mean(axis=1), ddof=1)) / expected_var
    assert 0.45 < ratio < 1.7, ratio


@pytest.mark.parametrize("order", [0, 1, 2, 3])
def test_the_chains_start_from_a_path_of_the_model(order):
    """``run_pgas`` starts its chains (and the moves' first shapes) from Gauss-Newton about the
    extended smoother's mean (``smoother_move.iterated_centre``), not from the mean itself: on a
    nonlinear system with a smooth force that mean is no path of the model. Its mechanical
    innovations, whitened, reached 6.7e3 sds on this Duffing record at Matérn-5/2 (3e4 on the
    frame with a Bouc-Wen brace, where two of four chains started from it ran off for good); the
    base path's stay within a few sds, and it fits the data as well."""
    pm, tr, od, eks, base = _duffing_acceleration_record(order)

    def innovations(path):  # the mechanical innovations in prior sds
        return np.abs(np.asarray(latent.whiten(tr, pm.latent(path)))[:, pm.latent_layout.noise]).max()

    assert innovations(base) < 5.0, innovations(base)
    ll = [float(latent.observation_log_likelihood(pm, od, p)) for p in (base, eks)]
    assert ll[0] > ll[1] - 1.0, ll
    if order >= 2:  # what the check guards against
        assert innovations(eks) > 100.0, innovations(eks)


# ---------------------------------------------------------------------------
# Nonlinear model: every path move leaves the joint distribution of (path, data) invariant
# ---------------------------------------------------------------------------
_JOINT_T, _JOINT_DT, _JOINT_NOISE = 40, 0.05, (0.01, 0.05)
_JOINT_PARAMS = dict(m=1.0, c=0.5, k=10.0, k3=1000.0, force_variance=1.0, force_lengthscale=0.5)


def _joint_model():
    """The stiffening Duffing model of the joint checks and its missing samples (both channels)."""
    model = LatentForceModel(
        Duffing(), Matern(0), [Sensor("displacement", 0, _JOINT_NOISE[0]), Sensor("acceleration", 0, _JOINT_NOISE[1])]
    )
    pm = smc.ParticleModel(model, _JOINT_PARAMS, _JOINT_DT, initial=(0.0, 0.05))
    mask = np.ones((_JOINT_T, 2), bool)
    mask[10:15, 1] = False
    mask[20:25, 0] = False
    return pm, jnp.asarray(mask)


def _joint_draw(pm, tr, mask, k_path, k_noise):
    """One (path, data) from the model at transition ``tr``; NaN where ``mask`` is False."""
    x = pm.path(latent.gp_prior_path(k_path, tr, _JOINT_T))
    y = latent.predicted_observations(pm, x) + jnp.asarray(_JOINT_NOISE) * jax.random.normal(k_noise, (_JOINT_T, 2))
    return x, jnp.where(mask, y, jnp.nan)


@pytest.fixture(scope="module")
def duffing_joint():
    """A strongly stiffening Duffing model (at the rms displacement 3 k3 z^2 is about 1.5 k) and
    2000 independent draws of (path, data) from its joint prior, some samples of both channels missing."""
    pm, mask = _joint_model()
    tr = pm.transition(1.0, 0.5)
    xs, ys = jit(jax.vmap(lambda key: _joint_draw(pm, tr, mask, *jax.random.split(key))))(
        jax.random.split(jax.random.key(0), 2000)
    )
    assert 3.0 * _JOINT_PARAMS["k3"] * float(jnp.mean(xs[:, :, 0] ** 2)) > _JOINT_PARAMS["k"]
    return pm, tr, mask, xs, ys


def _joint_statistics(pm, tr, mask, x, y):
    """Functions of (path, data) whose joint-prior means the moves must keep: force and
    displacement moments, the initial state, the latent's whitened innovations (its prior
    density) and each channel's normalised squared residuals (the likelihood)."""
    u, z = x[:, pm.nm], x[:, 0]
    r = (jnp.nan_to_num(y) - latent.predicted_observations(pm, x)) / jnp.asarray(_JOINT_NOISE) * mask
    eps = latent.whiten(tr, pm.latent(x))
    return jnp.array(
        [
            jnp.mean(u),
            jnp.mean(u**2),
            jnp.mean(z),
            jnp.mean(z**2),
            100.0 * jnp.mean(z**4),
            x[0, 0],
            x[0, 1],
            jnp.mean(eps**2),
            jnp.sum(r[:, 0] ** 2) / jnp.sum(mask[:, 0]),
            jnp.sum(r[:, 1] ** 2) / jnp.sum(mask[:, 1]),
        ]
    )


@pytest.mark.parametrize("kind", ["sweep", "sweep-bootstrap", "residual", "lowfreq", "smoother", "window"])
def test_path_moves_keep_the_joint_distribution_of_a_nonlinear_model(duffing_joint, kind):
    """Geweke's joint-distribution check of each path move on a nonlinear model, where no exact
    posterior is available: if (x, y) is drawn from the model and x' from a kernel that leaves
    p(x | y) invariant, (x', y) has the same distribution, so every statistic f has
    E[f(x', y) - f(x, y)] = 0. The paired differences over 2000 independent draws must have
    mean zero within 4.5 standard errors.

    Covered here and nowhere else: the smoother and window moves' weights on a nonlinear model (the centre the
    extended Kalman smoother, a function of y alone), the sweep's second-stage weights (the optimal proposal
    linearises the stiffness about rest) and its tangent-linear ancestor weights, and the
    residual-preserving rebuild through the cubic stiffness (the move's shape comes from the
    extended Kalman smoother: a function of y alone, so the kernel is a fixed one given y).
    Measured by breaking the code (largest |z|): the ancestor weights without the filter
    weights (the published code's error) 83 on the bootstrap sweep; without the future-data
    term Delta 23 (optimal) and 31 (bootstrap); without the second-stage weights 7 (optimal);
    the residual and low-frequency moves with their prior term scaled by 0.9, 17 and 9; the
    smoother move with the expanded likelihood in its weight scaled by 0.9, 11; the window move's
    likewise, 12 (its pin dropped from the exact target is not caught here: test_window_move's linear
    test catches it). A 10 %
    tempering of a move's likelihood is below this test's resolution (|z| < 4).
    """
    pm, tr, mask, xs, ys = duffing_joint
    rm = path_moves.ResidualMove(pm, _JOINT_T, 8, jnp.sqrt(jnp.diagonal(tr.Q)[pm.nfx :]))
    frame = path_moves.LowFrequencyFrame(tr, path_moves.lowfreq_basis(_JOINT_T, 8))
    proposal = "bootstrap" if kind == "sweep-bootstrap" else "optimal"
    sweep = smc.make_sweep(pm, 16, proposal=proposal)

    def move(key, x, y):
        if kind.startswith("sweep"):
            sc = smc.sweep_constants(pm, tr, y, mask, proposal)

            def one(x_, k):
                out = sweep(k, sc, x_)
                return out.trajectory, out.info.switched

            x, switched = jax.lax.scan(one, x, jax.random.split(key, 3))
            return x, jnp.mean(switched)  # the ancestor switch rate
        od = latent.observation_density(pm, y, mask)
        eks = pgas_start.extended_kalman_smoother(pm, tr, y, mask)
        if kind == "smoother":
            x, acc = smoother_move.smoother_move(key, pm, tr, od, eks, x, 5)
        elif kind == "window":  # bridges of 8 samples, re-centred about the smoother's mean
            x, acc = window_move.window_move(key, pm, tr, od, eks, x, width=8)
        elif kind == "residual":
            init = path_moves.residual_init(rm, pm, od, tr, eks)
            _, x, acc = path_moves.residual_move(key, init, rm, pm, od, tr, x, 30, adapt=False)
        else:
            _, x, acc = path_moves.lowfreq_move(
                key,
                path_moves.lowfreq_init(pm, od, frame, eks),
                pm,
                od,
                frame,
                x,
                30,
                adapt=False,
                step0=0,
                reshape_steps=jnp.asarray((-1,)),
            )
        return x, jnp.mean(acc.astype(float))

    x1, acc = jit(jax.vmap(move))(jax.random.split(jax.random.key(1), xs.shape[0]), xs, ys)
    stats = jit(jax.vmap(lambda x, y: _joint_statistics(pm, tr, mask, x, y)))
    d = np.asarray(stats(x1, ys) - stats(xs, ys))
    # the check has power only if the paths do move (acceptance, or the sweep's switch rate)
    assert np.mean(np.any(np.abs(np.asarray(x1 - xs)) > 0.0, axis=(1, 2))) > 0.9
    assert float(jnp.mean(acc)) > 0.15
    if kind == "residual":
        # the move keeps the acceleration residuals by construction (up to round-off):
        # their statistic is checked as conserved, not tested for a zero mean
        assert np.max(np.abs(d[:, -1])) < 1e-6
        d = d[:, :-1]
    z = d.mean(0) / (d.std(0, ddof=1) / np.sqrt(d.shape[0]))
    assert np.all(np.abs(z) < 4.5), np.round(z, 1)


_JOINT_FREE = {"force_variance": (LogNormal(0.0, 0.4), 1.0), "force_lengthscale": (LogNormal(np.log(0.5), 0.3), 0.5)}


def _joint_prior_draw(pm, hyper, mask, tr_ref, k_theta, k_path, k_noise):
    """``(x, tr, path, y, od, eks)``: log theta from :data:`_JOINT_FREE`'s priors, a path and a record
    from the model at it, and the extended Kalman smoother at the fixed ``tr_ref`` (a function of y)."""
    x = jnp.array([0.0, np.log(0.5)]) + jnp.array([0.4, 0.3]) * jax.random.normal(k_theta, (2,))
    tr = pm.transition(*hyper.values(x))
    path, y = _joint_draw(pm, tr, mask, k_path, k_noise)
    od = latent.observation_density(pm, y, mask)
    return x, tr, path, y, od, pgas_start.extended_kalman_smoother(pm, tr_ref, y, mask)


def test_joint_move_keeps_the_joint_distribution_of_a_nonlinear_model():
    """The joint (theta, path) move alone (:func:`smoother_move.joint_move`), Geweke's check on
    the stiffening Duffing model with both hyperparameters free: (theta, x, y) from the joint
    prior, four joint steps at a fixed proposal (centre: the extended Kalman smoother at a fixed
    theta, a function of y alone), and the paired differences of statistics of (theta, x, y) must
    have mean zero within 4.5 standard errors over 2000 draws. Measured by breaking the code
    (largest |z|): the linearised marginal likelihood dropped from the target, 6.0 (the latent's
    whitened size: the path no longer fits its theta). The weight's part is not resolved here
    (dropped, the test passes: with a displacement channel the expansion is nearly exact); it
    is the smoother move's, broken at |z| = 11 in the path-move test below.
    """
    pm, mask = _joint_model()
    hyper = hyper_moves.Hyper(_JOINT_PARAMS, _JOINT_FREE)
    tr_ref = pm.transition(1.0, 0.5)

    def one(key):
        k_theta, k_path, k_noise, k_move = jax.random.split(key, 4)
        x, tr, path, y, od, eks = _joint_prior_draw(pm, hyper, mask, tr_ref, k_theta, k_path, k_noise)
        rwm = hyper_moves.init_proposal(hyper, lambda x_: jnp.zeros(()), x, proposal_sd=0.3)
        rwm, path2, tr2, acc = smoother_move.joint_move(
            k_move,
            rwm,
            pm,
            hyper,
            od,
            eks,
            tr,
            path,
            4,
            adapt=False,
            reshape_steps=jnp.asarray((-1,)),
            step0=0,
            target=0.3,
        )
        before = jnp.concatenate([x, x**2, _joint_statistics(pm, tr, mask, path, y)])
        after = jnp.concatenate([rwm.x, rwm.x**2, _joint_statistics(pm, tr2, mask, path2, y)])
        return after - before, jnp.mean(acc.astype(float))

    d, acc = jit(jax.vmap(one))(jax.random.split(jax.random.key(3), 2000))
    d = np.asarray(d)
    assert float(jnp.mean(acc)) > 0.2, float(jnp.mean(acc))
    z = d.mean(0) / (d.std(0, ddof=1) / np.sqrt(d.shape[0]))
    assert np.all(np.abs(z) < 4.5), np.round(z, 1)


_SYSTEM_FREE = {"c": (LogNormal(np.log(0.5), 0.3), 0.5), "k3": (LogNormal(np.log(1000.0), 0.3), 1000.0)}


# hyperparameters: slow-marked for CI's time (73-81 s). with-c-k3 runs every move of its block
# (both hyperparameters free as well) and catches its breakages: with the non-centred step's
# likelihood tempered by 10 % it fails (2026-11-28), as it does when c, k3's Jacobian is dropped.
@pytest.mark.parametrize(
    "system", [pytest.param(False, marks=pytest.mark.slow), True], ids=["hyperparameters", "with-c-k3"]
)
def test_gibbs_block_keeps_the_joint_distribution_of_a_nonlinear_model(system):
    """The whole post-burn-in Gibbs block of ``run_pgas`` (:func:`pgas.make_block`: the joint
    (theta, path) move, sweep, smoother, low-frequency and residual-preserving moves, centred and
    non-centred hyperparameter steps), Geweke's joint-distribution check on the stiffening Duffing model with both
    hyperparameters free: (theta, x, y) drawn from the joint prior, three blocks applied given
    y, and the paired differences of statistics of (theta, x, y) must have mean zero within
    4.5 standard errors over 2000 independent draws. The path moves' shapes come from the
    extended Kalman smoother at a fixed theta (a function of y alone), as after burn-in.
    Measured by breaking the code (largest |z|): the log-Jacobian of the log-space walk dropped,
    10; the non-centred step's likelihood tempered by 10 %, 27 (the linear grid test above
    cannot see that one). Unbroken: |z| <= 2.1 over the 14 statistics.

    ``with-c-k3``: the damping c and the cubic stiffness k3 sampled too (by the joint move alone,
    each chain's moves on the model at its own c, k3), drawn from their priors with the rest:
    every statistic is computed with the state's own model. Measured by breaking the code
    (largest |z|): the log-Jacobian of c, k3's log-space walk dropped, 5.5 (with one joint step
    per block it was 3.5, hence three); the block's moves run at the starting model instead of
    the chain's, caught by the carried-transition check. Unbroken: |z| <= 2.1 over 18 statistics.
    """
    T = _JOINT_T
    pm, mask = _joint_model()
    hyper = hyper_moves.Hyper(_JOINT_PARAMS, {**_JOINT_FREE, **(_SYSTEM_FREE if system else {})}, ("c", "k3"))
    n_sys = len(hyper.sys_names)
    tr_ref = pm.transition(1.0, 0.5)
    basis = path_moves.lowfreq_basis(T, 8)
    rm = path_moves.ResidualMove(pm, T, 8, jnp.sqrt(jnp.diagonal(tr_ref.Q)[pm.nfx :]))
    sched = pgas.schedule(0, 6, state_every=2, mh_steps=2, thin_draws=1)
    assert sched.burn_blocks == 0 and sched.n_blocks == 3
    block = pgas.make_block(
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
        joint_steps=3 if system else 1,  # the move of c, k3 with the path redrawn: more steps for the check's power
        system_steps=3,  # c, k3 with the measured motion held (system_moves); none without them
    )
    n_draws = sched.n_draws

    def draw(key):
        k_theta, k_path, k_noise, k_chain = jax.random.split(key, 4)
        x_sys = jnp.log(jnp.array([0.5, 1000.0]))[:n_sys] + 0.3 * jax.random.normal(
            jax.random.fold_in(k_theta, 1), (n_sys,)
        )
        pm_x = hyper.model_at(pm, x_sys)
        x, tr, path, y, od, eks = _joint_prior_draw(pm_x, hyper, mask, tr_ref, k_theta, k_path, k_noise)
        # fixed proposals: the non-centred step moves the whole path, so it takes smaller steps
        rwm = hyper_moves.init_proposal(hyper, lambda x_: jnp.zeros(()), x, proposal_sd=0.25)
        rwm_nc = hyper_moves.init_proposal(hyper, lambda x_: jnp.zeros(()), x, proposal_sd=0.03)
        rwm_lf = path_moves.lowfreq_init(pm, od, path_moves.LowFrequencyFrame(tr_ref, basis), eks)
        nq = 2 * pm.ndof + pm.nforce
        rwm_rp = path_moves.residual_init(rm, pm, od, tr_ref, eks)
        state = pgas.ChainState(
            k_chain,
            path,
            rwm,
            rwm_nc,
            rwm_lf,
            rwm_rp,
            tr,
            jnp.zeros((), jnp.int32),
            jnp.zeros((T, nq)),
            jnp.zeros((T, nq)),
            jnp.zeros(()),
            jnp.zeros((n_draws + 1, T, pm.n_state)),
            jnp.asarray(sched.thin, jnp.int32),
            centre=eks,
            rwm_joint=hyper_moves.init_proposal(
                hyper, lambda x_: jnp.zeros(()), jnp.concatenate([x, x_sys]), proposal_sd=0.2 if system else 0.3
            ),
            rwm_sys=hyper_moves.init_proposal(hyper, lambda x_: jnp.zeros(()), x_sys, proposal_sd=0.3)
            if system
            else None,
        )
        return state, pgas.BlockData(y, mask, od, jnp.zeros((T, nq)))

    @jit
    def run(keys):
        states, data = jax.vmap(draw)(keys)
        end, info = jax.lax.scan(
            lambda s, b: jax.vmap(block, (0, None, 0))(s, b, data), states, jnp.arange(sched.n_blocks, dtype=jnp.int32)
        )
        return states, end, data, info

    states, end, data, info = run(jax.random.split(jax.random.key(2), 2000))

    def stats(s, y):  # theta's moments, and the path's statistics at the state's own theta
        x = jnp.concatenate([s.rwm.x, s.rwm_joint.x[2:]])
        pm_s = hyper.model_at(pm, s.rwm_joint.x[2:])
        return jnp.concatenate([x, x**2, _joint_statistics(pm_s, s.tr, mask, s.reference, y)])

    d = np.asarray(jax.vmap(stats)(end, data.y) - jax.vmap(stats)(states, data.y))
    # it moves: theta, the path, and every kind of step accepts
    assert np.mean(np.any(np.abs(np.asarray(end.rwm.x - states.rwm.x)) > 0, axis=1)) > 0.8
    assert np.mean(np.any(np.abs(np.asarray(end.reference - states.reference)) > 0, axis=(1, 2))) > 0.9
    rates = (
        info.accept,
        info.accept_noncentred,
        info.accept_lowfreq,
        info.accept_residual,
        info.accept_smoother,
        info.accept_joint,
    ) + ((info.accept_system,) if system else ())
    for a in rates:
        assert float(jnp.mean(a)) > 0.1, [float(jnp.mean(a_)) for a_ in rates]
    if system:  # the system parameters move, and the block records them
        assert np.mean(np.any(np.abs(np.asarray(end.rwm_joint.x[:, 2:] - states.rwm_joint.x[:, 2:])) > 0, axis=1)) > 0.5
        np.testing.assert_allclose(np.exp(np.asarray(end.rwm_joint.x[:, 2:])), np.asarray(info.system[-1, :, -1]))
    # the carried transition is the one at the final theta
    tr_end = jax.vmap(lambda x, xs: hyper.model_at(pm, xs).transition(*hyper.values(x)))(
        end.rwm.x[:5], end.rwm_joint.x[:5, 2:]
    )
    np.testing.assert_allclose(np.asarray(end.tr.Q[:5]), np.asarray(tr_end.Q), rtol=1e-10, atol=1e-300)
    z = d.mean(0) / (d.std(0, ddof=1) / np.sqrt(d.shape[0]))
    assert np.all(np.abs(z) < 4.5), np.round(z, 1)


# ---------------------------------------------------------------------------
# Channels: runs that differ only in their sensors share their compiled programs
# ---------------------------------------------------------------------------
def _two_sensor_records():
    params = dict(m=1.0, c=0.2, k=10.0, k3=50.0, force_variance=1.0, force_lengthscale=0.5)
    both = LatentForceModel(Duffing(), Matern(0), [Sensor("acceleration", 0, 0.1), Sensor("displacement", 0, 0.01)])
    pm = smc.ParticleModel(both, params, 0.02, initial=(0.0, 0.01))

    @jax.jit  # one program, not op by op
    def observed(key):
        path = pm.path(latent.gp_prior_path(key, pm.transition(1.0, 0.5), 80))
        return jax.vmap(lambda x: pm._observe(x[:2], x[2:]))(path)

    y = np.asarray(observed(jax.random.key(5))) + np.random.default_rng(0).normal(size=(80, 2)) * np.array([0.1, 0.01])
    acc_only = LatentForceModel(Duffing(), Matern(0), [Sensor("acceleration", 0, 0.2)])
    return params, both, y, acc_only, y[:, :1] * 1.5


def test_observe_through_keeps_the_likelihood_and_checks_the_sensors():
    params, _, _, acc_only, y = _two_sensor_records()
    mask = np.ones(y.shape, bool)
    mask[5:9] = False
    model2, y2, mask2 = pgas.observe_through(acc_only, [("displacement", 0), ("acceleration", 0)], y, mask)
    assert [(s.quantity, s.noise_std) for s in model2.sensors] == [("displacement", 1.0), ("acceleration", 0.2)]
    assert np.all(np.isnan(y2[:, 0])) and not mask2[:, 0].any()
    np.testing.assert_array_equal(y2[:, 1], y[:, 0])
    np.testing.assert_array_equal(mask2[:, 1], mask[:, 0])
    pm, pm2 = (smc.ParticleModel(m, params, 0.02, initial=(0.0, 0.01)) for m in (acc_only, model2))
    path = jax.jit(lambda k: pm.path(latent.gp_prior_path(k, pm.transition(1.0, 0.5), y.shape[0])))(jax.random.key(3))
    lls = [
        float(
            jax.jit(
                lambda yy, mm: latent.observation_log_likelihood(p, latent.observation_density(p, yy, mm, p.R), path)
            )(yy, mm)
        )
        for p, yy, mm in ((pm, y, mask), (pm2, y2, mask2))
    ]
    assert abs(lls[0] - lls[1]) < 1e-10 * abs(lls[0])
    with pytest.raises(ValueError, match="no channel of their own"):
        pgas.observe_through(acc_only, [("displacement", 0)], y, mask)
    with pytest.raises(ValueError, match="distinct"):
        pgas.observe_through(acc_only, [("acceleration", 0), ("acceleration", 0)], y, mask)
    with pytest.raises(ValueError, match="one column per sensor"):
        pgas.observe_through(acc_only, [("acceleration", 0)], np.ones((80, 2)), np.ones((80, 2), bool))


# slow-marked for CI's time (71 s on the 2-core machine, 2026-12-01); the compile-once property of
# runs of one structure is also checked in test_pgas_compile_once.py
@pytest.mark.slow
def test_runs_through_the_same_channels_compile_once_and_agree_with_their_own_sensors():
    """Two records with other sensors, noise and data, run through the same channels: the second
    run compiles nothing (one model structure: jax.jit's cache serves every program, the noise and
    the data being arguments), and gives what it gives through its own sensors (same draws,
    round-off apart). Hyperparameters fixed, to keep the programs small."""
    from test_pgas_compile_once import counting_compiles

    params, both, y, acc_only, y_acc = _two_sensor_records()
    channels = [("acceleration", 0), ("displacement", 0)]
    settings = dict(
        particles=16,
        iterations=12,
        burn_in=8,
        state_every=2,
        chains=2,
        initial=(0.0, 0.01),
        lowfreq_modes=4,
        residual_modes=4,
        # the step counts' defaults follow the channels (a displacement channel, here never observed, sets
        # them: pgas.default_smoother_steps), so the same draws need them set
        residual_steps=4,
        smoother_steps=4,
    )

    def run(model, y_, channels_):
        return pgas.run_pgas(
            jax.random.key(2), model, params, {}, y_, np.isfinite(y_), 0.02, channels=channels_, **settings
        )

    with counting_compiles() as compiles:
        run(both, y, channels)
        assert compiles  # else the check below says nothing
        compiles.clear()
        shared = run(acc_only, y_acc, channels)
        assert len(compiles) == 0, f"{len(compiles)} programs compiled for the second record"
    own = run(acc_only, y_acc, None)
    for name in own.state_mean:
        np.testing.assert_allclose(shared.state_mean[name], own.state_mean[name], rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(shared.trajectories, own.trajectories, rtol=1e-6, atol=1e-12)


# ---------------------------------------------------------------------------
# iterations = "auto": run until the convergence verdict holds
# ---------------------------------------------------------------------------
def test_fit_draws_halves_the_stored_paths_and_doubles_the_stride():
    from typing import NamedTuple

    class Stub(NamedTuple):
        draws: jnp.ndarray
        thin: jnp.ndarray

    n_slots = 8
    # slot j holds sweep j (stride 1); the last slot is the discard slot
    draws = jnp.broadcast_to(jnp.arange(n_slots + 1.0)[None, :, None, None], (2, n_slots + 1, 3, 1))
    st = pgas.fit_draws(Stub(draws, jnp.ones(2, jnp.int32)), 8, n_slots)
    assert int(st.thin[0]) == 1 and np.array_equal(st.draws, draws)  # fits: unchanged
    st = pgas.fit_draws(Stub(draws, jnp.ones(2, jnp.int32)), 30, n_slots)  # 30 sweeps need stride 4
    assert np.all(np.asarray(st.thin) == 4)
    np.testing.assert_array_equal(np.asarray(st.draws)[0, :2, 0, 0], [0.0, 4.0])  # sweeps 0 and 4 kept
    np.testing.assert_array_equal(np.asarray(st.draws)[1, 2:, 0, 0], 0.0)


def _auto_linear_run(progress=None):
    """``(out, ks)``: an "auto" pgas run on a linear SDOF (Matérn-3/2, missing samples) and its exact smoother."""
    prob = linear_problem(T=100, missing=True, kernel=Matern(1))
    pm = smc.ParticleModel(prob["model"], prob["params"], prob["dt"])
    A_d, Q_d, H, m0, P0 = pm.linear_discrete(pm.transition(1.0, 0.5))
    ks = kalman_smoother(A_d, Q_d, H, pm.R, m0, P0, prob["y"], prob["mask"])
    out = pgas.run_pgas(
        jax.random.key(3),
        prob["model"],
        prob["params"],
        {},
        prob["y"],
        prob["mask"],
        prob["dt"],
        particles=32,
        iterations=None,
        burn_in=200,
        chains=4,
        thin_draws=50,
        max_time=600,
        max_iterations=20_000,
        progress=progress,
    )
    return out, ks


def test_auto_runs_until_converged_and_matches_the_exact_smoother():
    """iterations=None: the run stops when R-hat and ESS over the hyperparameters and the
    monitored states say converged, well before the cap; the stored paths are thinned on the
    fly to at most thin_draws; the posterior is the exact smoother's."""
    out, ks = _auto_linear_run()
    d = out.diagnostics
    assert d["stopped"] == "converged" and d["convergence"]["converged"], d["convergence"]
    assert d["convergence"]["max_r_hat"] <= 1.01 and d["convergence"]["min_ess_bulk"] >= 400
    assert any(w["name"].startswith(("displacement[", "velocity[", "force[")) for w in d["convergence"]["worst"])
    assert 200 <= d["iterations_run"] < 20_000
    sweeps = d["iterations_run"]  # state_every = 1
    assert out.trajectories.shape[1] == -(-sweeps // d["thin"]) <= 50 < sweeps
    km = np.asarray(ks.means)
    for name, i in [("displacement", 0), ("force", 2)]:
        mean = out.state_mean[name][:, 0]
        assert np.mean((mean - km[:, i]) ** 2) / np.var(km[:, i]) < 0.005, name


def test_auto_warm_up_stops_at_half_of_max_time_and_the_draws_after_it_are_the_posterior(monkeypatch):
    """An "auto" run whose warm-up is still running at half of ``max_time`` ends it at that segment's end
    (the compiled block, built for the configured burn-in, then sees each later block numbered past it:
    no adaptation, draws stored from the first slot): the draws after the cut are the exact smoother's
    posterior, and the run reports the warm-up it ran. The test's clock jumps when a segment reports;
    the run is the test above's, so its compiled programs serve."""

    class Clock:
        now = 0.0

        def perf_counter(self):
            return self.now

    clock, reports = Clock(), []
    monkeypatch.setattr(pgas, "time", clock)

    def progress(done, total, rate):  # past half of max_time at the first report, past it 1 000 draws later
        reports.append((done, total))
        clock.now = 400.0 if done < 1_100 else 700.0

    out, ks = _auto_linear_run(progress)
    d = out.diagnostics
    assert reports[0] == (100, 20_200) and reports[1] == (200, 20_100)  # cut at the first segment's end
    assert d["burn_in_run"] == 100 and d["stopped"] in ("converged", "max_time")
    n = d["iterations_run"]
    assert n == reports[-1][0] - 100 and n <= 1_000
    assert out.trajectories.shape[1] == -(-n // d["thin"]) <= 50
    assert d["convergence"]["converged"] == (d["stopped"] == "converged")
    np.testing.assert_array_equal(out.trajectories[:, -1].any(axis=(1, 2)), True)  # every slot filled
    km, kv = np.asarray(ks.means), np.asarray(jnp.diagonal(ks.covs, axis1=1, axis2=2))
    for name, i in [("displacement", 0), ("force", 2)]:
        mean, sd = out.state_mean[name][:, 0], out.state_sd[name][:, 0]
        assert np.mean((mean - km[:, i]) ** 2) / np.var(km[:, i]) < 0.005, name
        assert np.mean(np.abs(sd / np.sqrt(kv[:, i]) - 1.0)) < 0.1, name


def test_first_check_after_a_warm_up_cut_waits_only_the_floor():
    """An uncut "auto" run first checks a tenth of its burn-in's sweeps (at least 20) after it; one whose
    warm-up max_time cut (half of it spent) checks 20 draw sweeps after the cut, so that with a burn-in of
    3 000 it can stop 280 sweeps sooner (in the compiled numbering, past the configured burn-in)."""
    from latentforce.inference.pgas_schedule import first_check, schedule

    sched = schedule(3000, 10_000)
    assert first_check(sched, None) == 3000 + 300 and first_check(sched, 3000) == 3300  # a "cut" at the end: none
    assert first_check(sched, 450) == 3000 + 20
    short = schedule(100, 1000)
    assert first_check(short, None) == first_check(short, 50) == 120
    assert first_check(schedule(600, 1000, state_every=3), None) == 200 + 20  # in blocks, not iterations


@pytest.mark.slow  # its own compile (50 s under load); tests/test_cli.py's twin runs in CI
def test_auto_stops_at_max_time_and_says_so():
    prob = linear_problem(T=50, missing=False, kernel=Matern(1))
    out = pgas.run_pgas(
        jax.random.key(4),
        prob["model"],
        prob["params"],
        {},
        prob["y"],
        prob["mask"],
        prob["dt"],
        particles=16,
        iterations=None,
        burn_in=100,
        chains=2,
        max_time=0.0,
        target_ess=1e6,
    )
    d = out.diagnostics
    assert d["stopped"] == "max_time" and not d["convergence"]["converged"]
    assert 0 < d["iterations_run"] <= 200  # the first check, after a handful of post-burn-in sweeps
    assert np.all(np.isfinite(out.state_mean["force"]))


# ---------------------------------------------------------------------------
# System parameters (m, c, k, k3 ...) sampled by run_pgas
# ---------------------------------------------------------------------------
# slow-marked for CI's time (135 s on 2026-12-02's slow 2-core machine);
# the system moves stay in CI in the Geweke test of the block with c
# and k3 free (test_gibbs_block_keeps_the_joint_distribution_of_a_nonlinear_model[with-c-k3])
@pytest.mark.slow
def test_pgas_samples_mass_damping_and_stiffness_of_a_linear_model_from_their_exact_posterior():
    """Linear SDOF, m, c and k free (lognormal priors), hyperparameters fixed: run_pgas's posterior
    of (log m, log c, log k) against the exact one, the prior times the Kalman filter's marginal
    likelihood of the same discrete model on a 31^3 grid over +-6 sd (an independent code path).
    For a linear model the joint move is the exact marginal random walk and the system move exact
    too (its Jacobian T log(m'/m) with the mass free), so the means must agree within a few
    Monte-Carlo errors and the sds within 15 %. Measured (2026-11-28, 600 iterations, two keys):
    means within 0.7-1.3 Monte-Carlo errors with this key (12), up to 3.0 (k) with key 11, sds within 2 %,
    ESS 640-1 300, R-hat <= 1.006, joint / system-move acceptance 0.31 / 0.30. Broken by dropping
    the system move's mass Jacobian: R-hat 1.41-1.53 and the draws off the grid. (Until 2026-11-28
    the test sampled c and k only, with m fixed: the same run, the mass Jacobian unchecked.)"""
    from latentforce.inference.kalman import log_likelihood

    prob = linear_problem(T=400, missing=True)
    pm = prob["pm"]
    priors = {"m": LogNormal(0.0, 0.3), "c": LogNormal(np.log(0.4), 0.5), "k": LogNormal(np.log(10.0), 0.2)}
    free = {"m": (priors["m"], 1.2), "c": (priors["c"], 0.3), "k": (priors["k"], 12.0)}
    out = pgas.run_pgas(
        jax.random.key(12),
        prob["model"],
        prob["params"],
        free,
        prob["y"],
        prob["mask"],
        prob["dt"],
        particles=16,
        iterations=600,
        burn_in=300,
        chains=4,
        initial=(0.0, 0.1),
    )
    assert out.names == ("m", "c", "k")
    hyper = hyper_moves.Hyper(prob["params"], free, ("m", "c", "k"))

    @jit
    def log_post(x):
        pm_x = hyper.model_at(pm, x)
        A_d, Q_d, H, m1, P1 = pm_x.linear_discrete(pm_x.transition(1.0, 0.5))
        log_prior = sum(priors[n].log_prob(jnp.exp(v)) + v for n, v in zip(out.names, x))  # of the logs
        return log_likelihood(A_d, Q_d, H, pm.R, m1, P1, prob["y"], prob["mask"]) + log_prior

    draws = {n: np.log(out.theta[n]) for n in out.names}
    G = 31
    grids = [
        np.linspace(np.mean(draws[n]) - 6 * np.std(draws[n]), np.mean(draws[n]) + 6 * np.std(draws[n]), G)
        for n in out.names
    ]
    X = np.stack(np.meshgrid(*grids, indexing="ij"), -1)  # (G, G, G, 3)
    flat = X.reshape(-1, 3)
    lp = np.concatenate([np.asarray(jax.vmap(log_post)(jnp.asarray(c))) for c in np.array_split(flat, 8)])
    lp = lp.reshape(G, G, G)
    w = np.exp(lp - lp.max())
    w /= w.sum()
    edges = sum(np.take(w, i, axis=a).sum() for a in range(3) for i in (0, -1))
    assert edges < 1e-4  # the grid holds the posterior
    ess = out.diagnostics["ess_bulk"]
    for i, n in enumerate(out.names):
        mean = float(np.sum(w * X[..., i]))
        sd = float(np.sqrt(np.sum(w * (X[..., i] - mean) ** 2)))
        assert abs(np.mean(draws[n]) - mean) < 4.0 * sd / np.sqrt(ess[n]), (n, np.mean(draws[n]), mean, sd, ess[n])
        assert abs(np.std(draws[n]) / sd - 1.0) < 0.15, (n, np.std(draws[n]), sd)
    assert min(ess.values()) > 200 and max(out.diagnostics["rhat"].values()) < 1.02
    assert 0.2 < np.mean(out.diagnostics["acceptance_joint"]) < 0.7
    assert 0.2 < np.mean(out.diagnostics["acceptance_system"]) < 0.7
    # the run started at the filter's posterior mode (pgas_mode), for a linear model the exact one:
    # the grid's best point, with the Laplace sds about the grid's
    start = out.diagnostics["start"]
    best = np.unravel_index(np.argmax(lp), lp.shape)
    for i, n in enumerate(out.names):
        sd = float(np.sqrt(np.sum(w * (X[..., i] - np.sum(w * X[..., i])) ** 2)))
        assert abs(np.log(start["mode"][n]) - X[best][i]) < 0.4 * sd, (n, start["mode"][n], np.exp(X[best][i]))
        assert 0.6 < start["laplace_sd_log"][n] / sd < 1.5, (n, start["laplace_sd_log"][n], sd)
