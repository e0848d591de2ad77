"""Matérn kernels: state-space form against the kernel; discretisation; the augmented model."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.scipy.linalg import expm

import latentforce  # noqa: F401
from latentforce.kernels import KernelParams, Matern, Sum, kernel_from_name, matern_bessel
from latentforce.linalg import expm as expm13
from latentforce.linalg import expm_balanced, solve_lyapunov, van_loan
from latentforce.models import LatentForceModel, Sensor
from latentforce.systems import Duffing, LinearSystem

LAGS = np.concatenate([[0.0], np.logspace(-3, 1, 40)])


def closed_form(p, tau, var, ell):
    r = np.abs(tau) / ell
    if p == 0:
        return var * np.exp(-r)
    if p == 1:
        return var * (1 + np.sqrt(3) * r) * np.exp(-np.sqrt(3) * r)
    if p == 2:
        return var * (1 + np.sqrt(5) * r + 5 * r**2 / 3) * np.exp(-np.sqrt(5) * r)
    raise ValueError(p)


@pytest.mark.parametrize("p", [0, 1, 2, 3, 4])
@pytest.mark.parametrize("var,ell", [(1.0, 1.0), (20.0, 0.1), (1e4, 7.5)])
def test_state_space_covariance_is_the_kernel(p, var, ell):
    k = Matern(p)
    params = KernelParams(jnp.asarray(var), jnp.asarray(ell))
    ss_cov = np.asarray(k.state_covariance(LAGS * ell, params))
    exact = closed_form(p, LAGS * ell, var, ell) if p <= 2 else matern_bessel(LAGS * ell, p + 0.5, var, ell)
    np.testing.assert_allclose(ss_cov, exact, rtol=1e-8, atol=1e-11 * var)
    np.testing.assert_allclose(np.asarray(k.covariance(LAGS * ell, params)), exact, rtol=1e-10, atol=1e-12 * var)


@pytest.mark.parametrize("p", [0, 1, 2, 3])
def test_discretisation_preserves_the_stationary_covariance(p):
    k = Matern(p)
    params = KernelParams(jnp.asarray(3.0), jnp.asarray(0.4))
    ss = k.state_space(params)
    for dt in (1e-4, 0.01, 0.3, 5.0):
        A, Q = k.discretise(params, dt)
        np.testing.assert_allclose(np.asarray(A), np.asarray(expm_balanced(ss.F * dt)), rtol=1e-10, atol=1e-14)
        np.testing.assert_allclose(
            np.asarray(A @ ss.Pinf @ A.T + Q),
            np.asarray(ss.Pinf),
            rtol=1e-9,
            atol=1e-10 * float(jnp.max(jnp.abs(ss.Pinf))),
        )
        assert np.all(np.linalg.eigvalsh(np.asarray(Q)) > -1e-12 * float(jnp.max(jnp.abs(Q))))


@pytest.mark.parametrize("n", [1, 2, 5, 8])
def test_expm_matches_eigendecomposition(n):
    """Our scaling-and-squaring Padé-13 against exp of a diagonalisable matrix, norms 1e-8 to 200."""
    rng = np.random.default_rng(n)
    V = rng.normal(size=(n, n)) + 3.0 * np.eye(n)
    for scale in (1e-8, 1e-3, 0.5, 5.0, 60.0, 200.0):
        lam = scale * (rng.uniform(-1.0, 0.3, size=n))  # mostly decaying, like an SDE's drift
        F = V @ np.diag(lam) @ np.linalg.inv(V)
        exact = V @ np.diag(np.exp(lam)) @ np.linalg.inv(V)
        got = np.asarray(expm13(jnp.asarray(F)))
        np.testing.assert_allclose(got, exact, rtol=1e-9, atol=1e-11 * np.max(np.abs(exact)))
        np.testing.assert_allclose(got, np.asarray(expm(jnp.asarray(F))), rtol=1e-9, atol=1e-11 * np.max(np.abs(exact)))
    # a non-finite matrix (an MH proposal far out) comes back non-finite at once, no runaway squaring loop
    assert not np.any(np.isfinite(np.asarray(expm13(jnp.full((n, n), jnp.nan)))))
    # forward-mode derivative against the Fréchet derivative from the block-triangular identity
    F, E = jnp.asarray(rng.normal(size=(n, n))), jnp.asarray(rng.normal(size=(n, n)))
    _, tangent = jax.jvp(expm13, (F,), (E,))
    block = expm(jnp.block([[F, E], [jnp.zeros((n, n)), F]]))
    np.testing.assert_allclose(np.asarray(tangent), np.asarray(block[:n, n:]), rtol=1e-8, atol=1e-10)


def test_van_loan_matches_closed_form_for_ou():
    lam, q, dt = 3.0, 2.0, 0.2
    A, Q = van_loan(jnp.array([[-lam]]), jnp.array([[q]]), dt)
    assert np.isclose(float(A[0, 0]), np.exp(-lam * dt))
    assert np.isclose(float(Q[0, 0]), q / (2 * lam) * (1 - np.exp(-2 * lam * dt)), rtol=1e-12)


def test_lyapunov_solution():
    F = jnp.array([[0.0, 1.0], [-4.0, -0.3]])
    W = jnp.array([[0.0, 0.0], [0.0, 2.0]])
    P = solve_lyapunov(F, W)
    np.testing.assert_allclose(np.asarray(F @ P + P @ F.T + W), 0.0, atol=1e-12)


def test_sum_and_product_kernels():
    a, b = Matern(0), Matern(1)
    pa, pb = KernelParams(jnp.asarray(2.0), jnp.asarray(0.5)), KernelParams(jnp.asarray(1.0), jnp.asarray(2.0))
    tau = LAGS[:20]
    s, m = Sum(a, b), a * b
    np.testing.assert_allclose(
        np.asarray(s.state_covariance(tau, (pa, pb))),
        closed_form(0, tau, 2.0, 0.5) + closed_form(1, tau, 1.0, 2.0),
        rtol=1e-9,
    )
    np.testing.assert_allclose(
        np.asarray(m.state_covariance(tau, (pa, pb))),
        closed_form(0, tau, 2.0, 0.5) * closed_form(1, tau, 1.0, 2.0),
        rtol=1e-8,
    )


def test_kernel_names_and_differentiability():
    assert kernel_from_name("matern52") == Matern(2)
    with pytest.raises(KeyError):
        kernel_from_name("rbf")
    g = jax.grad(lambda ell: Matern(1).state_space(KernelParams(jnp.asarray(1.0), ell)).Pinf[1, 1])(0.7)
    # Pinf[1,1] = variance * lambda^2 = 3 / ell^2  ->  derivative -6 / ell^3
    assert np.isclose(float(g), -6 / 0.7**3, rtol=1e-10)


def test_augmented_model_accelerometer_row_and_stationarity():
    model = LatentForceModel(LinearSystem(), Matern(1), [Sensor("acceleration", 0, 0.1)])
    p = dict(m=2.0, c=0.5, k=8.0, force_variance=3.0, force_lengthscale=0.6)
    H, _ = model.observation(p)
    np.testing.assert_allclose(np.asarray(H[0]), [-4.0, -0.25, 0.5, 0.0])  # (-k/m, -c/m, 1/m, 0): Eq. 23b
    F, W = model.continuous(p)
    m0, P0 = model.stationary_initial(p)
    np.testing.assert_allclose(np.asarray(F @ P0 + P0 @ F.T + W), 0.0, atol=1e-10)
    A, Q = model.discretise(p, 0.05)
    np.testing.assert_allclose(np.asarray(A @ P0 @ A.T + Q), np.asarray(P0), rtol=1e-8, atol=1e-10)
    # the nonlinear drift of a linear system equals the linear drift
    x = jnp.array([0.1, -0.2, 0.3, 0.05])
    np.testing.assert_allclose(np.asarray(model.drift(p, x)), np.asarray(F @ x), rtol=1e-12)


def test_mdof_augmented_model():
    M = jnp.diag(jnp.array([1.0, 2.0]))
    K = jnp.array([[30.0, -10.0], [-10.0, 10.0]])
    C = 0.02 * K + 0.1 * M
    model = LatentForceModel(
        LinearSystem(ndof=2, force_dofs=(1,)),
        Matern(0),
        [Sensor("acceleration", 0, 0.1), Sensor("displacement", 1, 0.01)],
    )
    p = dict(M=M, C=C, K=K, force_variance=1.0, force_lengthscale=0.3)
    assert model.n_state == 5
    F, _ = model.continuous(p)
    np.testing.assert_allclose(np.asarray(F[2:4, 4]), [0.0, 0.5])  # force on DOF 1 through M^-1
    H, _ = model.observation(p)
    np.testing.assert_allclose(np.asarray(H[1]), [0, 1, 0, 0, 0])


def test_duffing_has_no_linear_form_but_a_linear_part():
    model = LatentForceModel(Duffing(), Matern(0), [Sensor("acceleration", 0, 0.1)])
    p = dict(m=1.0, c=20.0, k=1e4, k3=1e9, force_variance=20.0, force_lengthscale=0.1)
    with pytest.raises(TypeError):
        model.continuous(p)
    F, _ = model.continuous(p, linear_part=True)
    assert float(F[1, 0]) == -1e4
    x = jnp.array([1e-3, 0.0, 0.0])
    assert np.isclose(float(model.drift(p, x)[1]), -(1e4 * 1e-3 + 1e9 * 1e-9))


@pytest.mark.parametrize("order", [2, 3])
def test_van_loan_of_a_forceful_smooth_kernel_is_finite_and_exact(order):
    """A Matérn-5/2 or 7/2 force of variance 2500 N^2 and lengthscale 0.01 s at 750 Hz (the Bouc-Wen
    benchmark's scales): the driving noise's density is ~1e16, the Van Loan block's norm was 1.5e11,
    beyond the squarings expm allows, and Q was NaN until W was scaled to F's size (Q is linear in
    W). Against SciPy's expm of the same block in float64."""
    import scipy.linalg

    ss = Matern(order).state_space(KernelParams(jnp.asarray(2500.0), jnp.asarray(0.01)))
    W = np.asarray(ss.L @ ss.Qc @ ss.L.T)
    dt = 1.0 / 750.0
    A, Q = van_loan(ss.F, jnp.asarray(W), dt)
    n = W.shape[0]
    F = np.asarray(ss.F)
    E = scipy.linalg.expm(np.block([[F, W], [np.zeros_like(F), -F.T]]) * dt)
    Q_ref = E[:n, n:] @ E[:n, :n].T
    assert np.all(np.isfinite(np.asarray(Q)))
    np.testing.assert_allclose(np.asarray(Q), 0.5 * (Q_ref + Q_ref.T), rtol=1e-6, atol=1e-9 * np.max(np.abs(Q_ref)))


