r"""Sequential Monte Carlo for the latent force model: filter, conditional SMC, ancestor sampling.

The model (re-parametrised so that it has no degenerate transition)
-------------------------------------------------------------------
The augmented state is :math:`x_t = (\mathrm{mech}_t, x_{f,t})` with
:math:`\mathrm{mech} = (z, \dot z)` (``2 ndof``) and the force states
:math:`x_f` (``nforce * kernel.dim``). The mechanical states carry no process
noise in the model of Rogers et al. (Vibration 2020, Eq. 18-20), so the
transition density of :math:`x_t` is singular and the ancestor weights of
Eq. (22) degenerate. We therefore take as the Markov latent the force-state
process alone, an exact linear-Gaussian GP transition

.. math:: x_{f,1} \sim N(0, P_{\infty,f}), \qquad
          x_{f,t} = A_f x_{f,t-1} + q_t,\; q_t \sim N(0, Q_f),

plus the initial mechanical state :math:`\mathrm{mech}_1 \sim N(m_0, P_0)`;
the mechanical states are the deterministic function
:math:`\mathrm{mech}_t = \Phi(\mathrm{mech}_{t-1}, x_{f,t-1})` of that
latent (:class:`ParticleModel.phi`: one RK4 or Euler step of
:math:`M\ddot z + h(z,\dot z) = B u` with the force held as the Taylor
polynomial of the Matérn derivative states at :math:`t-1`; independent of
the GP hyperparameters). Every sensor is linear in :math:`x_{f,t}` given
:math:`\mathrm{mech}_t`:

.. math:: y_t = c(\mathrm{mech}_t) + D x_{f,t} + v_t,\qquad v_t \sim N(0, R).

The model is non-Markovian in :math:`x_f`; conditional SMC with ancestor
sampling for non-Markovian models is Lindsten, Jordan & Schön (2014, JMLR,
Sec. 4-5).

Proposals
---------
``"optimal"`` (default): given :math:`x_{t-1}`, :math:`\mathrm{mech}_t` is known,
so the locally optimal proposal is exact and Gaussian:
:math:`x_{f,t} \mid x_{t-1}, y_t \sim N(m + K(y_t - c - D m),\, Q_f - K S K^T)`
with :math:`m = A_f x_{f,t-1}`, :math:`S = D Q_f D^T + R`,
:math:`K = Q_f D^T S^{-1}`; the first-stage weight is
:math:`p(y_t \mid x_{t-1}) = N(y_t; c + D m, S)` (fully adapted auxiliary
filter, Pitt & Shephard 2001). ``K``, ``S`` and the proposal covariance do not
depend on the particle: they are computed once per sweep, so a particle
costs a mean shift. ``"bootstrap"``: :math:`x_{f,t} \sim N(A_f x_{f,t-1}, Q_f)`,
weight :math:`g(y_t \mid x_t)` (Algorithm 1, Vibration 2020).

Both are written as one auxiliary particle filter: at step ``t`` resample
with :math:`\log w_{t-1} + \psi_t` (``psi = log p(y_t | x_{t-1})`` for the
optimal proposal, 0 for the bootstrap), propose, and weight with the
second-stage weight (``log g`` for the bootstrap, 0 for the optimal proposal).
The marginal-likelihood estimate (Eq. 5, Vibration 2020) is
:math:`\log\hat Z = \sum_t [\operatorname{logsumexp}(\log \bar w_{t-1} + \psi_t)
+ \operatorname{logsumexp}(\log w^{(2)}_t) - \log N]`, unbiased for :math:`Z`.

Resampling at every step; the schemes share the signature
``(key, log_weights, n) -> indices``. Conditional SMC draws the ``N - 1``
non-reference ancestors i.i.d. multinomially: that *is* the conditional of
multinomial resampling given the reference's index; a plain systematic draw
of ``N - 1`` indices is not the conditional of systematic resampling
(Chopin & Singh 2015), so the conditional sweep always uses multinomial.

Ancestor sampling (Eq. 21, Vibration 2020, corrected)
-----------------------------------------------------
The reference at ``t`` takes ancestor ``a`` with

.. math:: P(a = i) \propto \bar w^i_{t-1}\, f_f(x'_{f,t} \mid x^i_{f,t-1})\, \exp\Delta^i_t,

where :math:`\bar w_{t-1}` are the filter's normalised weights targeting
:math:`p(x_{1:t-1}, y_{1:t-1})` (the published MATLAB omits them: an error)
and :math:`\Delta^i_t = \log p(y_{t:T} \mid \text{spliced}) - \log p(y_{t:T} \mid x')`
is the change of the future log-likelihood when the reference's future force
path is driven from particle ``i``'s state (the non-Markovian AS weight of
Lindsten et al. 2014, Eq. 29). With
:math:`\delta_t = \Phi(\mathrm{mech}^i_{t-1}, x^i_{f,t-1}) - \mathrm{mech}'_t`,
:math:`\delta_{s+1} = J_s \delta_s` and residual change :math:`C_s \delta_s`
(:math:`J_s = \partial\Phi/\partial\mathrm{mech}`,
:math:`C_s = \partial c/\partial \mathrm{mech}` at the reference),

.. math:: \Delta^i_t = -\tfrac12 \delta_t^T \Lambda_t \delta_t + \delta_t^T \eta_t,\quad
   \Lambda_s = C_s^T R^{-1} C_s + J_s^T \Lambda_{s+1} J_s,\quad
   \eta_s = C_s^T R^{-1} e_s + J_s^T \eta_{s+1},

:math:`e_s` the reference residuals, from one backward information recursion
per sweep (:func:`ancestor_information`). This is *exact* for linear systems
and a first-order (tangent-linear) approximation of the ancestor weights for
nonlinear ones; Lindsten et al. (2014, Sec. 5) discuss PGAS with truncated or
approximated ancestor weights (the kernel then still targets the right
posterior only approximately, with an error that vanishes with the
linearisation error). ``i``-independent terms cancel, so measuring
:math:`\delta` against the reference as it was at the start of the sweep is
fine even after the reference's ancestry has switched.
"""

