"""latentforce.linalg: the LAPACK-free factorisations and solves, against NumPy, and the
samplers' compiled programs free of LAPACK calls (the module doc says why)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import latentforce  # noqa: F401
from latentforce import linalg
from latentforce.kernels import Matern
from latentforce.models import LatentForceModel, Sensor
from latentforce.priors import LogNormal
from latentforce.systems import Duffing, LinearSystem


def _spd(rng, n, cond=1e3):
    Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
    return (Q * np.geomspace(1.0, 1.0 / cond, n)) @ Q.T


@pytest.mark.parametrize("n", [1, 2, 5, 30])
def test_cholesky_matches_numpy(n):
    rng = np.random.default_rng(n)
    A = _spd(rng, n)
    L = np.asarray(linalg.cholesky(jnp.asarray(A)))
    np.testing.assert_allclose(L, np.linalg.cholesky(A), rtol=1e-10, atol=1e-12)
    assert np.all(np.triu(L, 1) == 0.0)
    # only the lower triangle is read
    junk = A + np.triu(rng.normal(size=(n, n)), 1)
    np.testing.assert_allclose(np.asarray(linalg.cholesky(jnp.asarray(junk))), L, rtol=1e-12, atol=1e-14)


def test_cholesky_batches_and_fails_like_jax():
    rng = np.random.default_rng(0)
    As = np.stack([_spd(rng, 4) for _ in range(3)])
    Ls = np.asarray(jax.vmap(linalg.cholesky)(jnp.asarray(As)))
    np.testing.assert_allclose(Ls, np.linalg.cholesky(As), rtol=1e-10, atol=1e-12)
    indefinite = np.diag([1.0, -1.0, 2.0])
    singular = np.ones((3, 3))
    for bad in (indefinite, singular, np.full((2, 2), np.nan)):
        assert np.all(np.isnan(np.asarray(linalg.cholesky(jnp.asarray(bad))))), bad


def test_psd_sqrt_of_rank_deficient_matrices():
    rng = np.random.default_rng(1)
    for n, r in [(5, 5), (5, 3), (6, 1), (3, 0)]:
        B = rng.normal(size=(n, r)) * np.geomspace(1.0, 1e-3, max(r, 1))[:r]
        A = B @ B.T
        A[0, 0] -= 1e-17  # round-off below zero in a null direction must not matter
        S = np.asarray(linalg.psd_sqrt(jnp.asarray(A)))
        assert np.all(np.isfinite(S))
        np.testing.assert_allclose(S @ S.T, A, atol=1e-12 * max(1.0, np.abs(A).max()))
    A = _spd(rng, 4)  # full rank: the Cholesky factor
    np.testing.assert_allclose(np.asarray(linalg.psd_sqrt(jnp.asarray(A))), np.linalg.cholesky(A), rtol=1e-10)


@pytest.mark.parametrize("rhs", [(6,), (6, 3)])
def test_triangular_and_cholesky_solves(rhs):
    rng = np.random.default_rng(2)
    A = _spd(rng, 6)
    L = np.linalg.cholesky(A)
    B = rng.normal(size=rhs)
    np.testing.assert_allclose(
        np.asarray(linalg.solve_lower(jnp.asarray(L), jnp.asarray(B))), np.linalg.solve(L, B), rtol=1e-9, atol=1e-12
    )
    np.testing.assert_allclose(
        np.asarray(linalg.solve_lower(jnp.asarray(L), jnp.asarray(B), transpose=True)),
        np.linalg.solve(L.T, B),
        rtol=1e-9,
        atol=1e-12,
    )
    np.testing.assert_allclose(
        np.asarray(linalg.cho_solve(jnp.asarray(L), jnp.asarray(B))), np.linalg.solve(A, B), rtol=1e-8, atol=1e-11
    )


def test_general_solve_pivots():
    rng = np.random.default_rng(3)
    # a zero leading pivot and a tiny one: without row exchanges these fail or lose all accuracy
    for A in (
        np.array([[0.0, 1.0], [1.0, 0.0]]),
        np.array([[1e-18, 1.0], [1.0, 1.0]]),
        rng.normal(size=(9, 9)),
        np.kron(rng.normal(size=(3, 3)), np.eye(3)) + np.kron(np.eye(3), rng.normal(size=(3, 3))),
    ):
        n = A.shape[0]
        for B in (rng.normal(size=n), rng.normal(size=(n, 4))):
            X = np.asarray(linalg.solve(jnp.asarray(A), jnp.asarray(B)))
            np.testing.assert_allclose(X, np.linalg.solve(A, B), rtol=1e-9, atol=1e-11)
        np.testing.assert_allclose(np.asarray(linalg.inv(jnp.asarray(A))), np.linalg.inv(A), rtol=1e-9, atol=1e-11)
    assert not np.all(np.isfinite(np.asarray(linalg.solve(jnp.ones((3, 3)), jnp.ones(3)))))


def test_derivatives_match_jax_linalg():
    """Forward and reverse mode through the loops agree with JAX's own (LAPACK-backed) rules."""
    rng = np.random.default_rng(4)
    A0, B = jnp.asarray(_spd(rng, 4, cond=10.0)), jnp.asarray(rng.normal(size=4))
    dA = jnp.asarray(0.01 * rng.normal(size=(4, 4)))

    def ours(t):
        A = A0 + t * (dA + dA.T)
        return (
            jnp.sum(linalg.cholesky(A)) + jnp.sum(linalg.solve(A, B)) + jnp.sum(linalg.cho_solve(linalg.cholesky(A), B))
        )

    def theirs(t):
        A = A0 + t * (dA + dA.T)
        return (
            jnp.sum(jnp.linalg.cholesky(A))
            + jnp.sum(jnp.linalg.solve(A, B))
            + jnp.sum(jax.scipy.linalg.cho_solve((jnp.linalg.cholesky(A), True), B))
        )

    assert np.isfinite(float(theirs(0.1)))  # positive definite along the way
    for d in (lambda f: f, jax.jacfwd, jax.grad):
        np.testing.assert_allclose(float(d(ours)(0.1)), float(d(theirs)(0.1)), rtol=1e-8)