def _augmented_sdof(order: int, lengthscale: float):
    """An SDOF (m 1, c 0.4, k 12) driven by a Matérn force of variance 1: the model's ``(F, W)``."""
    model = LatentForceModel(LinearSystem(), Matern(order), [Sensor("acceleration", 0, 0.05)])
    params = {"m": 1.0, "c": 0.4, "k": 12.0, "force_variance": 1.0, "force_lengthscale": lengthscale}
    return model, params


@pytest.mark.parametrize("order", [0, 1, 2, 3])
@pytest.mark.parametrize("lam_dt", [0.05, 2.0, 20.0, 40.0])
def test_van_loan_of_the_augmented_model_for_any_step(order, lam_dt):
    """The augmented model's Q over a step from 1/20 of the force's time scale to 40 times it,
    against the stationary form P - A P A^T (Lyapunov and expm, no Van Loan; accurate for coarse
    steps; its Lyapunov solve loses digits beyond this range at the higher orders) and, for the
    finest, against SciPy's Van Loan block. Every entry compared on the scale
    of its row's and column's sds. Before the step was halved and doubled back, at |F| dt = 22 (a
    lengthscale of 4 ms at 20 Hz) Q's small entries were off by 1e-5 of the largest and the
    Kalman log-likelihood by 160 nats; at 44 every digit was gone."""
    import scipy.linalg

    dt = 0.05
    nu = order + 0.5
    lengthscale = np.sqrt(2 * nu) * dt / lam_dt
    model, params = _augmented_sdof(order, lengthscale)
    A, Q = model.discretise(params, dt)
    F, W = (np.asarray(M) for M in model.continuous(params))
    A_ref = scipy.linalg.expm(F * dt)
    if lam_dt < 1.0:
        n = F.shape[0]
        E = scipy.linalg.expm(np.block([[F, W], [np.zeros_like(F), -F.T]]) * dt)
        Q_ref = E[:n, n:] @ E[:n, :n].T
    else:
        P = scipy.linalg.solve_continuous_lyapunov(F, -W)
        Q_ref = P - A_ref @ P @ A_ref.T
    Q_ref = 0.5 * (Q_ref + Q_ref.T)
    sd = np.sqrt(np.diag(Q_ref))
    assert np.all(np.isfinite(np.asarray(Q)))
    np.testing.assert_allclose(np.asarray(Q) / np.outer(sd, sd), Q_ref / np.outer(sd, sd), atol=1e-6)
    np.testing.assert_allclose(np.asarray(A), A_ref, atol=1e-9 * max(1.0, np.abs(A_ref).max()))