from __future__ import annotations

import math
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.linalg import cho_factor, cho_solve, solve_triangular
from jaxtyping import Array, Bool, Float, Int

from latentforce.kernels import KernelParams, Matern
from latentforce.linalg import symmetrise

_LOG_2PI = math.log(2.0 * math.pi)

#: Jitter added to covariances before a Cholesky factorisation, relative to
#: their mean diagonal: keeps Q_f of smooth (high-order) Matérn kernels and
#: the proposal covariance Q_f - K S K^T (rank-deficient up to roundoff when a
#: sensor sees a force state almost noise-free) factorisable.
JITTER = 1e-10

DISCRETISATIONS = ("rk4", "euler")
PROPOSALS = ("optimal", "bootstrap")


# ---------------------------------------------------------------------------
# Resampling: (key, log_weights, n) -> indices
# ---------------------------------------------------------------------------
def _points(scheme: str, u: Float[Array, " n"]) -> Float[Array, " n"]:
    """Map ``n`` i.i.d. U(0,1) draws to the scheme's points in [0, 1)."""
    n = u.shape[-1]
    if scheme == "multinomial":
        return u
    if scheme == "stratified":
        return (jnp.arange(n) + u) / n
    if scheme == "systematic":
        return (jnp.arange(n) + u[..., :1]) / n
    raise ValueError(f"unknown resampling scheme {scheme!r}; valid: {RESAMPLING}")


def _inverse_cdf(log_weights: Float[Array, " N"], points: Float[Array, " n"]) -> Int[Array, " n"]:
    """Indices ``i`` with ``cdf[i-1] <= p < cdf[i]`` for the normalised weights."""
    w = jnp.exp(log_weights - jnp.max(log_weights))
    cdf = jnp.cumsum(w)
    # compare_all is the fastest search for the few dozen particles we use on CPU.
    idx = jnp.searchsorted(cdf, points * cdf[-1], side="right", method="compare_all")
    return jnp.minimum(idx, log_weights.shape[0] - 1).astype(jnp.int32)


def _resampler(scheme: str):
    def resample(key: Array, log_weights: Float[Array, " N"], n: int) -> Int[Array, " n"]:
        u = jax.random.uniform(key, (n,), dtype=log_weights.dtype)
        return _inverse_cdf(log_weights, _points(scheme, u))

    resample.__name__ = scheme
    resample.__doc__ = (
        f"{scheme.capitalize()} resampling: ``n`` ancestor indices drawn with probabilities "
        "proportional to ``exp(log_weights)`` (unnormalised log weights accepted)."
    )
    return resample


multinomial = _resampler("multinomial")
systematic = _resampler("systematic")
stratified = _resampler("stratified")
RESAMPLING = {"multinomial": multinomial, "systematic": systematic, "stratified": stratified}


def effective_sample_size(log_weights: Float[Array, " N"]) -> Float[Array, ""]:
    """ESS :math:`1 / \\sum_i \\bar w_i^2` of (unnormalised) log weights."""
    lw = log_weights - jax.scipy.special.logsumexp(log_weights)
    return jnp.exp(-jax.scipy.special.logsumexp(2.0 * lw))


