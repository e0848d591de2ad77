"""Particle filter and conditional SMC (latentforce.inference.smc) against exact answers."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import latentforce  # noqa: F401
from latentforce.compile import jit
from latentforce.inference import smc
from latentforce.inference.kalman import log_likelihood
from latentforce.kernels import Matern
from latentforce.models import LatentForceModel, Sensor
from latentforce.systems import Duffing, LinearSystem

NOISE = (0.05, 0.3)


def linear_problem(T=50, seed=1, kernel=Matern(0), missing=True, noise=NOISE, init_sd=0.1):
    """Linear SDOF model, data simulated from the *same* discrete model PGAS uses."""
    model = LatentForceModel(
        LinearSystem(), kernel, [Sensor("displacement", 0, noise[0]), Sensor("acceleration", 0, noise[1])]
    )
    params = dict(m=1.0, c=0.4, k=10.0, force_variance=1.0, force_lengthscale=0.5)
    dt = 0.05
    pm = smc.ParticleModel(model, params, dt, initial=(0.0, init_sd))
    tr = pm.transition(1.0, 0.5)
    A_d, Q_d, H, m0f, P0 = pm.linear_discrete(tr)
    rng = np.random.default_rng(seed)
    x = rng.multivariate_normal(np.asarray(m0f), np.asarray(P0))
    ys = []
    for _ in range(T):
        ys.append(np.asarray(H) @ x + rng.normal(size=2) * np.asarray(noise))
        x = np.asarray(A_d) @ x + rng.multivariate_normal(np.zeros(pm.n_state), np.asarray(Q_d))
    y = np.array(ys)
    mask = np.ones(y.shape, bool)
    if missing:
        mask[10:15, 1] = False
        y[10:15, 1] = np.nan
    return dict(
        model=model,
        params=params,
        dt=dt,
        pm=pm,
        tr=tr,
        A_d=A_d,
        Q_d=Q_d,
        H=H,
        m0f=m0f,
        P0=P0,
        y=jnp.asarray(y),
        mask=jnp.asarray(mask),
    )


def test_sampler_discretisation_is_the_exact_one_for_linear_systems():
    """The latent (force states + within-step mechanical noise) reproduces the exact Van Loan
    discretisation of the continuous model: A up to RK4's error, Q exactly."""
    prob = linear_problem(T=5, kernel=Matern(1))
    pm = prob["pm"]
    A_ex, Q_ex = prob["model"].discretise(
        {**prob["params"], "force_variance": 1.0, "force_lengthscale": 0.5}, prob["dt"]
    )
    nm = pm.nm
    # force columns exact; the homogeneous mechanical block carries RK4's O((omega dt)^5) error
    np.testing.assert_allclose(prob["A_d"][:, nm:], A_ex[:, nm:], rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(prob["A_d"][:nm, :nm], A_ex[:nm, :nm], atol=(np.sqrt(10.0) * 0.05) ** 5 / 20)
    scale = np.sqrt(np.outer(np.diag(Q_ex), np.diag(Q_ex)))
    assert np.max(np.abs(np.asarray(prob["Q_d"]) - np.asarray(Q_ex)) / scale) < 1e-8
    # path <-> latent round trip
    g = jax.random.normal(jax.random.key(0), (20, pm.nl))
    np.testing.assert_allclose(pm.latent(pm.path(g)), g, atol=1e-12)


@pytest.mark.parametrize("scheme", ["multinomial", "systematic", "stratified"])
def test_resamplers_are_unbiased(scheme):
    w = jnp.array([0.1, 0.2, 0.3, 0.4, 0.0])
    keys = jax.random.split(jax.random.key(0), 4000)
    idx = jax.vmap(lambda k: smc.RESAMPLING[scheme](k, jnp.log(w), 10))(keys)
    counts = jax.vmap(lambda i: jnp.bincount(i, length=5))(idx)
    mean = np.asarray(counts.mean(0))
    se = np.asarray(counts.std(0)) / np.sqrt(keys.shape[0]) + 1e-12
    assert np.all(np.abs(mean - 10 * np.asarray(w)) <= 5 * se + 1e-9)
    assert np.all(np.asarray(counts[:, 4]) == 0)  # zero weight never drawn


def test_box_muller_normals_are_standard_normal():
    from scipy import stats

    x = np.asarray(smc.box_muller(jax.random.key(3, impl="rbg"), (301, 7, 3)))  # odd count: one pair cut
    assert x.shape == (301, 7, 3) and np.all(np.isfinite(x))
    flat = x.ravel()
    assert stats.kstest(flat, "norm").pvalue > 1e-3
    # the two halves (cos and sin of the same radius) are uncorrelated
    half = flat.size // 2
    assert abs(np.corrcoef(flat[:half], flat[half : 2 * half])[0, 1]) < 4.0 / np.sqrt(half)
    assert abs(np.mean(flat**2) - 1.0) < 5.0 * np.sqrt(2.0 / flat.size)


def test_unit_circle_is_the_cosine_and_sine_of_the_words_angle():
    rng = np.random.default_rng(11)
    edges = [0, 1, 2**30 - 1, 2**30, 2**31 - 1, 2**31, 3 * 2**30 - 1, 3 * 2**30, 2**32 - 1]
    w = np.concatenate([np.array(edges, dtype=np.uint64), rng.integers(0, 2**32, 200000, dtype=np.uint64)])
    cos, sin = smc.unit_circle(jnp.asarray(w.astype(np.uint32)))
    assert cos.dtype == jnp.float32
    phi = 2.0 * np.pi * w / 2.0**32  # the angle the word encodes, in double precision
    np.testing.assert_allclose(np.asarray(cos, float), np.cos(phi), rtol=0, atol=3e-7)
    np.testing.assert_allclose(np.asarray(sin, float), np.sin(phi), rtol=0, atol=3e-7)


def test_uniform32_is_uniform_on_the_open_interval():
    from scipy import stats

    u = np.asarray(smc.uniform32(jax.random.key(5), (20000,)))
    assert u.dtype == np.float64 and np.all((u > 0) & (u < 1))
    assert stats.kstest(u, "uniform").pvalue > 1e-3
    # every value is on the 2^-32 grid, offset by half a step (never an endpoint)
    grid = u * 2.0**32 - 0.5
    np.testing.assert_array_equal(grid, np.round(grid))


def test_box_muller_extremes_are_finite_and_bounded(monkeypatch):
    # the smallest and largest 32-bit words: the largest radius (the documented
    # 6.76 sd cut) and a zero radius; both finite
    words = jnp.array([[0, 2**32 - 1], [0, 2**32 - 1]], dtype=jnp.uint32)
    monkeypatch.setattr(jax.random, "bits", lambda key, shape, dtype: words)
    z = np.asarray(smc.box_muller(jax.random.key(0), (4,)))
    monkeypatch.undo()
    assert z.dtype == np.float64 and np.all(np.isfinite(z))
    assert 6.7 < z[0] < 6.77 and abs(z[1]) < 1e-3 and abs(z[2]) < 1e-6
    z = np.asarray(smc.box_muller(jax.random.key(7), (200000,)))
    assert np.all(np.abs(z) < 6.77)


def test_observation_and_step_match_the_model():
    model = LatentForceModel(
        Duffing(),
        Matern(1),
        [Sensor("displacement", 0, 0.1), Sensor("velocity", 0, 0.1), Sensor("acceleration", 0, 0.1)],
    )
    params = dict(m=1.3, c=0.2, k=10.0, k3=50.0, force_variance=1.0, force_lengthscale=0.5)
    x = jnp.array([0.1, -0.3, 0.7, 0.2])
    for disc in ("euler", "rk4"):
        pm = smc.ParticleModel(model, params, 1e-3, disc)
        np.testing.assert_allclose(pm._observe(x[:2], x[2:]), model.observe(params, x), rtol=1e-12)
        np.testing.assert_allclose(pm.offset(x[:2]) + pm.D @ x[2:], model.observe(params, x), rtol=1e-12)
        # one step agrees with the drift of the augmented SDE to first order
        step = pm.phi(x[:2], x[2:])
        drift = model.drift(params, x)[:2]
        np.testing.assert_allclose((step - x[:2]) / 1e-3, drift, rtol=1e-2, atol=1e-3)


@pytest.mark.parametrize("proposal,particles,noise", [("bootstrap", 100, (0.2, 1.0)), ("optimal", 100, NOISE)])
def test_particle_filter_log_likelihood_is_unbiased(proposal, particles, noise):
    """E[Z_hat] = Z: mean of exp(logZ_hat - logZ_kalman) is 1 within 5 Monte-Carlo s.e."""
    # a tight initial mechanical prior: mech_1 is a static parameter of the filter
    # (never rejuvenated), which is what makes log Z_hat noisy
    prob = linear_problem(T=30, noise=noise, init_sd=0.02)
    ll = float(
        log_likelihood(
            prob["A_d"], prob["Q_d"], prob["H"], prob["pm"].R, prob["m0f"], prob["P0"], prob["y"], prob["mask"]
        )
    )
    sc = smc.sweep_constants(prob["pm"], prob["tr"], prob["y"], prob["mask"], proposal)
    sweep = smc.make_sweep(prob["pm"], particles, proposal=proposal, conditional=False)
    runs = 300
    keys = jax.random.split(jax.random.key(7), runs)
    ref = jnp.zeros((prob["y"].shape[0], prob["pm"].n_state))
    L = np.asarray(jit(jax.vmap(lambda k: sweep(k, sc, ref).info.log_likelihood))(keys))
    assert np.all(np.isfinite(L))
    # the CLT on W needs a modest log-variance; the tests are set up so that it holds
    assert L.std() < 1.25, L.std()
    W = np.exp(L - ll)
    se = W.std(ddof=1) / np.sqrt(runs)
    assert abs(W.mean() - 1.0) < 5 * se, (W.mean(), se)
    # and the log estimate is biased low by about var/2 (delta method)
    assert abs(L.mean() + 0.5 * L.var() - ll) < 5 * L.std() / np.sqrt(runs) + 0.05


def test_optimal_proposal_has_lower_variance():
    prob = linear_problem(T=40)
    out = {}
    for proposal in ("bootstrap", "optimal"):
        sc = smc.sweep_constants(prob["pm"], prob["tr"], prob["y"], prob["mask"], proposal)
        sweep = smc.make_sweep(prob["pm"], 50, proposal=proposal, conditional=False)
        keys = jax.random.split(jax.random.key(3), 100)
        ref = jnp.zeros((prob["y"].shape[0], prob["pm"].n_state))
        out[proposal] = np.asarray(jit(jax.vmap(lambda k: sweep(k, sc, ref).info.log_likelihood))(keys)).std()
    assert out["optimal"] < out["bootstrap"]


def test_conditional_sweep_keeps_reference_and_compiles_once():
    prob = linear_problem(T=30)
    pm = prob["pm"]
    traces = []
    sweep = smc.make_sweep(pm, 16)

    def f(key, sc, ref):
        traces.append(1)  # runs only while tracing
        return sweep(key, sc, ref)

    f = jit(f)
    sc = smc.sweep_constants(pm, prob["tr"], prob["y"], prob["mask"])
    ref = pm.path(jnp.zeros((30, pm.nl)))
    out1 = f(jax.random.key(0), sc, ref)
    # with a different reference, key and theta: same shapes, no retrace
    sc2 = smc.sweep_constants(pm, pm.transition(2.0, 0.3), prob["y"], prob["mask"])
    out2 = f(jax.random.key(1), sc2, out1.trajectory)
    assert len(traces) == 1
    # innovation form: particle N-1 keeps the reference's innovations q'_t = g'_t - A g'_{t-1},
    # driven from the ancestor it drew (the reference itself at t = 0)
    ref, parts, anc = out1.trajectory, out2.particles, out2.ancestors
    nm, nfx = pm.nm, pm.nfx
    A_f = sc2.A[:nfx]
    q_ref = ref[1:, nm:] - ref[:-1, nm:] @ A_f.T
    np.testing.assert_allclose(parts[0, -1], ref[0])
    prev = parts[np.arange(29), anc[1:, -1]]  # each step's drawn ancestor of particle N-1
    np.testing.assert_allclose(parts[1:, -1, nm:] - prev[:, nm:] @ A_f.T, q_ref, atol=1e-12)
    assert np.any(np.asarray(anc[1:, -1]) != 15)  # it did switch
    # without ancestor sampling (CSMC) the reference is kept whole
    csmc = jit(smc.make_sweep(pm, 16, ancestor_sampling=False))(jax.random.key(1), sc2, ref)
    np.testing.assert_allclose(csmc.particles[:, -1], ref, atol=1e-12)
    # the state form (nonlinear systems' default) keeps the reference's force states
    state = jit(smc.make_sweep(pm, 16, innovation=False))(jax.random.key(1), sc2, ref)
    np.testing.assert_allclose(state.particles[:, -1, nm:], ref[:, nm:], atol=1e-12)
    assert float(state.info.switched) > 0.0
    # the returned path is a lineage: traced back through the stored ancestors
    path = out2.trajectory
    idx = [int(out2.info.final_index)]
    for t in range(29, 0, -1):
        idx.append(int(out2.ancestors[t, idx[-1]]))
    np.testing.assert_array_equal(path, out2.particles[np.arange(30), np.array(idx[::-1])])
    assert 0.0 < float(out2.info.switched) <= 1.0


def test_state_form_ancestor_information_is_exact_for_linear_model():
    """The state form (nonlinear systems' default): Delta for a perturbation of the mechanical
    state with the future latent held equals the brute-force change of the future log-likelihood."""
    prob = linear_problem(T=25)
    pm = prob["pm"]
    sc = smc.sweep_constants(pm, prob["tr"], prob["y"], prob["mask"])
    g = jax.random.normal(jax.random.key(2), (25, pm.nl)).at[:, pm.nfx :].multiply(0.01)
    ref = pm.path(g)
    Lam, eta = smc.ancestor_information(pm, sc, ref, innovation=False)
    t = 5
    delta = jnp.array([0.03, -0.2])

    def future_loglik(mech_t):
        path = pm.path(g[t:].at[0, pm.nfx :].set(mech_t - pm.mech0_mean))
        r = sc.y[t:] - jax.vmap(lambda x: pm._observe(x[: pm.nm], x[pm.nm :]))(path) * sc.maskf[t:]
        return -0.5 * jnp.sum(jnp.einsum("td,tde,te->t", r, sc.Rinv[t:], r))

    brute = future_loglik(ref[t, : pm.nm] + delta) - future_loglik(ref[t, : pm.nm])
    approx = -0.5 * delta @ Lam[t] @ delta + delta @ eta[t]
    np.testing.assert_allclose(approx, brute, rtol=1e-8)


@pytest.mark.parametrize("order", [0, 1, 2, 3])
def test_ancestor_information_is_exact_for_linear_model(order):
    """Delta from the information recursion equals the brute-force change of the future
    log-likelihood when the whole state at t is perturbed and the future innovations are held
    (the innovation form of the ancestor weights), for every Matérn order."""
    prob = linear_problem(T=25, kernel=Matern(order))
    pm = prob["pm"]
    nm, nfx = pm.nm, pm.nfx
    sc = smc.sweep_constants(pm, prob["tr"], prob["y"], prob["mask"])
    g = jax.random.normal(jax.random.key(2), (25, pm.nl)).at[:, pm.nfx :].multiply(0.01)
    ref = pm.path(g)
    Lam, eta = smc.ancestor_information(pm, sc, ref)
    A = prob["tr"].A
    q = g - jnp.concatenate([jnp.zeros((1, pm.nl)), g[:-1] @ A.T])  # the innovations
    t = 5

    def rollout(x_t):
        def step(x, q_s):  # x_s = Phi(mech, x_f) + E x_f + q_w, A_f x_f + q_f
            m = A @ jnp.concatenate([x[nm:], jnp.zeros(nm)])
            nxt = jnp.concatenate([pm.phi(x[:nm], x[nm:]) + m[nfx:] + q_s[nfx:], m[:nfx] + q_s[:nfx]])
            return nxt, nxt

        _, xs = jax.lax.scan(step, x_t, q[t + 1 :])
        return jnp.concatenate([x_t[None], xs])

    def future_loglik(x_t):
        path = rollout(x_t)
        r = sc.y[t:] - jax.vmap(lambda x: pm._observe(x[:nm], x[nm:]))(path) * sc.maskf[t:]
        return -0.5 * jnp.sum(jnp.einsum("td,tde,te->t", r, sc.Rinv[t:], r))

    np.testing.assert_allclose(rollout(ref[t]), ref[t:], rtol=1e-10, atol=1e-12)  # held innovations rebuild it
    delta = 0.05 * jax.random.normal(jax.random.key(order), (pm.n_state,)) * jnp.sqrt(jnp.diagonal(prob["P0"]))
    brute = future_loglik(ref[t] + delta) - future_loglik(ref[t])
    approx = -0.5 * delta @ Lam[t] @ delta + delta @ eta[t]
    assert abs(float(brute)) > 1e-3  # the perturbation matters
    np.testing.assert_allclose(approx, brute, rtol=1e-8)


def test_a_particle_that_overflows_gets_no_weight_and_the_path_stays_finite():
    """At extreme parameters (a force variance of 1e12 on a stiff Duffing with 2 RK4 substeps) some
    particles' weights are not finite: they must get none. Before, a NaN weight made every
    resampling point pick particle 0, and a NaN path then held the chain for good (14 476 NaN
    particle values and a NaN log-likelihood on this case). The conditional sweep (the sampler's)
    always keeps the finite reference to resample from."""
    from latentforce.systems import Duffing

    model = LatentForceModel(Duffing(substeps=2), Matern(1), [Sensor("acceleration", 0, 0.5)])
    params = dict(m=1.0, c=0.5, k=100.0, k3=1e6, force_variance=1e12, force_lengthscale=2e-3)
    pm = smc.ParticleModel(model, params, 0.02, initial=(0.0, 0.1))
    y = np.random.default_rng(0).normal(size=(60, 1)) * 100
    sc = smc.sweep_constants(pm, pm.transition(1e12, 2e-3), y, np.ones(y.shape, bool))
    sweep = smc.make_sweep(pm, 64, innovation=False)
    out = jit(sweep)(jax.random.key(0), sc, jnp.zeros((60, pm.n_state)))
    assert np.all(np.isfinite(np.asarray(out.trajectory)))
    assert np.isfinite(float(out.info.log_likelihood))
