r"""Gaussian filters and smoothers on the nonlinear model: ``ekf`` and ``ukf``.

The fast answers engineers know, beside the particle sampler: an extended and
an unscented Kalman filter with their Rauch-Tung-Striebel-type smoothers, on
the particle sampler's own discrete model of the state :math:`x = (\mathrm{mech},
x_f)` (:mod:`latentforce.inference.particle_model`; :meth:`~particle_model.ParticleModel.linear_discrete`),

.. math::
    x_t = f(x_{t-1}) + q_t,\quad q_t \sim N(0, Q), \qquad
    f(x) = \big(\Phi(\mathrm{mech}, x_f) + E x_f,\; A_f x_f\big),
    \qquad y_t = h(x_t) + v_t,\quad h(x) = c(\mathrm{mech}) + D x_f,

so that the three methods answer the same question. Each step predicts and
updates with a Gaussian approximation of the moments it needs:

* **EKF** (Särkkä 2013, Alg. 5.4 and 9.5): first-order Taylor expansions of
  :math:`f` and :math:`h` at the current mean (Jacobians by ``jax.jacfwd``);
* **UKF** (Särkkä 2013, Alg. 5.14 and 9.3): the unscented transform with
  :math:`\alpha = 1, \beta = 0, \kappa = 0`, i.e. the :math:`2n` points
  :math:`m \pm \sqrt{n}\, L e_i` of equal weight :math:`1/(2n)` (the
  spherical-radial cubature rule): every weight positive, so every
  covariance stays positive semi-definite, which the classical
  :math:`\kappa = 3 - n` does not guarantee for :math:`n > 3`.

Both reduce to the exact Kalman filter and RTS smoother for a linear system
(tested against :mod:`latentforce.inference.kalman` on the same discrete
model). The update is the joint one, :math:`S = \operatorname{Cov}[h] + R`,
:math:`K = C_{xy} S^{-1}`, on the channels observed at that step (a missing
channel has no row); the log-likelihood is the sum of the innovations'
Gaussian densities, the filters' usual approximation of :math:`\log p(y)`
(exact for linear systems). The smoother's gain is
:math:`G_t = C_{t,t+1} P^p_{t+1}{}^{-1}` with :math:`C_{t,t+1}` the
predicted cross-covariance of :math:`x_t` and :math:`x_{t+1}`, and a
trajectory can be drawn from the smoother's Gaussian (forward filtering,
backward sampling with the same gains).
"""

from __future__ import annotations

import math
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from latentforce.compile import Bound
from latentforce.inference import particle_model
from latentforce.linalg import cho_solve, cholesky, psd_sqrt, solve, symmetrise

_LOG_2PI = math.log(2.0 * math.pi)
METHODS = ("ekf", "ukf")


class GaussianSmoother(NamedTuple):
    """Smoothed moments of the state ``(mech, x_f)``, the approximate log-likelihood, a drawn path."""

    means: Float[Array, "T n"]
    covs: Float[Array, "T n n"]
    log_likelihood: Float[Array, ""]
    path: Float[Array, "T n"]  # zeros unless a key was given
    #: the first sample whose log-likelihood term is not finite (the filter overflowed there), -1 if none
    first_nonfinite: Int[Array, ""]
    #: the ``[[outputs]]``' means and variances by the method's transform of each time's smoothed
    #: Gaussian, and their values on the drawn path (zeros unless a key was given); ``(T, 0)`` without
    #: outputs (:func:`gaussian_smoother`'s ``out_fn``)
    output_means: Float[Array, "T k"]
    output_vars: Float[Array, "T k"]
    output_path: Float[Array, "T k"]
    #: each step's normalised innovation squared, :math:`v^T S^{-1} v` over the observed channels (a
    #: chi-squared with as many degrees of freedom where the filter's Gaussian is right; 0 where none is)
    nis: Float[Array, " T"]


def model_functions(pm: particle_model.ParticleModel, tr: particle_model.Transition):
    """``(f, h, Q, m_1, P_1)`` of the sampler's discrete model (module doc) at the transition ``tr``."""
    _, Q, _, m1, P1 = pm.linear_discrete(tr)

    def f(x):
        return pm.state_step(tr, x)

    h = pm.readout

    return f, h, Q, m1, P1


def _unit_diagonal(P):
    """``(d, P / d d^T)``: the standard deviations and the correlation matrix of ``P``. The
    variances here span ~15 orders (the force's highest derivative against the within-step
    displacement noise), so square roots and solves are taken on this scale: unscaled,
    ``linalg.psd_sqrt``'s threshold relative to the largest pivot dropped the displacement's
    spread altogether, and the UKF smoother diverged (force NMSE 1e24 on a Duffing case)."""
    d = jnp.sqrt(jnp.clip(jnp.diagonal(P), jnp.finfo(P.dtype).tiny, None))
    return d, P / jnp.outer(d, d)


def _root(P):
    """``L`` with ``L L^T = P`` (semi-definite ``P``), taken on the correlation scale."""
    d, corr = _unit_diagonal(symmetrise(P))
    return d[:, None] * psd_sqrt(corr)