# ---------------------------------------------------------------------------
# The model in the form the particle methods need
# ---------------------------------------------------------------------------
class ForceTransition(NamedTuple):
    """The force-state GP for all forces at one value of the hyperparameters."""

    A: Float[Array, "nf nf"]
    Q: Float[Array, "nf nf"]
    Pinf: Float[Array, "nf nf"]


class ParticleModel:
    r"""Static view of a :class:`~latentforce.models.LatentForceModel` for particle methods.

    Holds the model, the fixed system/sensor parameters ``params``, ``dt`` and
    the discretisation; everything that depends on the GP hyperparameters is
    computed by :meth:`force_transition` from a traced ``(variance, lengthscale)``.
    """

    def __init__(self, model, params: dict, dt: float, discretisation: str = "rk4"):
        if discretisation not in DISCRETISATIONS:
            raise ValueError(f"unknown discretisation {discretisation!r}; valid: {DISCRETISATIONS}")
        self.model = model
        self.params = {k: (jnp.asarray(v, dtype=float)) for k, v in params.items()}
        self.dt = float(dt)
        self.discretisation = discretisation
        self.nm = model.n_mech
        self.ndof = model.ndof
        self.nforce = model.nforce
        self.kdim = model.kernel.dim
        self.nfx = model.nforce * model.kernel.dim
        self.n_state = model.n_state
        self.n_obs = model.n_obs
        self.R = jnp.asarray(model.noise_covariance())
        if isinstance(model.kernel, Matern):
            # Taylor coefficients s^k / k! of the held force, over the derivative states.
            self._taylor = True
        else:  # composite kernels: zero-order hold of u = H_f x_f
            self._taylor = False
        self._Minv = jnp.linalg.inv(model.system.mass(self.params))
        self._B = model.system.input_matrix()
        zero_mech = jnp.zeros(self.nm)
        self.D = jax.jacfwd(lambda xf: self.model.observe(self._gp_dummy(), jnp.concatenate([zero_mech, xf])))(
            jnp.zeros(self.nfx))

    # ----- pieces of the model ---------------------------------------------
    def _hold(self, xf: Float[Array, " nf"], s) -> Float[Array, " nforce"]:
        """The force at time ``s`` into the step, held as a Taylor polynomial of ``x_f``."""
        if self._taylor:
            k = np.arange(self.kdim)
            coeff = jnp.asarray(s) ** k / np.array([math.factorial(int(i)) for i in k])
            return jnp.sum(jnp.reshape(xf, (self.nforce, self.kdim)) * coeff, axis=1)
        _, _, Hf, _ = self.model.force_state_space(self._gp_dummy())
        return Hf @ xf

    def _gp_dummy(self):
        return {**self.params, "force_variance": 1.0, "force_lengthscale": 1.0}

    def acceleration(self, z, v, u):
        r""":math:`\ddot z = M^{-1}(B u - h(z, \dot z))`, as ``system.acceleration`` but with
        :math:`M^{-1}` precomputed: a batched ``linalg.solve`` per particle and RK4
        stage dominated the sweep's cost on CPU."""
        rhs = _mv1(self._B, u) - self.model.system.restoring(self.params, z, v)
        return _mv1(self._Minv, rhs)

    def _rhs(self, mech, u):
        nd = self.ndof
        z, v = mech[:nd], mech[nd:]
        return jnp.concatenate([v, self.acceleration(z, v, u)])

    def phi(self, mech: Float[Array, " nm"], xf: Float[Array, " nf"]) -> Float[Array, " nm"]:
        r""":math:`\Phi(\mathrm{mech}_{t-1}, x_{f,t-1})`: one RK4 (or Euler) step of the mechanical ODE."""
        h = self.dt
        if self.discretisation == "euler":
            return mech + h * self._rhs(mech, self._hold(xf, 0.0))
        u0, u1, u2 = self._hold(xf, 0.0), self._hold(xf, 0.5 * h), self._hold(xf, h)
        k1 = self._rhs(mech, u0)
        k2 = self._rhs(mech + 0.5 * h * k1, u1)
        k3 = self._rhs(mech + 0.5 * h * k2, u1)
        k4 = self._rhs(mech + h * k3, u2)
        return mech + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)

    def phi_particles(self, mech: Float[Array, "N nm"], xf: Float[Array, "N nf"]) -> Float[Array, "N nm"]:
        """:meth:`phi` for a batch of particles, with displacement and velocity carried as
        separate arrays through the stages: XLA then fuses the whole step into one
        loop (stacking ``(z, v)`` at every stage made it materialise each stage)."""
        nd, h = self.ndof, self.dt
        acc = jax.vmap(self.acceleration)
        hold = jax.vmap(self._hold, (0, None))
        z, v = mech[:, :nd], mech[:, nd:]
        if self.discretisation == "euler":
            a = acc(z, v, hold(xf, 0.0))
            return jnp.concatenate([z + h * v, v + h * a], axis=1)
        u0, u1, u2 = hold(xf, 0.0), hold(xf, 0.5 * h), hold(xf, h)
        a1 = acc(z, v, u0)
        z2, v2 = z + 0.5 * h * v, v + 0.5 * h * a1
        a2 = acc(z2, v2, u1)
        z3, v3 = z + 0.5 * h * v2, v + 0.5 * h * a2
        a3 = acc(z3, v3, u1)
        z4, v4 = z + h * v3, v + h * a3
        a4 = acc(z4, v4, u2)
        return jnp.concatenate([z + (h / 6.0) * (v + 2.0 * v2 + 2.0 * v3 + v4),
                                v + (h / 6.0) * (a1 + 2.0 * a2 + 2.0 * a3 + a4)], axis=1)

    def _observe(self, mech, xf):
        r"""Noise-free observation ``c(mech) + D x_f``; equals ``model.observe`` (tested), written
        out with the precomputed :math:`M^{-1}` for speed."""
        nd = self.ndof
        z, v = mech[:nd], mech[nd:]
        return self.model.sensor_readout(z, v, lambda: self.acceleration(z, v, self._hold(xf, 0.0)))

    def offset(self, mech: Float[Array, " nm"]) -> Float[Array, " d"]:
        """:math:`c(\\mathrm{mech})`: the observation with the force states at zero."""
        return self._observe(mech, jnp.zeros(self.nfx))

    def force_transition(self, variance, lengthscale) -> ForceTransition:
        """``(A_f, Q_f, Pinf_f)`` for all forces (block diagonal), exact (Van Loan)."""
        kp = KernelParams(jnp.asarray(variance, dtype=float), jnp.asarray(lengthscale, dtype=float))
        A, Q = self.model.kernel.discretise(kp, self.dt)
        Pinf = self.model.kernel.state_space(kp).Pinf
        eye = jnp.eye(self.nforce)
        return ForceTransition(jnp.kron(eye, A), symmetrise(jnp.kron(eye, Q)), symmetrise(jnp.kron(eye, Pinf)))

    def initial_mech(self, initial=None):
        """``(mean, cov)`` of the initial mechanical state: ``initial = (mean, sd)`` or the model default."""
        if initial is not None:
            mean, sd = initial
            mean = jnp.broadcast_to(jnp.asarray(mean, dtype=float), (self.nm,))
            sd = jnp.broadcast_to(jnp.asarray(sd, dtype=float), (self.nm,))
            return mean, jnp.diag(sd**2)
        m0, P0 = self.model.default_initial({**self.params, "force_variance": 1.0, "force_lengthscale": 1.0})
        return m0[: self.nm], symmetrise(P0[: self.nm, : self.nm])

    def mech_path(self, mech1: Float[Array, " nm"], xf: Float[Array, "T nf"]) -> Float[Array, "T n"]:
        """The full state path ``(mech, x_f)`` driven deterministically by a force-state path."""

        def _step(mech, xf_prev):
            nxt = self.phi(mech, xf_prev)
            return nxt, nxt

        _, mechs = jax.lax.scan(_step, mech1, xf[:-1])
        return jnp.concatenate([jnp.concatenate([mech1[None], mechs]), xf], axis=1)

    def linear_discrete(self, ft: ForceTransition):
        """Jacobians of the full one-step map and the observation (exact for linear systems).

        Returns ``(A_d, Q_d, H)`` of ``x_t = A_d x_{t-1} + (0, q)``, ``y = H x + v``,
        for tests against the Kalman filter and for the extended Kalman smoother.
        """
        nm = self.nm

        def step(x):
            return jnp.concatenate([self.phi(x[:nm], x[nm:]), ft.A @ x[nm:]])

        x0 = jnp.zeros(self.n_state)
        A_d = jax.jacfwd(step)(x0)
        Q_d = jnp.zeros((self.n_state, self.n_state)).at[nm:, nm:].set(ft.Q)
        H = jax.jacfwd(lambda x: self._observe(x[:nm], x[nm:]))(x0)
        return A_d, Q_d, H