# ---------------------------------------------------------------------------
# The samplers' programs hold no LAPACK call
# ---------------------------------------------------------------------------
def _recording_programs(monkeypatch, texts, *modules):
    """Replace every module-level compiled program (a ``jit`` function) of ``modules`` by one that
    keeps its StableHLO text, once per program and signature (the arguments' tree, the arrays' shapes
    and types, the other arguments' values): the optimiser calls one program hundreds of times."""
    seen = set()
    for module in modules:
        for name, prog in list(vars(module).items()):
            if not (callable(prog) and hasattr(prog, "lower") and hasattr(prog, "trace")):
                continue

            def call(*args, _prog=prog, _name=name, **kw):
                leaves, tree = jax.tree_util.tree_flatten((args, kw))
                sig = tuple((np.shape(x), str(x.dtype)) if hasattr(x, "dtype") else x for x in leaves)
                if (_name, tree, sig) not in seen:
                    seen.add((_name, tree, sig))
                    texts.append((_name, _prog.lower(*args, **kw).as_text()))
                return _prog(*args, **kw)

            monkeypatch.setattr(module, name, call)


def _lapack_calls(texts):
    return sorted({name for name, text in texts if "lapack" in text})


# with-k3 slow-marked for CI's time (its programs use the same linalg as the others; 60-120 s)
@pytest.mark.parametrize(
    "system", [False, pytest.param(True, marks=pytest.mark.slow)], ids=["hyperparameters", "with-k3"]
)
def test_particle_gibbs_programs_call_no_lapack(monkeypatch, system):
    """Every program of a nonlinear PGAS run (free hyperparameters, so the theta steps, the
    low-frequency and the residual-preserving moves all run; chains vmapped, which is what
    batches the factorisations) is free of LAPACK custom calls; ``with-k3``: k3 sampled too (the
    per-chain model in every program, and the filter's mode search that starts the run)."""
    from latentforce.inference import laplace, particle_model, pgas

    texts = []
    _recording_programs(monkeypatch, texts, pgas, particle_model, laplace)
    model = LatentForceModel(Duffing(), Matern(0), [Sensor("acceleration", 0, 0.1)])
    params = dict(m=1.0, c=0.5, k=10.0, k3=1000.0, force_variance=1.0, force_lengthscale=0.5)
    free = {"force_variance": (LogNormal(0.0, 1.0), 1.0), "force_lengthscale": (LogNormal(-0.5, 1.0), 0.5)}
    if system:
        free["k3"] = (LogNormal(np.log(1000.0), 0.5), 800.0)
    y = np.sin(np.arange(32) * 0.3)[:, None]
    out = pgas.run_pgas(
        jax.random.key(0, impl="rbg"),
        model,
        params,
        free,
        y,
        np.ones(y.shape, bool),
        0.05,
        particles=8,
        iterations=4,
        burn_in=2,
        chains=2,
    )
    assert np.all(np.isfinite(out.state_mean["force"]))
    names = {name for name, _ in texts}
    expected = {"_run_chunk", "_shapes", "_smooth", "_init_chains", "_start_transitions", "_derived_program"}
    assert expected | ({"_value_and_grad", "_centres"} if system else set()) <= names, names
    assert ("k3" in out.theta) == system
    assert _lapack_calls(texts) == [], _lapack_calls(texts)


def test_kalman_programs_call_no_lapack(monkeypatch):
    """The linear path: the optimiser's gradient, Kalman MCMC and NUTS over chains, and the
    mixture of smoothers (vmapped over parameter draws, with backward sampling)."""
    from latentforce.inference import kalman_mcmc, kalman_nuts, laplace, mixture

    texts = []
    _recording_programs(monkeypatch, texts, kalman_mcmc, kalman_nuts, laplace, mixture)
    M, K = np.diag([1.0, 0.5]), np.array([[30.0, -10.0], [-10.0, 10.0]])
    model = LatentForceModel(
        LinearSystem(ndof=2, force_dofs=(0,)),
        Matern(1),
        [Sensor("acceleration", 0, 0.05), Sensor("acceleration", 1, 0.05)],
    )
    fixed = dict(M=M, C=0.02 * K + 0.1 * M, K=K, force_variance=1.0, force_lengthscale=0.5)
    free = {"force_variance": (LogNormal(0.0, 1.0), 1.0)}
    y = np.random.default_rng(0).normal(size=(24, 2))
    mask = np.ones(y.shape, bool)
    out = kalman_mcmc.run_kalman_mcmc(
        jax.random.key(0), model, fixed, free, y, mask, 0.05, iterations=8, burn_in=4, chains=2
    )
    kalman_nuts.run_kalman_nuts(jax.random.key(2), model, fixed, free, y, mask, 0.05, iterations=4, burn_in=4, chains=2)
    mixture.mixture_posterior(jax.random.key(1), model, fixed, out.draws, y, mask, 0.05, thin_draws=2)
    names = {name for name, _ in texts}
    assert {"_run_chains", "_init_chains", "_value_and_grad", "_batch"} <= names, names
    assert _lapack_calls(texts) == [], _lapack_calls(texts)