def test_kalman_log_likelihood_with_a_lengthscale_far_below_the_step():
    """End to end: the Kalman log-likelihood of a record at 20 Hz with a Matérn-3/2 force of
    lengthscale 4 ms and 2 ms against a NumPy filter on the stationary-form discretisation."""
    import scipy.linalg

    from latentforce.inference.kalman import log_likelihood

    dt = 0.05
    rng = np.random.default_rng(0)
    y = rng.standard_normal((60, 1)) * 0.5
    for lengthscale in (0.004, 0.002):
        model, params = _augmented_sdof(1, lengthscale)
        F, W = (np.asarray(M) for M in model.continuous(params))
        P0 = scipy.linalg.solve_continuous_lyapunov(F, -W)
        A = scipy.linalg.expm(F * dt)
        Q = P0 - A @ P0 @ A.T
        H, R = (np.asarray(M) for M in model.observation(params))
        x, P, ll = np.zeros(F.shape[0]), P0.copy(), 0.0
        for t in range(len(y)):
            if t:
                x, P = A @ x, A @ P @ A.T + Q
            S = H @ P @ H.T + R
            v = y[t] - H @ x
            ll -= 0.5 * (v @ np.linalg.solve(S, v) + np.linalg.slogdet(2 * np.pi * S)[1])
            K = P @ H.T @ np.linalg.inv(S)
            x, P = x + K @ v, P - K @ S @ K.T
        A_, Q_ = model.discretise(params, dt)
        m0, P0_ = model.stationary_initial(params)
        got = float(log_likelihood(A_, Q_, jnp.asarray(H), jnp.asarray(R), m0, P0_, jnp.asarray(y)))
        assert np.isclose(got, ll, rtol=1e-8, atol=1e-6), (lengthscale, got, ll)