def _mv1(M, x):
    # M @ x as a broadcast-multiply-sum: for the tiny matrices here XLA fuses it
    # into the surrounding elementwise loop instead of emitting a dot call.
    return jnp.sum(M * x[None, :], axis=1)


def _mv(X: Float[Array, "N k"], M: Float[Array, "m k"]) -> Float[Array, "N m"]:
    """``X @ M.T`` as a fusible broadcast-multiply-sum (see :func:`_mv1`)."""
    return jnp.sum(X[:, None, :] * M[None, :, :], axis=-1)


def _quad(X: Float[Array, "N k"], M: Float[Array, "k k"]) -> Float[Array, " N"]:
    """Row-wise quadratic forms ``x_i^T M x_i``."""
    return jnp.sum(X[:, :, None] * M[None] * X[:, None, :], axis=(1, 2))


def _chol(P):
    n = P.shape[-1]
    scale = jnp.trace(P) / n
    return jnp.linalg.cholesky(symmetrise(P) + JITTER * scale * jnp.eye(n, dtype=P.dtype))


# ---------------------------------------------------------------------------
# Per-sweep precomputation
# ---------------------------------------------------------------------------
class SweepConstants(NamedTuple):
    """Everything a sweep needs that does not depend on the particles (one per theta)."""

    y: Float[Array, "T d"]  # zero where masked
    D: Float[Array, "T d nf"]  # masked rows zeroed
    Rinv: Float[Array, "T d d"]  # masked channels: zero rows/cols
    obs_const: Float[Array, " T"]  # -0.5 (log|R_t| + n_obs log 2 pi)
    A: Float[Array, "nf nf"]
    Q_inv: Float[Array, "nf nf"]
    L: Float[Array, "T nf nf"]  # proposal covariance Cholesky factor at each step
    K: Float[Array, "T nf d"]  # proposal gain (zero for the bootstrap)
    Sinv: Float[Array, "T d d"]  # first-stage innovation precision (optimal proposal)
    S_const: Float[Array, " T"]  # -0.5 (log|S_t| + n_obs log 2 pi)
    mech0_mean: Float[Array, " nm"]
    mech0_chol: Float[Array, "nm nm"]
    maskf: Float[Array, "T d"]