def _sigma_points(m, P):
    """The :math:`2n` cubature points of :math:`N(m, P)` (module doc), rows."""
    n = m.shape[0]
    L = _root(P)
    offsets = math.sqrt(n) * jnp.concatenate([L.T, -L.T])
    return m[None, :] + offsets


def _moments(points, values):
    """Mean of ``values`` and (cross-)covariances over equally weighted points."""
    mx, mv = points.mean(0), values.mean(0)
    dx, dv = points - mx, values - mv
    k = points.shape[0]
    return mv, dv.T @ dv / k, dx.T @ dv / k


def _linearised(kind: str, fn: Callable, m, P):
    """``(mean of fn, Cov[fn], Cov[x, fn])`` under :math:`x \\sim N(m, P)`: Taylor (``ekf``) or
    unscented (``ukf``)."""
    if kind == "ekf":
        J = jax.jacfwd(fn)(m)
        PJ = P @ J.T
        return fn(m), J @ PJ, PJ
    X = _sigma_points(m, P)
    return _moments(X, jax.vmap(fn)(X))


def _update(m, P, y_hat, S_h, C, R, y, mask):
    """Joint Gaussian update on the observed channels; returns ``(m_f, P_f, log-likelihood term, normalised
    innovation squared)``."""
    mf = mask.astype(m.dtype)
    v = jnp.where(mask, y - y_hat, 0.0)
    # unit variance on the missing channels keeps S invertible; their rows and columns are cut
    S = symmetrise(S_h + R) * jnp.outer(mf, mf) + jnp.diag(1.0 - mf)
    L = cholesky(S)
    K = cho_solve(L, (C * mf[None, :]).T).T
    m_f = m + K @ v
    P_f = symmetrise(P - K @ S @ K.T)
    alpha = cho_solve(L, v)
    nis = v @ alpha
    ll = -0.5 * (nis + 2.0 * jnp.sum(jnp.log(jnp.diagonal(L))) + jnp.sum(mf) * _LOG_2PI)
    return m_f, P_f, ll, nis


def _smoother_gain(P_p, C):
    """:math:`G = C P_p^{-1}` (``C`` = Cov[x_t, x_{t+1}]), solved on the correlation scale of
    ``P_p`` (:func:`_unit_diagonal`) with a relative jitter of 1e-12."""
    d, corr = _unit_diagonal(P_p)
    corr = corr + 1e-12 * jnp.eye(P_p.shape[0])
    return (solve(corr, (C / d[None, :]).T) / d[:, None]).T


def _filter_pass(kind, f, h, Q, R, m1, P1, y, mask):
    """The forward pass: filtered and predicted moments, cross-covariances, log-likelihood terms and
    normalised innovations squared."""
    y = jnp.where(mask, y, 0.0)

    def _filter(carry, inputs):
        m_p, P_p = carry
        y_t, mask_t = inputs
        y_hat, S_h, C = _linearised(kind, h, m_p, P_p)
        m_f, P_f, ll, nis = _update(m_p, P_p, y_hat, S_h, C, R, y_t, mask_t)
        m_next, P_fx, C_next = _linearised(kind, f, m_f, P_f)
        P_next = symmetrise(P_fx + Q)
        return (m_next, P_next), (m_f, P_f, m_next, P_next, C_next, ll, nis)

    _, out = jax.lax.scan(_filter, (m1, P1), (y, mask))
    return out


def gaussian_log_likelihood(
    kind: str, pm: particle_model.ParticleModel, tr: particle_model.Transition, y, mask, R=None
) -> Float[Array, ""]:
    r"""The filter's approximate :math:`\log p(y)` alone (no smoothing pass)."""
    f, h, Q, m1, P1 = model_functions(pm, tr)
    R = pm.R if R is None else R
    lls = _filter_pass(kind, f, h, Q, R, m1, P1, jnp.asarray(y, dtype=float), jnp.asarray(mask, dtype=bool))[5]
    return jnp.sum(lls)


def for_parameters(kind: str, model, dt: float, discretisation: str = "rk4", initial=None, outputs=()):
    """``(loglik, smoother)``: ``loglik(params, y, mask)`` and ``smoother(params, y, mask, key=None)``
    of the ``kind`` filter with every number taken from ``params`` (jittable, differentiable: the
    samplers' model is built inside, :class:`particle_model.ParticleModel`); ``initial`` the mechanical
    states' ``(mean, sd|cov)`` as for ``pgas``; ``outputs`` the ``[[outputs]]``
    (:class:`latentforce.outputs.OutputSpec`), whose moments the smoother then returns too.

    Each is a :class:`latentforce.compile.Bound`: its numbers (``initial`` and the sensors' noise
    levels, :meth:`~latentforce.models.LatentForceModel.noise_params`, which ``params`` may
    override) are leaves, its structure (``kind``, the model, ``dt``, the discretisation) static,
    so a compiled program that takes it as an argument serves every model of one structure."""
    if kind not in METHODS:
        raise ValueError(f"unknown Gaussian smoother {kind!r}; valid: {METHODS}")
    if initial is not None:
        initial = tuple(jnp.asarray(a, dtype=float) for a in initial)
    static = (kind, model, float(dt), discretisation, tuple(outputs))
    numbers = (initial, {n: jnp.asarray(v, dtype=float) for n, v in model.noise_params().items()})
    return Bound(_loglik, static, numbers), Bound(_smoother, static, numbers)