def _masked_R(R, maskf):
    R_t = R * jnp.outer(maskf, maskf) + jnp.diag(1.0 - maskf)
    return R_t


def sweep_constants(pm: ParticleModel, ft: ForceTransition, y, mask, mech0_mean, mech0_cov,
                    proposal: str = "optimal") -> SweepConstants:
    """Precompute masked observation matrices, ``K, S``, Cholesky factors (once per sweep/theta)."""
    if proposal not in PROPOSALS:
        raise ValueError(f"unknown proposal {proposal!r}; valid: {PROPOSALS}")
    mask = jnp.asarray(mask, dtype=bool)
    maskf = mask.astype(float)
    T = y.shape[0]
    yz = jnp.where(mask, jnp.nan_to_num(y), 0.0)
    D_t = pm.D[None] * maskf[:, :, None]
    R_t = jax.vmap(_masked_R, (None, 0))(pm.R, maskf)
    n_obs = jnp.sum(maskf, axis=1)

    def _inv_logdet(S, m):
        c = _chol(S)
        inv = cho_solve((c, True), jnp.eye(S.shape[0]))
        inv = symmetrise(inv) * jnp.outer(m, m)
        return inv, 2.0 * jnp.sum(jnp.log(jnp.diag(c)))

    Rinv, logdetR = jax.vmap(_inv_logdet)(R_t, maskf)
    obs_const = -0.5 * (logdetR + n_obs * _LOG_2PI)
    Qc = _chol(ft.Q)
    Q_inv = cho_solve((Qc, True), jnp.eye(ft.Q.shape[0]))
    # step 0 uses the stationary covariance, every later step Q_f
    prior_cov = jnp.concatenate([ft.Pinf[None], jnp.broadcast_to(ft.Q, (T - 1,) + ft.Q.shape)])
    if proposal == "optimal":
        def _gain(P, Dm, Rm, m):
            S = symmetrise(Dm @ P @ Dm.T + Rm)
            Sinv, logdetS = _inv_logdet(S, m)
            K = P @ Dm.T @ Sinv
            Sigma = symmetrise(P - K @ S @ K.T)
            return _chol(Sigma), K, Sinv, logdetS

        L, K, Sinv, logdetS = jax.vmap(_gain)(prior_cov, D_t, R_t, maskf)
        S_const = -0.5 * (logdetS + n_obs * _LOG_2PI)
    else:
        L = jax.vmap(_chol)(prior_cov)
        K = jnp.zeros((T, pm.nfx, pm.n_obs))
        Sinv, S_const = Rinv, obs_const
    return SweepConstants(yz, D_t, Rinv, obs_const, ft.A, symmetrise(Q_inv), L, K, Sinv, S_const,
                          jnp.asarray(mech0_mean, dtype=float), _chol(jnp.asarray(mech0_cov, dtype=float)),
                          maskf)


def ancestor_information(pm: ParticleModel, sc: SweepConstants, reference: Float[Array, "T n"]):
    r"""Backward information recursion :math:`(\Lambda_t, \eta_t)` along the reference (module doc).

    ``Lambda[t], eta[t]`` summarise :math:`\log p(y_{t:T})` as a quadratic in the
    mechanical-state perturbation :math:`\delta_t`; exact for linear systems,
    tangent-linear otherwise.
    """
    nm = pm.nm
    mech, xf = reference[:, :nm], reference[:, nm:]
    J = jax.vmap(jax.jacfwd(pm.phi, argnums=0))(mech[:-1], xf[:-1])  # (T-1, nm, nm)
    C = jax.vmap(jax.jacfwd(pm.offset))(mech) * sc.maskf[:, :, None]  # (T, d, nm)
    c = jax.vmap(pm.offset)(mech) * sc.maskf
    e = sc.y - c - jnp.einsum("tdf,tf->td", sc.D, xf)
    CtRinv = jnp.einsum("tdm,tde->tme", C, sc.Rinv)
    Lam_obs = jnp.einsum("tme,ten->tmn", CtRinv, C)
    eta_obs = jnp.einsum("tme,te->tm", CtRinv, e)

    def _step(carry, inputs):
        Lam_next, eta_next = carry
        J_s, Lo, eo = inputs
        Lam = symmetrise(Lo + J_s.T @ Lam_next @ J_s)
        eta = eo + J_s.T @ eta_next
        return (Lam, eta), (Lam, eta)

    last = (Lam_obs[-1], eta_obs[-1])
    _, (Lams, etas) = jax.lax.scan(_step, last, (J, Lam_obs[:-1], eta_obs[:-1]), reverse=True)
    return jnp.concatenate([Lams, Lam_obs[-1:]]), jnp.concatenate([etas, eta_obs[-1:]])


# ---------------------------------------------------------------------------
# The sweep: bootstrap/optimal particle filter, CSMC, CSMC with AS
# ---------------------------------------------------------------------------
class SweepInfo(NamedTuple):
    """Per-sweep diagnostics."""

    log_likelihood: Float[Array, ""]  # log of the unbiased estimate of p(y_{1:T}), Eq. (5)
    ess: Float[Array, " T"]  # ESS / N of the resampling weights at each step
    switched: Float[Array, ""]  # fraction of steps where AS picked a != reference
    final_index: Int[Array, ""]


class SweepOutput(NamedTuple):
    trajectory: Float[Array, "T n"]
    info: SweepInfo
    particles: Float[Array, "T N n"]
    ancestors: Int[Array, "T N"]
    log_weights: Float[Array, " N"]  # normalised, at the final step