def _build(static, numbers, params):
    """The samplers' model, the transition and the noise covariance at ``params`` (:func:`for_parameters`)."""
    _, model, dt, discretisation, _ = static
    initial, noise = numbers
    params = {**noise, **params}
    pm = particle_model.ParticleModel(model, params, dt, discretisation, initial)
    kp = model.kernel_params(params)
    tr = pm.transition(kp.variance, kp.lengthscale)
    return pm, tr, model.noise_covariance(params)


def _loglik(static, numbers, params, y, mask):
    pm, tr, R = _build(static, numbers, params)
    return gaussian_log_likelihood(static[0], pm, tr, y, mask, R)


def _smoother(static, numbers, params, y, mask, key=None):
    from latentforce.outputs import output_function

    pm, tr, R = _build(static, numbers, params)
    kind, model, _, _, outputs = static
    out_fn = output_function(model, outputs, {**numbers[1], **params}) if outputs else None
    return gaussian_smoother(kind, pm, tr, y, mask, R, key, out_fn)


def gaussian_smoother(
    kind: str,
    pm: particle_model.ParticleModel,
    tr: particle_model.Transition,
    y,
    mask,
    R=None,
    key=None,
    out_fn: Callable | None = None,
) -> GaussianSmoother:
    """The ``kind`` (``"ekf"`` or ``"ukf"``) filter and RTS-type smoother of the module doc.

    ``y`` ``(T, d)`` (anything where ``mask`` is False), ``mask`` ``(T, d)``;
    ``R`` the channels' noise covariance (default ``pm.R``). With ``key``,
    also one trajectory from the smoother's Gaussian. ``out_fn``: the outputs ``o(x)`` of one state
    (:func:`latentforce.outputs.output_function`), whose moments under each time's smoothed Gaussian
    are taken by the filter's own transform (Taylor or cubature, as for a sensor's readout).
    """
    if kind not in METHODS:
        raise ValueError(f"unknown Gaussian smoother {kind!r}; valid: {METHODS}")
    f, h, Q, m1, P1 = model_functions(pm, tr)
    R = pm.R if R is None else R
    y = jnp.asarray(y, dtype=float)
    mask = jnp.asarray(mask, dtype=bool)
    mf, Pf, mp, Pp, Cs, lls, nis = _filter_pass(kind, f, h, Q, R, m1, P1, y, mask)
    # gains G_t = C_{t,t+1} P_p(t+1)^{-1}, t < T-1, solved on the correlation scale: P_p's
    # variances span ~15 orders (the force's highest derivative against the within-step
    # displacement noise)
    Pp_n, C_n = Pp[:-1], Cs[:-1]
    G = jax.vmap(_smoother_gain)(Pp_n, C_n)

    def _smooth(carry, inputs):
        m_next, P_next = carry
        m_f, P_f, m_p, P_p, g = inputs
        m_s = m_f + g @ (m_next - m_p)
        P_s = symmetrise(P_f + g @ (P_next - P_p) @ g.T)
        return (m_s, P_s), (m_s, P_s)

    _, (ms, Ps) = jax.lax.scan(_smooth, (mf[-1], Pf[-1]), (mf[:-1], Pf[:-1], mp[:-1], Pp_n, G), reverse=True)
    means = jnp.concatenate([ms, mf[-1:]])
    covs = jnp.concatenate([Ps, Pf[-1:]])
    path = jnp.zeros_like(means)
    if key is not None:
        eps = jax.random.normal(key, means.shape, dtype=means.dtype)
        x_last = mf[-1] + _root(Pf[-1]) @ eps[-1]

        def _draw(x_next, inputs):
            m_f, P_f, m_p, P_p, g, e = inputs
            cov = symmetrise(P_f - g @ P_p @ g.T)
            x = m_f + g @ (x_next - m_p) + _root(cov) @ e
            return x, x

        _, xs = jax.lax.scan(_draw, x_last, (mf[:-1], Pf[:-1], mp[:-1], Pp_n, G, eps[:-1]), reverse=True)
        path = jnp.concatenate([xs, x_last[None]])
    bad = ~jnp.isfinite(lls)
    first_nonfinite = jnp.where(jnp.any(bad), jnp.argmax(bad), -1)
    if out_fn is None:
        o_mean = o_var = o_path = jnp.zeros((means.shape[0], 0), dtype=means.dtype)
    else:
        o_mean, o_cov, _ = jax.vmap(lambda m, P: _linearised(kind, out_fn, m, P))(means, covs)
        o_var = jnp.clip(jnp.diagonal(o_cov, axis1=-2, axis2=-1), 0.0, None)
        o_path = jax.vmap(out_fn)(path) if key is not None else jnp.zeros_like(o_mean)
    return GaussianSmoother(means, covs, jnp.sum(lls), path, first_nonfinite, o_mean, o_var, o_path, nis)