def make_sweep(pm: ParticleModel, n_particles: int, *, proposal: str = "optimal",
               resampling: str = "multinomial", conditional: bool = True,
               ancestor_sampling: bool = True, unroll: int = 1) -> Callable:
    r"""Build ``sweep(key, sc, reference) -> SweepOutput``: one pass of SMC (pure, jittable).

    ``conditional=False``: the particle filter of Algorithm 1 (``reference``
    ignored). ``conditional=True, ancestor_sampling=False``: CSMC, Algorithm 3.
    ``conditional=True, ancestor_sampling=True``: the PGAS kernel, Algorithm 4,
    with the non-Markovian ancestor weights of the module docstring.
    The returned trajectory is drawn with probability proportional to the
    final weights and traced back through the stored ancestors.

    The sequential loop is written for XLA on CPU, where a step costs about
    one fused kernel per reduction: the resampling and ancestor-sampling
    draws share one max, one cumulative sum (a product with a constant
    triangle, cheaper than ``cumsum`` for a few dozen particles) and one
    count of CDF values below each point (inverse CDF); the reference's own
    resampling uniform drives its ancestor draw; the normalisers, ESS and the
    likelihood estimate are formed from the stored weights after the loop.
    """
    if proposal not in PROPOSALS:
        raise ValueError(f"unknown proposal {proposal!r}; valid: {PROPOSALS}")
    if resampling not in RESAMPLING:
        raise ValueError(f"unknown resampling scheme {resampling!r}; valid: {tuple(RESAMPLING)}")
    if conditional:
        # the valid conditional resampler for the N-1 free ancestors (module doc)
        resampling = "multinomial"
    N, nm, nfx = n_particles, pm.nm, pm.nfx
    ref = N - 1
    optimal = proposal == "optimal"
    with_as = conditional and ancestor_sampling
    voffset = jax.vmap(pm.offset)
    log_N = math.log(N)
    lse = jax.scipy.special.logsumexp
    # upper[i, j] = 1 for i <= j: w @ upper is the cumulative sum of w
    upper = np.triu(np.ones((N, N)))
    is_ref = np.arange(N) == ref

    def _obs_loglik(r, Rinv, const):  # r: (N, d)
        return -0.5 * _quad(r, Rinv) + const

    def _draw(log_weights: Float[Array, "k N"], points: Float[Array, " N"]) -> Int[Array, " N"]:
        """Inverse-CDF draws: point ``j`` searches row 1 of ``log_weights`` if ``j`` is the
        reference (its ancestor-sampling draw) and ``with_as``, else row 0."""
        w = jnp.exp(log_weights - jnp.max(log_weights, axis=1, keepdims=True))
        cdf = jnp.dot(w, jnp.asarray(upper, dtype=w.dtype))
        cdf_j = jnp.where(is_ref[:, None], cdf[-1][None, :], cdf[0][None, :]) if with_as else cdf[0][None, :]
        target = points[:, None] * cdf_j[:, -1:]
        idx = jnp.sum(cdf_j <= target, axis=1, dtype=jnp.int32)
        return jnp.minimum(idx, N - 1)

    def sweep(key: Array, sc: SweepConstants, reference: Float[Array, "T n"]) -> SweepOutput:
        T = sc.y.shape[0]
        dtype = sc.y.dtype
        k_init, k_step, k_fin = jax.random.split(key, 3)
        # a sweep's random numbers in two large draws (per step: N resampling points and
        # N x nfx proposal normals), the proposal noise formed outside the sequential loop.
        # (Normals by inversion of 32-bit uniforms, half the random bits, measured ~2 ms
        # per sweep slower than jax.random.normal at T=1024.)
        k1, k2 = jax.random.split(k_step)
        eps = jax.random.normal(k1, (T, N, nfx), dtype)
        u = jax.random.uniform(k2, (T, N, 1), dtype)
        noise = jnp.einsum("tnf,tgf->tng", eps, sc.L)
        points = _points(resampling, u[:, :, 0])
        z0 = jax.random.normal(k_init, (N, nm), dtype)
        u_fin = jax.random.uniform(k_fin, (), dtype)

        if with_as:
            Lam, eta = ancestor_information(pm, sc, reference)
        else:
            Lam = jnp.zeros((T, nm, nm))
            eta = jnp.zeros((T, nm))

        # ---- t = 0: mech from its prior, x_f from the (optimal) proposal
        mech = sc.mech0_mean + z0 @ sc.mech0_chol.T
        if conditional:
            mech = mech.at[ref].set(reference[0, :nm])
        c = voffset(mech) * sc.maskf[0]
        r = sc.y[0] - c  # prior force mean is zero
        xf = _mv(r, sc.K[0]) + noise[0]
        if conditional:
            xf = xf.at[ref].set(reference[0, nm:])
        if optimal:
            logw0 = _obs_loglik(r, sc.Sinv[0], sc.S_const[0])
        else:
            r2 = r - _mv(xf, sc.D[0])
            logw0 = _obs_loglik(r2, sc.Rinv[0], sc.obs_const[0])
        x0 = jnp.concatenate([mech, xf], axis=1)

        def _step(carry, inputs):
            # g_prev: the previous step's (unnormalised) second-stage log weights; for the
            # optimal proposal they are the t = 0 weights at t = 1 and zero after, so they
            # come in as an input rather than as a carry written every step
            y_t, D_t, Rinv_t, oc_t, K_t, Sinv_t, Sc_t, m_t, noise_t, p_t, Lam_t, eta_t, ref_t, g_in = inputs
            x_prev, g_prev = (carry, g_in) if optimal else carry
            mech_pred = pm.phi_particles(x_prev[:, :nm], x_prev[:, nm:])
            m = _mv(x_prev[:, nm:], sc.A)
            r = y_t - voffset(mech_pred) * m_t - _mv(m, D_t)
            if optimal:
                res_logw = g_prev + _obs_loglik(r, Sinv_t, Sc_t)
                # the particle's proposal mean, before resampling (it depends on the ancestor only)
                mean = m + _mv(r, K_t)
            else:
                res_logw = g_prev
                mean = m
            rows = [res_logw]
            if with_as:
                log_f = -0.5 * _quad(ref_t[nm:] - m, sc.Q_inv)
                delta = mech_pred - ref_t[:nm]
                Delta = -0.5 * _quad(delta, Lam_t) + jnp.sum(delta * eta_t, axis=1)
                rows.append(g_prev + log_f + Delta)
            # the barrier stops XLA from fusing (and so recomputing) the RK4 step and
            # the residuals into every consumer (reductions over particles, the gather)
            moved, log_weights = jax.lax.optimization_barrier(
                (jnp.concatenate([mech_pred, mean, r], axis=1), jnp.stack(rows)))
            anc = _draw(log_weights, p_t)
            if conditional and not ancestor_sampling:
                anc = jnp.where(is_ref, ref, anc)
            moved = moved[anc]
            xf_new = moved[:, nm:nm + nfx] + noise_t
            if conditional:
                xf_new = jnp.where(is_ref[:, None], ref_t[nm:], xf_new)
            x_new = jnp.concatenate([moved[:, :nm], xf_new], axis=1)
            if optimal:
                return x_new, (x_new, anc, res_logw)
            # y - c - D x_f = r - D (x_f - m), r and m those of the ancestor
            r2 = moved[:, nm + nfx:] - _mv(xf_new - moved[:, nm:nm + nfx], D_t)
            g = _obs_loglik(r2, Rinv_t, oc_t)
            return (x_new, g), (x_new, anc, res_logw, g)

        inputs = (sc.y[1:], sc.D[1:], sc.Rinv[1:], sc.obs_const[1:], sc.K[1:], sc.Sinv[1:],
                  sc.S_const[1:], sc.maskf[1:], noise[1:], points[1:], Lam[1:], eta[1:], reference[1:])
        if optimal:
            g_in = jnp.zeros((T - 1, N), dtype).at[0].set(logw0)
            _, (xs, ancs, res_logw) = jax.lax.scan(_step, x0, inputs + (g_in,), unroll=unroll)
            gs = jnp.zeros((T - 1, N), dtype)
            g_T = logw0 if T == 1 else gs[-1]
        else:
            (_, g_T), (xs, ancs, res_logw, gs) = jax.lax.scan(
                _step, (x0, logw0), inputs + (jnp.zeros((T - 1, 0), dtype),), unroll=unroll)
        particles = jnp.concatenate([x0[None], xs])
        ancestors = jnp.concatenate([jnp.broadcast_to(jnp.arange(N, dtype=ancs.dtype), (1, N)), ancs])
        # Eq. (5) with unnormalised second-stage weights g_t:
        # log Z = sum_t lse(g_t) - T log N + sum_{t>=1} [lse(g_{t-1} + psi_t) - lse(g_{t-1})]
        g_all = jnp.concatenate([logw0[None], gs])
        lse_g = lse(g_all, axis=1)
        log_z = jnp.sum(lse_g) - T * log_N + jnp.sum(lse(res_logw, axis=1) - lse_g[:-1])
        ess = jax.vmap(effective_sample_size)(res_logw) / N
        logw_T = g_T - lse(g_T)
        k = _inverse_cdf(logw_T, u_fin[None])[0]

        def _back(idx, a_t):
            return a_t[idx], idx

        _, path_idx = jax.lax.scan(_back, k, ancestors, reverse=True)
        path = particles[jnp.arange(T), path_idx]
        switched = jnp.mean((ancs[:, ref] != ref).astype(dtype)) if conditional else jnp.zeros((), dtype)
        info = SweepInfo(log_z, jnp.concatenate([jnp.ones(1, dtype), ess]), switched, k)
        return SweepOutput(path, info, particles, ancestors, logw_T)

    return sweep


def particle_filter(key: Array, pm: ParticleModel, ft: ForceTransition, y, mask, mech0_mean, mech0_cov,
                    n_particles: int, *, proposal: str = "optimal", resampling: str = "multinomial"):
    """Convenience wrapper: the (unconditional) particle filter; returns ``(log_likelihood, SweepOutput)``."""
    sc = sweep_constants(pm, ft, jnp.asarray(y, dtype=float), mask, mech0_mean, mech0_cov, proposal)
    sweep = make_sweep(pm, n_particles, proposal=proposal, resampling=resampling, conditional=False)
    out = sweep(key, sc, jnp.zeros((sc.y.shape[0], pm.n_state)))
    return out.info.log_likelihood, out
