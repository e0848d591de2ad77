r"""Blocked particle Gibbs for joint input-state-hyperparameter estimation (Algorithm 5, Vibration 2020).

Each Gibbs block is one PGAS sweep (:mod:`latentforce.inference.smc`) for the
trajectory :math:`x_{1:T}` given :math:`\theta`, then ``state_every``
iterations of Metropolis-within-Gibbs for the GP hyperparameters
:math:`\theta \subseteq \{\sigma_f^2, \ell\}` given the trajectory
(Eq. 23-25), each of ``mh_steps`` random-walk steps. Because the mechanical
map :math:`\Phi` does not depend on :math:`\theta`, the observation terms of
Eq. (25) cancel and the MH target is the density of the latent path
:math:`g = (x_f, w)` (force states and within-step mechanical noise,
:mod:`smc`) times the prior.

**Low-frequency trajectory move.** With acceleration-only data the weakly
observed direction of the path is a slow, coherent shift of force and
displacement (:math:`\delta u \approx k\,\delta z` leaves the acceleration
unchanged). The ancestor-sampling splice keeps the reference's future latent
and changes only the mechanical state, so the sweep alone cannot move that
component and chains stay where they start. After each sweep
``lowfreq_steps`` Metropolis steps (:func:`lowfreq_move`) therefore move, at
fixed :math:`\theta`, the ``lowfreq_modes`` lowest DCT-II modes (and the
first innovation) of every column of the latent's whitened innovations (the
non-centred coordinates, prior :math:`N(0, I)`), the path being rebuilt by
``colour`` and :meth:`~smc.ParticleModel.path`; the proposal's shape is a
Gauss-Newton posterior covariance at the initial path (for nonlinear
systems recomputed at each chain's path at 5, 10, 20, 40, 70 % of the burn-in)
and its scale adapts in burn-in.

**Residual-preserving trajectory move.** On a stiffening system the slow
direction is not a fixed combination of modes: the force follows a slow
displacement offset through the *tangent* stiffness
:math:`k + 3k_3 z(t)^2`, which varies fast, so holding the fast innovations
(the move above) pins it (Duffing, acceleration only: conditional sd of the
mean force a twentieth of the posterior's). After it, ``residual_steps``
Metropolis steps (:func:`residual_move`, :class:`ResidualMove`) move the
slow content of the mechanical within-step noise and rebuild the force
sample by sample so that the acceleration predictions, hence the residuals,
stay as they were; the map has a constant Jacobian, so the acceptance ratio
is exact for any system (prior ratio times the other channels' likelihood
ratio). Gauss-Newton shape, recomputed like the low-frequency move's;
scale adapted in burn-in.

**Sampling space.** The random walk runs in *log* space,
:math:`x = \log\theta` (this method's choice, overriding the softplus default
of INTERFACE.md; the priors stay on the physical values):

.. math:: \log \pi(x) = \sum_i \left[\log p(\theta_i) + x_i\right]
    + \log N(x_{f,1}; 0, P_{\infty,f}(\theta))
    + \sum_{t=2}^T \log N(x_{f,t}; A_f(\theta) x_{f,t-1}, Q_f(\theta)),

the :math:`x_i` being :math:`\log|d\theta_i/dx_i|`. Why: given a long path
the GP density pins the high-frequency scale of the force (for Matérn-1/2
the quadratic variation gives :math:`q = 2\sigma_f^2/\ell` to a relative
error of about :math:`\sqrt{2/T}`; for Matérn-:math:`\nu`,
:math:`\sigma_f^2/\ell^{2\nu}`) while the direction along that ridge is
only weakly identified. In log space the ridge is a straight line, so a
random walk with a full (adapted) covariance follows it; in softplus space
it is curved, and with :math:`\sigma_f^2 \gg 1` softplus is the identity, a
poor scale for a positive scale parameter.

**Adaptation** (burn-in only, so the post-burn-in chain is a plain
Metropolis-within-Gibbs chain with a fixed proposal and is exact): the
kernel is :func:`latentforce.inference.mcmc.step` (Haario, Saksman &
Tamminen 2001 covariance, Robbins-Monro scale towards
:func:`~latentforce.inference.mcmc.target_acceptance`). The proposal shape is
reset from the chain's covariance at the end of doubling windows of the
burn-in (at 5, 10, 20, 40 and 70 % of its MH steps), the running moments
being restarted after each reset so that the transient from the dispersed
start does not stretch the later proposals.

**Priors.** Along that ridge the path density tends to a constant once
:math:`\ell` exceeds the record length (a long-lengthscale Matérn-1/2 path
is Brownian motion over the record), so the ridge's tail is held only by
the prior: a flat prior on :math:`\sigma_f^2` contributes a factor
:math:`\sigma_f^2 \propto \ell` in log space and puts the posterior at
lengthscales far beyond the record (Duffing case, 0.5 s record: posterior
median :math:`\ell` of several seconds). Use a proper prior on
:math:`\sigma_f^2` or :math:`\ell` when the record spans few lengthscales.

One Gibbs block of one chain is :func:`make_block` (a pure function of the chain
state, the block index and the data); :func:`run_pgas` initialises the chains,
``jax.vmap``-s the block over them and runs the blocks in a ``lax.scan``; Python only
chunks the scan for progress reports. Initialisation never uses the truth:
an extended Kalman smoother at the initial :math:`\theta` gives a path that
fits the data; each chain starts from it moved by twice its Gauss-Newton
posterior sd in the low-frequency coordinates (:func:`dispersed_start`,
different per chain), and from :math:`\theta_0 \exp(0.5\,\varepsilon)` per
parameter.

Any key implementation works. The sweep draws its random numbers in two
large batches of 32-bit words before its sequential loop
(:func:`smc.box_muller`, :func:`smc.uniform32`); with jaxlib 0.10 on a
2-core CPU a sweep timed the same with ``threefry2x32``, ``rbg`` and
``unsafe_rbg`` keys (about 10 ns a word for each generator). Under ``vmap``
JAX draws the bits of ``rbg`` keys from the first key of the batch only
(each chain gets its own slice of that one stream, so the chains stay
independent, but a chain's draws then depend on the first chain's key).
"""

from __future__ import annotations

import math
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from latentforce.compile import shared_jit
from latentforce.inference import mcmc, smc
from latentforce.inference.kalman import _update
from latentforce.linalg import cho_solve, cholesky, solve, solve_lower, symmetrise

HYPERPARAMETERS = ("force_variance", "force_lengthscale")
_LOG_2PI = math.log(2.0 * math.pi)
# fractions of the burn-in MH steps after which the proposal shape is re-estimated
_RESHAPE_AT = (0.05, 0.1, 0.2, 0.4, 0.7)


# ---------------------------------------------------------------------------
# Hyperparameter step (Eq. 23-25)
# ---------------------------------------------------------------------------
def gp_path_log_density(pm: smc.ParticleModel, variance, lengthscale,
                        g: Float[Array, "T nl"]) -> Float[Array, ""]:
    r""":math:`\log p(g_{1:T} \mid \theta)` of the latent path (force states and within-step
    mechanical noise, :mod:`smc`), vectorised over time (no scan)."""
    return latent_log_density(pm.transition(variance, lengthscale), g)


def latent_log_density(tr: smc.Transition, g: Float[Array, "T nl"]) -> Float[Array, ""]:
    """:func:`gp_path_log_density` given the transition at :math:`\theta`."""
    T, nl = g.shape
    cP, cQ = smc._chol(tr.Pinf), smc._chol(tr.Q)
    eps = _whiten(tr, g, cP, cQ)
    logdetQ = 2.0 * jnp.sum(jnp.log(jnp.diag(cQ)))
    logdetP = 2.0 * jnp.sum(jnp.log(jnp.diag(cP)))
    return -0.5 * jnp.sum(eps**2) - 0.5 * ((T - 1) * logdetQ + logdetP) - 0.5 * T * nl * _LOG_2PI


class Hyper:
    """Which hyperparameters are free, their priors, and the fixed values of the others.

    The sampling coordinates are :math:`x = \\log\\theta` (module doc).
    """

    def __init__(self, params: dict, free: dict):
        bad = [n for n in free if n not in HYPERPARAMETERS]
        if bad:
            raise ValueError(f"PGAS samples only {HYPERPARAMETERS}; cannot sample {bad}")
        self.names = tuple(n for n in HYPERPARAMETERS if n in free)
        self.priors = tuple(free[n][0] for n in self.names)
        self.init = np.array([float(free[n][1]) for n in self.names], dtype=float)
        if not np.all(self.init > 0):
            raise ValueError(f"initial hyperparameters must be positive, got {dict(zip(self.names, self.init))}")
        self.fixed = {n: float(params[n]) for n in HYPERPARAMETERS}

    @staticmethod
    def to_unconstrained(theta: Float[Array, " p"]) -> Float[Array, " p"]:
        r""":math:`x = \log\theta` (the sampling coordinates)."""
        return jnp.log(jnp.asarray(theta, dtype=float))

    @staticmethod
    def to_constrained(x: Float[Array, " p"]) -> Float[Array, " p"]:
        r""":math:`\theta = e^x`."""
        return jnp.exp(jnp.asarray(x, dtype=float))

    def values(self, x: Float[Array, " p"]):
        """``(variance, lengthscale)`` from the unconstrained vector ``x``."""
        vals = dict(self.fixed)
        theta = self.to_constrained(x)
        for i, n in enumerate(self.names):
            vals[n] = theta[i]
        return jnp.asarray(vals["force_variance"], dtype=float), jnp.asarray(vals["force_lengthscale"], dtype=float)

    def log_prior(self, x: Float[Array, " p"]) -> Float[Array, ""]:
        r""":math:`\sum_i \log p(\theta_i) + x_i`: the prior density of :math:`x = \log\theta`."""
        theta = self.to_constrained(x)
        lp = jnp.zeros(())
        for i, prior in enumerate(self.priors):
            lp = lp + prior.log_prob(theta[i]) + x[i]
        return lp

    def log_target(self, pm, x: Float[Array, " p"], g: Float[Array, "T nl"]) -> Float[Array, ""]:
        """Centred MH target in log space: prior + log-Jacobian + latent path density (module doc)."""
        return self.log_target_and_transition(pm, x, g)[0]

    def log_target_and_transition(self, pm, x: Float[Array, " p"], g: Float[Array, "T nl"]
                                  ) -> tuple[Float[Array, ""], smc.Transition]:
        """:meth:`log_target` and the latent's transition at ``x`` (which the sampler carries)."""
        tr = pm.transition(*self.values(x))
        return self.log_target_given(tr, x, g), tr

    def log_target_given(self, tr: smc.Transition, x: Float[Array, " p"], g: Float[Array, "T nl"]
                         ) -> Float[Array, ""]:
        """:meth:`log_target` when ``tr``, the transition at ``x``, is already known."""
        return self.log_prior(x) + latent_log_density(tr, g)


def init_proposal(hyper: Hyper, log_target: Callable, x: Float[Array, " p"],
                  proposal_sd: float = 0.05) -> mcmc.RWMState:
    """Start the hyperparameter random walk at ``x`` with a diagonal proposal (log space)."""
    return mcmc.init(x, log_target, jnp.full(x.shape, proposal_sd))


def adaptation_schedule(burn_in_steps: int) -> tuple[int, ...]:
    """MH step numbers (0-based, burn-in) after which the proposal shape is reset (module doc)."""
    out = sorted({int(math.ceil(f * burn_in_steps)) - 1 for f in _RESHAPE_AT})
    return tuple(s for s in out if s >= 9)  # at least ten steps in the first window


def mh_step(key: Array, state: mcmc.RWMState, log_target: Callable, *, adapt: Array,
            reshape: Array, target: float, aux=None):
    """One random-walk MH step on the hyperparameters (``mcmc.step``), adaptive only where ``adapt``.

    ``state.logdensity`` must be ``log_target(state.x)`` (refresh it when the
    conditioning path changes). ``reshape``: reset the proposal shape from
    the running covariance, then restart the running moments. A non-finite
    proposed target is a rejection (never a propagated NaN). With ``aux``,
    as :func:`mcmc.step` (the target returns ``(log density, aux)``).
    """
    out = mcmc.step(key, state, log_target, adapt, reshape & adapt, target, aux)
    restart = reshape & adapt
    state = out[0]._replace(mean=jnp.where(restart, out[0].x, out[0].mean),
                            count=jnp.where(restart, 0.0, out[0].count))
    return (state,) + tuple(out[1:])


def proposal_covariance(state: mcmc.RWMState) -> Float[Array, "p p"]:
    """The (frozen after burn-in) random-walk covariance :math:`s^2 L L^\\top` in log space."""
    return jnp.exp(2.0 * state.log_scale) * state.chol @ state.chol.T


# ---------------------------------------------------------------------------
# Non-centred (interweaving) step: Yu & Meng (2011), ASIS
# ---------------------------------------------------------------------------
def whiten(tr: smc.Transition, g: Float[Array, "T nl"]) -> Float[Array, "T nl"]:
    r"""Innovations :math:`\varepsilon_1 = L_\infty^{-1} g_1`, :math:`\varepsilon_t = L_Q^{-1}(g_t - A g_{t-1})`."""
    return _whiten(tr, g, smc._chol(tr.Pinf), smc._chol(tr.Q))


def _whiten(tr: smc.Transition, g, cP, cQ):
    # one small triangular inverse applied as a matrix product: XLA's CPU triangular
    # solve with T right-hand sides cost ~1 ms at T = 1024, the product ~10 us
    e1 = solve_lower(cP, g[0])
    cQ_inv = solve_lower(cQ, jnp.eye(cQ.shape[0]))
    resid = g[1:] - g[:-1] @ tr.A.T
    return jnp.concatenate([e1[None], resid @ cQ_inv.T])


def colour(tr: smc.Transition, eps: Float[Array, "T nl"]) -> Float[Array, "T nl"]:
    """The latent path with innovations ``eps`` (inverse of :func:`whiten`)."""
    g1 = smc._chol(tr.Pinf) @ eps[0]
    noise = eps[1:] @ smc._chol(tr.Q).T

    def _step(g, q):
        nxt = tr.A @ g + q
        return nxt, nxt

    _, gs = jax.lax.scan(_step, g1, noise)
    return jnp.concatenate([g1[None], gs])


class ObservationDensity(NamedTuple):
    """Per-time masked Gaussian observation terms (independent of :math:`\\theta`)."""

    y: Float[Array, "T d"]  # zero where missing
    maskf: Float[Array, "T d"]
    Rinv: Float[Array, "T d d"]  # zero rows/columns where missing
    const: Float[Array, " T"]


def observation_density(pm: smc.ParticleModel, y, mask, R=None) -> ObservationDensity:
    """Precompute :math:`R_t^{-1}` and normalising constants of the observed channels (``R``
    default ``pm.R``)."""
    R = pm.R if R is None else R
    maskf = jnp.asarray(mask, dtype=float)
    yz = jnp.where(jnp.asarray(mask, dtype=bool), jnp.nan_to_num(jnp.asarray(y, dtype=float)), 0.0)

    def _one(m):
        # unit variance on the missing channels keeps R_t invertible; they are masked out below
        R_t = R * jnp.outer(m, m) + jnp.diag(1.0 - m)
        c = cholesky(symmetrise(R_t))
        inv = cho_solve(c, jnp.eye(R_t.shape[0])) * jnp.outer(m, m)
        return symmetrise(inv), -jnp.sum(jnp.log(jnp.diag(c))) - 0.5 * jnp.sum(m) * _LOG_2PI

    Rinv, const = jax.vmap(_one)(maskf)
    return ObservationDensity(yz, maskf, Rinv, const)


def predicted_observations(pm: smc.ParticleModel, path: Float[Array, "T n"]) -> Float[Array, "T d"]:
    r"""Noise-free observations :math:`c(\mathrm{mech}_t) + D x_{f,t}` of a path."""
    return jax.vmap(pm.offset)(path[:, :pm.nm]) + path[:, pm.nm:] @ pm.D.T


def observation_log_likelihood(pm: smc.ParticleModel, od: ObservationDensity,
                               path: Float[Array, "T n"]) -> Float[Array, ""]:
    r""":math:`\sum_t \log N(y_t; c(\mathrm{mech}_t) + D x_{f,t}, R)` over the observed channels."""
    r = (od.y - predicted_observations(pm, path)) * od.maskf
    return jnp.sum(od.const) - 0.5 * jnp.einsum("ti,tij,tj->", r, od.Rinv, r)


def noncentred_log_target(hyper: Hyper, pm: smc.ParticleModel, od: ObservationDensity,
                          x: Float[Array, " p"], eps: Float[Array, "T nl"]
                          ) -> tuple[Float[Array, ""], tuple[Float[Array, "T nl"], Float[Array, "T n"], smc.Transition]
                                     ]:
    r"""Target of :math:`x = \log\theta` given the latent's innovations; the rebuilt latent, path and transition.

    :math:`\log p(\theta) + \sum_i x_i + \log p(y \mid x_{1:T}(\theta, \varepsilon))`:
    the innovations' density does not depend on :math:`\theta` and, the
    innovations being held fixed, there is no path Jacobian. Returns
    ``(log target, (latent, path, transition at theta))``.
    """
    tr = pm.transition(*hyper.values(x))
    g = colour(tr, eps)
    path = pm.path(g)
    return hyper.log_prior(x) + observation_log_likelihood(pm, od, path), (g, path, tr)


# ---------------------------------------------------------------------------
# Low-frequency trajectory move in the non-centred coordinates
# ---------------------------------------------------------------------------
def lowfreq_basis(T: int, K: int) -> Float[Array, "T K1"]:
    r"""Orthonormal basis of the ``K`` lowest DCT-II vectors, :math:`\cos(\pi k (t + 1/2) / T)`, and of :math:`e_1`.

    :math:`e_1` (the first innovation, i.e. the initial force state) is
    added because the weakly observed start-up direction (initial force and
    displacement moving together, decaying over a lengthscale) is local to
    the start of the record and not spanned by a few global modes. ``K + 1``
    columns (``T`` when ``K >= T``).
    """
    K = min(int(K), int(T))
    t = np.arange(T)[:, None] + 0.5
    k = np.arange(K)[None, :]
    B = np.sqrt(2.0 / T) * np.cos(np.pi * k * t / T)
    B[:, 0] = 1.0 / np.sqrt(T)
    if K < T:
        e1 = np.zeros(T)
        e1[0] = 1.0
        e1 -= B @ (B.T @ e1)
        B = np.concatenate([B, (e1 / np.linalg.norm(e1))[:, None]], axis=1)
    return jnp.asarray(B)


class LowFrequencyFrame(NamedTuple):
    r"""What a low-frequency move holds fixed: :math:`\theta` (through ``tr``) and the basis.

    With :math:`\varepsilon` the latent's innovations (:func:`whiten`; the
    first row whitens the initial force and mechanical states), the path is
    coordinatised by :math:`W = B^\top \varepsilon` (``(K, nl)``: every
    latent column, the force states and the within-step mechanical noise)
    and :math:`\varepsilon_\perp = \varepsilon - B W`, held fixed. :math:`B`
    contains :math:`e_1`, so the initial state is moved too. The move samples
    :math:`w = \mathrm{vec}\,W`.
    """

    tr: smc.Transition
    basis: Float[Array, "T K"]


def lowfreq_coordinates(pm: smc.ParticleModel, frame: LowFrequencyFrame,
                        path: Float[Array, "T n"]) -> tuple[Float[Array, " q"], Float[Array, "T nl"]]:
    """``(w, eps_perp)`` of a path (inverse of :func:`lowfreq_path`)."""
    eps = whiten(frame.tr, pm.latent(path))
    W = frame.basis.T @ eps
    return W.ravel(), eps - frame.basis @ W


def lowfreq_path(pm: smc.ParticleModel, frame: LowFrequencyFrame, eps_perp: Float[Array, "T nl"],
                 w: Float[Array, " q"]) -> Float[Array, "T n"]:
    """The full path with low-frequency coordinates ``w`` (``colour`` then :meth:`~smc.ParticleModel.path`)."""
    W = jnp.reshape(w, (frame.basis.shape[1], pm.nl))
    return pm.path(colour(frame.tr, eps_perp + frame.basis @ W))


def lowfreq_log_target(pm: smc.ParticleModel, od: ObservationDensity, frame: LowFrequencyFrame,
                       eps_perp: Float[Array, "T nf"], w: Float[Array, " q"]
                       ) -> tuple[Float[Array, ""], Float[Array, "T n"]]:
    r""":math:`\log N(w; 0, I) + \log p(y \mid x_{1:T}(w, \varepsilon_\perp))` up to a constant, and the path.

    The maps :math:`w \mapsto (\mathrm{mech}_1, \varepsilon) \mapsto x_{1:T}`
    are affine with a constant Jacobian, and the prior of
    :math:`(\mathrm{mech}_1, \varepsilon)` is standard normal in these
    coordinates, so this is the conditional posterior of :math:`w` given
    :math:`\varepsilon_\perp` and :math:`\theta`.
    """
    path = lowfreq_path(pm, frame, eps_perp, w)
    return -0.5 * jnp.sum(w**2) + observation_log_likelihood(pm, od, path), path


def lowfreq_init(pm: smc.ParticleModel, od: ObservationDensity, frame: LowFrequencyFrame,
                 path: Float[Array, "T n"]) -> mcmc.RWMState:
    r"""Adaptation state of the low-frequency walk, its shape from a Gauss-Newton precision at ``path``.

    The proposal covariance starts at :math:`(2.38^2/q)\,(I + J^\top R^{-1} J)^{-1}`,
    :math:`J` the Jacobian of the predicted observations with respect to the
    :math:`q` coordinates :math:`w` (exact posterior covariance for a linear
    model). The observed directions are hundreds of times tighter than the
    prior-dominated slow one, and a walk that had to learn that shape from
    its own draws would spend the burn-in doing so.
    """
    w, eps_perp = lowfreq_coordinates(pm, frame, path)
    q = w.shape[0]

    def predicted(w_):
        x = lowfreq_path(pm, frame, eps_perp, w_)
        return (predicted_observations(pm, x) * od.maskf).ravel()

    J = jnp.reshape(jax.jacfwd(predicted)(w), (od.y.shape[0], od.y.shape[1], q))
    prec = symmetrise(jnp.eye(q) + jnp.einsum("tim,tij,tjn->mn", J, od.Rinv, J))
    cov = symmetrise(cho_solve(cholesky(prec), jnp.eye(q)))
    chol = cholesky(cov) * (2.38 / math.sqrt(q))
    return mcmc.RWMState(w, jnp.zeros(()), jnp.zeros(()), chol, w, cov, jnp.zeros(()))


def lowfreq_move(key: Array, rwm: mcmc.RWMState, pm: smc.ParticleModel, od: ObservationDensity,
                 frame: LowFrequencyFrame, path: Float[Array, "T n"], n_steps: int, *, adapt: Array,
                 step0: Array, reshape_steps: Array, target: float = 0.25
                 ) -> tuple[mcmc.RWMState, Float[Array, "T n"], Float[Array, " n_steps"]]:
    r"""``n_steps`` Metropolis steps on the path's low-frequency non-centred coordinates, :math:`\theta` fixed.

    The sweep's ancestor-sampling splice keeps the reference's future force
    and changes only the mechanical state; with acceleration-only data the
    weakly observed direction is a slow, coherent shift of force and
    displacement (:math:`\delta u \approx k\,\delta z` leaves the acceleration
    unchanged), which such splices cannot make. This move proposes
    :math:`w' = w + s L \xi` in the span of the ``K`` lowest DCT-II modes of
    the innovations of every force state and the whitened initial mechanical
    state, holding :math:`\varepsilon_\perp` fixed (:func:`lowfreq_log_target`).
    The proposal is symmetric; its shape :math:`L` (Haario et al. 2001) and
    scale :math:`s` (Robbins-Monro towards ``target``) adapt only where
    ``adapt``, so the frozen kernel is a plain Metropolis kernel that leaves
    the posterior invariant. ``step0``: index of the first step (for
    ``reshape_steps``). Returns the walk state, the new path (the input path
    bit-for-bit when nothing was accepted) and the acceptances.
    """
    w, eps_perp = lowfreq_coordinates(pm, frame, path)

    def log_target(w_):
        return lowfreq_log_target(pm, od, frame, eps_perp, w_)

    # the path is the one at w (up to round-off): no rebuild for the current point's target
    rwm = rwm._replace(x=w, logdensity=-0.5 * jnp.sum(w**2) + observation_log_likelihood(pm, od, path))

    return _walk(key, rwm, log_target, path, n_steps, adapt=adapt, step0=step0, reshape_steps=reshape_steps,
                 target=target)


# ---------------------------------------------------------------------------
# Residual-preserving trajectory move
# ---------------------------------------------------------------------------
class ResidualMove:
    r"""Static pieces of the residual-preserving move for one model and record length.

    **Why.** With acceleration-only data on a stiffening system the slow
    direction of the posterior is a slow displacement offset :math:`\delta z(t)`
    with the force following it, :math:`\delta u \approx k_t(t)\,\delta z`,
    where the tangent stiffness :math:`k_t = k + 3k_3 z(t)^2` varies *fast*
    along the path. The low-frequency move holds the fast content of the
    force's innovations fixed, so it cannot make that step (its conditional
    sd of the mean force is a twentieth of the posterior's on the Duffing
    case), and the sweep's splices cannot either.

    **The map.** Coordinates of the latent path :math:`(x_f, w)`: the within-step
    mechanical noise :math:`w_{1:T}` (``w_1`` the initial state's offset), the
    residuals :math:`\rho_t = y_t - c_S(\mathrm{mech}_t) - D_S x_{f,t}` of a set
    :math:`S` of ``nforce`` channels whose force block :math:`D_S` (on the force
    *value* states) is invertible, and the other force states (Matérn
    derivatives), which are held. Given :math:`w` the force values follow
    sample by sample, :math:`u_t = D_S^{-1}(y_{S,t} - \rho_t - c_S(\mathrm{mech}_t))`,
    and :math:`\mathrm{mech}_{t+1} = \Phi(\mathrm{mech}_t, x_{f,t}) + w_{t+1}`:
    a move in :math:`w` at fixed :math:`\rho` keeps the noise-free prediction
    :math:`c_S(\mathrm{mech}_t) + D_S x_{f,t}` of every sample, observed or
    missing, and only the other channels' residuals change. The map is
    triangular in time with the constant diagonal block :math:`-D_S`, so its
    Jacobian is constant.

    **The move.** A symmetric random walk on :math:`w` in the span of the ``K``
    lowest DCT-II modes of every mechanical component (from the second
    sample on, scaled by the within-step noise sd times :math:`\sqrt T`) and
    of the initial state (scaled by its prior sd), everything else in the
    coordinates above held. The Jacobian being constant, the acceptance ratio
    is the latent's prior density ratio times the likelihood ratio (1 on the
    channels of :math:`S`); no linearisation enters it, so the move leaves
    the exact posterior invariant for any system. The proposal's shape is a
    Gauss-Newton covariance at a path (exact for linear systems), its scale
    adapts in burn-in (:func:`residual_move`).

    ``applies`` is False (the move is skipped) when no set of ``nforce``
    channels sees the force values through an invertible block, e.g.
    displacement sensors only, or a kernel whose force is a combination of
    several states.
    """

    def __init__(self, pm: smc.ParticleModel, T: int, K: int, noise_sd: Float[Array, " nm"]):
        D = np.asarray(pm.D)
        self.cols = np.flatnonzero(np.any(D != 0.0, axis=0))
        self.applies = len(self.cols) == pm.nforce and pm.nforce > 0
        self.rows = np.zeros(0, dtype=int)
        if self.applies:
            import scipy.linalg

            # the best-conditioned nforce channels: QR with column pivoting of D_cols^T
            _, _, piv = scipy.linalg.qr(D[:, self.cols].T, pivoting=True)
            self.rows = np.sort(piv[: pm.nforce])
            self.applies = bool(np.linalg.cond(D[np.ix_(self.rows, self.cols)]) < 1e10)
        self.Dinv = jnp.asarray(np.linalg.inv(D[np.ix_(self.rows, self.cols)])) if self.applies else None
        self.K = min(int(K), int(T))
        self.basis = lowfreq_basis(T, self.K)[:, : self.K].at[0].set(0.0)  # w_1 moves on its own
        # noise_sd: the within-step noise sd at one fixed theta (the initial one in run_pgas),
        # so that a proposal shape computed at one theta stays meaningful at another
        self.scale_w = jnp.asarray(noise_sd) * math.sqrt(T)
        self.scale_0 = jnp.sqrt(jnp.diagonal(pm.mech0_cov))
        self.dim = (self.K + 1) * pm.nm

    def delta_w(self, c: Float[Array, " q"]) -> Float[Array, "T nm"]:
        """The change of the within-step noise for coordinates ``c``."""
        C = jnp.reshape(c, (self.K + 1, -1))
        return ((self.basis @ C[: self.K]) * self.scale_w).at[0].set(C[self.K] * self.scale_0)

    def builder(self, pm: smc.ParticleModel, od: ObservationDensity, path: Float[Array, "T n"]):
        """``c -> (latent, path)``: the path with noise ``w + delta_w(c)`` and the residuals of ``path`` kept."""
        nm = pm.nm
        rows, cols = self.rows, self.cols
        g0 = pm.latent(path)
        xf0, w0 = g0[:, : pm.nfx], g0[:, pm.nfx:]
        # y_S,t - rho_t is the path's own noise-free prediction on S: the map keeps it,
        # whether or not y_S,t was observed
        target = predicted_observations(pm, path)[:, rows]
        T = path.shape[0]
        # the solved-for states as a scatter matrix (no indexed updates inside the scan:
        # batched over chains they were slow on CPU)
        scatter = jnp.zeros((pm.nfx, len(cols))).at[cols, jnp.arange(len(cols))].set(1.0)
        keep = 1.0 - jnp.sum(scatter, axis=1)

        def _force(mech, target_t, xf0_t):
            # products as broadcast-multiply-sums: XLA fuses them (a dot per step,
            # batched over chains, cost ten times the whole step on CPU)
            u = smc._mv1(self.Dinv, target_t - pm.offset(mech)[rows])
            return xf0_t * keep + smc._mv1(scatter, u)

        def build(c):
            w = w0 + self.delta_w(c)
            mech1 = pm.mech0_mean + w[0]

            def _step(mech, inp):
                target_t, xf0_t, w_next = inp
                xf = _force(mech, target_t, xf0_t)
                # one stacked output: two (mech and xf), batched over chains, made XLA's
                # CPU loop several times slower
                return pm.phi(mech, xf) + w_next, jnp.concatenate([mech, xf])

            last, rows_ = jax.lax.scan(_step, mech1, (target[:-1], xf0[:-1], w[1:]))
            new_path = jnp.concatenate([rows_, jnp.concatenate([last, _force(last, target[-1], xf0[-1])])[None]])
            return jnp.concatenate([new_path[:, nm:], w], axis=1), new_path

        return build


def residual_log_target(tr: smc.Transition, pm: smc.ParticleModel, od: ObservationDensity, build,
                        c: Float[Array, " q"], cP=None, cQ=None) -> tuple[Float[Array, ""], Float[Array, "T n"]]:
    r"""Log target of the residual-preserving move up to a constant, and the path.

    :math:`-\tfrac12|\varepsilon(c)|^2 + \log p(y \mid x_{1:T}(c))`, :math:`\varepsilon`
    the latent's whitened innovations (its prior density up to a constant);
    the map's Jacobian is constant (:class:`ResidualMove`).
    """
    cP = smc._chol(tr.Pinf) if cP is None else cP
    cQ = smc._chol(tr.Q) if cQ is None else cQ
    g, path = build(c)
    return -0.5 * jnp.sum(_whiten(tr, g, cP, cQ) ** 2) + observation_log_likelihood(pm, od, path), path


def residual_init(rm: ResidualMove, pm: smc.ParticleModel, od: ObservationDensity, tr: smc.Transition,
                  path: Float[Array, "T n"]) -> mcmc.RWMState:
    r"""Adaptation state of the residual-preserving walk, its shape a Gauss-Newton covariance at ``path``.

    :math:`(2.38^2/q)(J_\varepsilon^\top J_\varepsilon + J_y^\top R^{-1} J_y)^{-1}`, the
    Jacobians of the whitened innovations and of the predicted observations
    with respect to the :math:`q` coordinates at ``path`` (the exact
    posterior covariance of the coordinates for a linear model).
    """
    build = rm.builder(pm, od, path)
    q = rm.dim
    cP, cQ = smc._chol(tr.Pinf), smc._chol(tr.Q)

    def features(c):
        g, x = build(c)
        return _whiten(tr, g, cP, cQ).ravel(), predicted_observations(pm, x) * od.maskf

    Je, Jy = jax.jacfwd(features)(jnp.zeros(q))
    prec = symmetrise(Je.T @ Je + jnp.einsum("tim,tij,tjn->mn", Jy, od.Rinv, Jy))
    cov = symmetrise(cho_solve(cholesky(prec), jnp.eye(q)))
    chol = cholesky(cov) * (2.38 / math.sqrt(q))
    return mcmc.RWMState(jnp.zeros(q), jnp.zeros(()), jnp.zeros(()), chol, jnp.zeros(q), cov, jnp.zeros(()))


def residual_move(key: Array, rwm: mcmc.RWMState, rm: ResidualMove, pm: smc.ParticleModel,
                  od: ObservationDensity, tr: smc.Transition, path: Float[Array, "T n"], n_steps: int, *,
                  adapt: Array, target: float = 0.25
                  ) -> tuple[mcmc.RWMState, Float[Array, "T n"], Float[Array, " n_steps"]]:
    r"""``n_steps`` residual-preserving Metropolis steps (:class:`ResidualMove`) at fixed :math:`\theta`.

    The coordinates are re-origined at ``path`` (``c = 0``); the proposal
    :math:`c' = c + s L \xi` keeps ``rwm``'s shape :math:`L`, and its scale
    :math:`s` follows Robbins-Monro towards ``target`` only where ``adapt``
    (the frozen kernel is a plain Metropolis kernel). Returns the walk state,
    the new path (the input path bit-for-bit when nothing was accepted) and
    the acceptances.
    """
    build = rm.builder(pm, od, path)
    cP, cQ = smc._chol(tr.Pinf), smc._chol(tr.Q)

    def log_target(c):
        return residual_log_target(tr, pm, od, build, c, cP, cQ)

    ld0 = -0.5 * jnp.sum(_whiten(tr, pm.latent(path), cP, cQ) ** 2) + observation_log_likelihood(pm, od, path)
    rwm = rwm._replace(x=jnp.zeros_like(rwm.x), logdensity=ld0)
    return _walk(key, rwm, log_target, path, n_steps, adapt=adapt, step0=jnp.zeros((), jnp.int32),
                 reshape_steps=jnp.asarray((-1,)), target=target)


def _walk(key, rwm: mcmc.RWMState, log_target: Callable, path, n_steps: int, *, adapt, step0, reshape_steps,
          target):
    """``n_steps`` of :func:`mh_step` whose target also returns the path (kept bit-for-bit on rejection)."""

    def _one(carry, inp):
        r, x = carry
        k, s = inp
        r, info, x = mh_step(k, r, log_target, adapt=adapt, reshape=jnp.any(step0 + s == reshape_steps),
                             target=target, aux=x)
        return (r, x), info.accepted

    (rwm, path), accs = jax.lax.scan(_one, (rwm, path), (jax.random.split(key, n_steps), jnp.arange(n_steps)))
    return rwm, path, accs


# ---------------------------------------------------------------------------
# Initialisation: extended Kalman smoother
# ---------------------------------------------------------------------------
def extended_kalman_smoother(pm: smc.ParticleModel, tr: smc.Transition, y, mask, R=None) -> Float[Array, "T n"]:
    r"""Smoothed means of the sampler's state-space model in ``(mech, x_f)``.

    The transition is :math:`x_t = (\Phi(\mathrm{mech}_{t-1}, x_{f,t-1}) + E x_{f,t-1},
    A_f x_{f,t-1}) + q_t` with the latent's joint noise :math:`q_t`
    (:meth:`~smc.ParticleModel.linear_discrete`). Extended Kalman filter
    (Jacobians by ``jax.jacfwd``) with the Kalman update of
    :mod:`latentforce.inference.kalman` applied to the linearised
    observation, then an RTS pass with the per-step Jacobians (Särkkä 2013,
    Alg. 9.5). Exact for linear systems. ``R``: the channels' noise covariance
    (default ``pm.R``).
    """
    nm, nfx, n = pm.nm, pm.nfx, pm.n_state
    R = pm.R if R is None else R
    y = jnp.asarray(y, dtype=float)
    mask = jnp.asarray(mask, dtype=bool)
    _, Qd, _, m0, P0 = pm.linear_discrete(tr)
    A_f, E = tr.A[:nfx, :nfx], tr.A[nfx:, :nfx]

    def f(x):
        return jnp.concatenate([pm.phi(x[:nm], x[nm:]) + E @ x[nm:], A_f @ x[nm:]])

    def h(x):
        return pm.offset(x[:nm]) + pm.D @ x[nm:]

    def _filter(carry, inputs):
        m, P = carry
        y_t, mask_t = inputs
        H = jax.jacfwd(h)(m)
        # the linear update with y shifted so that the innovation is y - h(m)
        y_lin = jnp.where(mask_t, y_t, 0.0) - h(m) + H @ m
        m_f, P_f, _ = _update(m, P, H, R, y_lin, mask_t)
        F = jax.jacfwd(f)(m_f)
        m_p = f(m_f)
        P_p = symmetrise(F @ P_f @ F.T + Qd)
        return (m_p, P_p), (m_f, P_f, m_p, P_p, F)

    _, (ms, Ps, mps, Pps, Fs) = jax.lax.scan(_filter, (m0, P0), (y, mask))

    def _smooth(carry, inputs):
        m_next, P_next = carry
        m_f, P_f, m_p, P_p, F = inputs
        G = solve(P_p + 1e-12 * jnp.diag(jnp.diagonal(P_p)), F @ P_f).T
        m_s = m_f + G @ (m_next - m_p)
        P_s = symmetrise(P_f + G @ (P_next - P_p) @ G.T)
        return (m_s, P_s), m_s

    _, msm = jax.lax.scan(_smooth, (ms[-1], Ps[-1]), (ms[:-1], Ps[:-1], mps[:-1], Pps[:-1], Fs[:-1]), reverse=True)
    return jnp.concatenate([msm, ms[-1:]])


def dispersed_start(key: Array, pm: smc.ParticleModel, frame: LowFrequencyFrame, rwm_lf: mcmc.RWMState,
                    path: Float[Array, "T n"], spread: float = 2.0) -> Float[Array, "T n"]:
    r"""A chain's starting path: ``path`` (the smoother's) moved by ``spread`` times its
    Gauss-Newton posterior sd in the low-frequency coordinates (``rwm_lf.cov``, :func:`lowfreq_init`).

    Over-dispersed exactly where the sampler is slow (the weakly observed, slow
    directions), while every acceleration sample stays fitted; the first sweep
    disperses the observed, fast content. Adding prior-scale noise to the whole
    latent path instead (the earlier start) leaves the mechanical path out of
    step with the force: on the Duffing case each acceleration sample was missed
    by about the force perturbation (log-likelihood near -1e6 against +2300 at
    the posterior), and the conditional SMC needed tens of sweeps to climb back,
    longer than a quick run's burn-in.
    """
    w, eps_perp = lowfreq_coordinates(pm, frame, path)
    step = spread * cholesky(rwm_lf.cov) @ jax.random.normal(key, w.shape)
    return lowfreq_path(pm, frame, eps_perp, w + step)


def gp_prior_path(key: Array, tr: smc.Transition, T: int) -> Float[Array, "T nl"]:
    """One draw of the latent path from its prior."""
    return colour(tr, jax.random.normal(key, (T, tr.A.shape[0])))


# ---------------------------------------------------------------------------
# The blocked Gibbs sampler
# ---------------------------------------------------------------------------
class ChainState(NamedTuple):
    """State of one chain between Gibbs blocks (a pytree; vmapped over chains)."""

    key: Array
    reference: Float[Array, "T n"]
    rwm: mcmc.RWMState  # hyperparameters x = log(theta) and their centred random walk's adaptation
    rwm_nc: mcmc.RWMState  # the non-centred (interweaving) random walk's adaptation; its x mirrors rwm.x
    rwm_lf: mcmc.RWMState  # the low-frequency trajectory move's adaptation (x: its last coordinates)
    rwm_rp: mcmc.RWMState  # the residual-preserving move's adaptation
    # the latent's transition at rwm.x, carried so that a compiled block evaluates the
    # transition at only two places (its matrix exponentials were 40 % of the program)
    tr: smc.Transition
    block: Array  # Gibbs block counter
    # running sums over post-burn-in state samples: (z, v, u) per time
    sum1: Float[Array, "T q"]
    sum2: Float[Array, "T q"]
    count: Float[Array, ""]
    draws: Float[Array, "S T n"]  # thinned trajectories (last slot is a discard slot)


class BlockInfo(NamedTuple):
    theta: Float[Array, "k p"]
    accept: Float[Array, " k"]
    accept_noncentred: Float[Array, " k"]
    accept_lowfreq: Float[Array, ""]
    accept_residual: Float[Array, ""]
    log_likelihood: Float[Array, ""]
    switch_rate: Float[Array, ""]
    ess: Float[Array, ""]
    force_points: Float[Array, "P nforce"]


class BlockData(NamedTuple):
    """The record and what is precomputed from it (arguments of the compiled programs)."""

    y: Float[Array, "T d"]
    mask: Array
    R: Float[Array, "d d"]  # the channels' noise covariance
    od: ObservationDensity
    ref_q: Float[Array, "T q"]  # centring of the running sums (the smoother's summary quantities)


class PGASOutput(NamedTuple):
    """What :func:`run_pgas` returns (NumPy arrays; ``chains`` leading)."""

    names: tuple  # free hyperparameter names
    theta: dict  # name -> (chains, iterations), post burn-in
    theta_burn: dict  # name -> (chains, burn_in)
    trajectories: np.ndarray  # (chains, draws, T, n_state), thinned, post burn-in
    state_mean: dict  # "displacement" | "velocity" | "force" -> (T, ndof|nforce), all post-burn-in sweeps
    state_sd: dict
    acceptance: np.ndarray  # (chains,), post burn-in MH acceptance rate
    switch_rate: np.ndarray  # (chains, sweeps) post burn-in AS switch fraction per sweep
    ess: np.ndarray  # (chains, sweeps) mean ESS/N of the filter per sweep
    log_likelihood: np.ndarray  # (chains, sweeps) PF estimate log p(y | theta) per sweep
    force_points: np.ndarray  # (chains, sweeps, P, nforce) force at `time_points`
    time_points: np.ndarray
    diagnostics: dict
    mh_scale: np.ndarray  # (chains, p) frozen random-walk proposal sd per parameter (log space)


def _summary_quantities(pm: smc.ParticleModel, path: Float[Array, "T n"]):
    nd = pm.ndof
    force_idx = pm.nm + pm.kdim * np.arange(pm.nforce)
    return jnp.concatenate([path[:, :2 * nd], path[:, force_idx]], axis=1)


class Schedule(NamedTuple):
    """Iteration bookkeeping of a Gibbs run (static integers; :func:`schedule`)."""

    state_every: int
    mh_steps: int
    burn_in: int  # iterations
    total: int  # iterations, burn-in included
    n_blocks: int  # Gibbs blocks, one sweep each
    burn_blocks: int  # blocks whose sweep is at an iteration < burn_in (they adapt)
    thin: int  # every thin-th post-burn-in path is stored
    n_draws: int  # stored paths


def schedule(burn_in: int, iterations: int, state_every: int = 1, mh_steps: int = 1,
             thin_draws: int = 200) -> Schedule:
    """The blocks of a run of ``burn_in + iterations`` iterations, a sweep on every ``state_every``-th."""
    k_every, n_mh = int(state_every), int(mh_steps)
    if n_mh < 1:
        raise ValueError(f"mh_steps must be at least 1, got {mh_steps}")
    if k_every < 1:
        raise ValueError(f"state_every must be at least 1, got {state_every}")
    total = int(burn_in) + int(iterations)
    n_blocks = -(-total // k_every)
    burn_blocks = -(-int(burn_in) // k_every)
    post_sweeps = n_blocks - burn_blocks
    thin = max(1, -(-post_sweeps // max(1, int(thin_draws))))
    n_draws = -(-post_sweeps // thin) if post_sweeps > 0 else 0
    return Schedule(k_every, n_mh, int(burn_in), total, n_blocks, burn_blocks, thin, n_draws)


def path_move_shapes(pm: smc.ParticleModel, rm: ResidualMove, basis, od: ObservationDensity,
                     tr: smc.Transition, path: Float[Array, "T n"], with_residual: bool
                     ) -> tuple[mcmc.RWMState, mcmc.RWMState]:
    """Fresh low-frequency and residual-preserving walks shaped at ``path`` (:func:`lowfreq_init`,
    :func:`residual_init`); without the residual move its walk is a copy of the other."""
    lf = lowfreq_init(pm, od, LowFrequencyFrame(tr, basis), path)
    return lf, (residual_init(rm, pm, od, tr, path) if with_residual else lf)


def reshape_chunks(n_blocks: int, burn_blocks: int, chunk_blocks: int, nonlinear: bool
                   ) -> tuple[int, list[tuple[int, int]], tuple[int, ...]]:
    """``(scan_len, segments, reshape_at)``: how :func:`run_pgas` runs its blocks.

    ``segments``: the ``(start, end)`` runs of blocks, each one call of one
    compiled program that scans ``scan_len >= end - start`` blocks and skips
    those at or past ``end``. ``reshape_at``: the blocks before which the path
    moves are re-shaped at each chain's path. For a linear model the
    Gauss-Newton shapes from the smoother are exact and nothing is re-shaped.
    For a nonlinear one the chain's path moves away from the smoother's, so the
    shapes are re-computed at fractions ``_RESHAPE_AT`` of the burn-in, by a
    program of their own shared with the start: inside the block (under a
    conditional) they added a quarter to its compile time. A scan of fixed
    length with skipped iterations, not one program per segment length: XLA
    unrolls short scans, and the block compiled twice as long at length 2.
    """
    chunk_blocks = max(1, int(chunk_blocks))
    scan_len = -(-n_blocks // max(1, -(-n_blocks // chunk_blocks)))
    at = () if not nonlinear else tuple(sorted(
        {int(math.ceil(f * burn_blocks)) - 1 for f in _RESHAPE_AT if 1 <= math.ceil(f * burn_blocks) - 1}))
    bounds = sorted(set(range(0, n_blocks, scan_len)) | {b for b in at if b < n_blocks} | {n_blocks})
    return scan_len, list(zip(bounds[:-1], bounds[1:])), at


def _with_scale_of(fresh: mcmc.RWMState, adapted: mcmc.RWMState) -> mcmc.RWMState:
    """``fresh``'s shape with ``adapted``'s scale and adaptation count (the re-shaping keeps the scale)."""
    return fresh._replace(log_scale=adapted.log_scale, count=adapted.count)


def make_block(pm: smc.ParticleModel, hyper: Hyper, sched: Schedule, rm: ResidualMove, basis, tpoints, *,
               particles: int = 50, proposal: str = "optimal", resampling: str = "multinomial",
               ancestor_sampling: bool = True, unroll: int = 1, interweave: bool = True,
               lowfreq_steps: int = 5, residual_steps: int = 60) -> Callable:
    r"""``block(state, b, data) -> (state, BlockInfo)``: Gibbs block ``b`` of one chain (pure, jittable).

    A PGAS sweep at the carried transition; ``lowfreq_steps`` low-frequency
    moves (``basis``: :func:`lowfreq_basis`) and ``residual_steps``
    residual-preserving moves (``rm``; skipped where it does not apply); the
    post-burn-in running sums and thinned draws; then ``state_every``
    Metropolis-within-Gibbs iterations of ``mh_steps`` centred and (with
    ``interweave``) non-centred steps on :math:`\theta`. Blocks
    ``b < sched.burn_blocks`` adapt the proposals' scales; later blocks are a
    fixed kernel. The path moves' shapes are the caller's (for nonlinear
    systems :func:`run_pgas` re-computes them between burn-in blocks with
    :func:`path_move_shapes`). ``b`` must be shared by vmapped chains (it drives conditionals);
    ``data`` (:class:`BlockData`) may be shared or batched. ``tpoints``: the
    time indices whose force values are recorded.

    The caller's :class:`ChainState` must hold ``tr``, the transition at
    ``rwm.x``, and ``draws`` with ``sched.n_draws + 1`` slots (the last is a
    discard slot); ``data.ref_q`` centres the running sums (``(T, q)``, see
    :func:`run_pgas`). The walks' ``logdensity`` fields are refreshed before
    use.
    """
    p = len(hyper.names)
    k_every, n_mh, burn_in = sched.state_every, sched.mh_steps, sched.burn_in
    n_blocks, burn_blocks, thin, n_draws = sched.n_blocks, sched.burn_blocks, sched.thin, sched.n_draws
    sweep = smc.make_sweep(pm, particles, proposal=proposal, resampling=resampling, conditional=True,
                           ancestor_sampling=ancestor_sampling, unroll=unroll)
    target_acc = mcmc.target_acceptance(max(p, 1))
    reshape_steps = jnp.asarray(adaptation_schedule(burn_in * n_mh) or (-1,))
    n_lf, n_rp = int(lowfreq_steps), int(residual_steps)
    if n_lf < 0:
        raise ValueError(f"lowfreq_steps must be non-negative, got {lowfreq_steps}")
    if n_rp < 0:
        raise ValueError(f"residual_steps must be non-negative, got {residual_steps}")
    n_rp = n_rp if rm.applies else 0

    lf_reshape = jnp.asarray((-1,))
    interweave = bool(interweave) and p > 0

    def _block(state: ChainState, b, data: BlockData):
        """One Gibbs block of one chain (:func:`make_block`)."""
        key, k_sweep, k_mh, k_lf, k_rp = jax.random.split(state.key, 5)
        tr = state.tr
        sc = smc.sweep_constants(pm, tr, data.y, data.mask, proposal, data.R)
        out = sweep(k_sweep, sc, state.reference)
        path = out.trajectory
        rwm_lf, acc_lf = state.rwm_lf, jnp.zeros(())
        if n_lf:
            frame = LowFrequencyFrame(tr, basis)
            rwm_lf, path, accs_lf = lowfreq_move(k_lf, rwm_lf, pm, data.od, frame, path, n_lf, adapt=b < burn_blocks,
                                                 step0=b * n_lf, reshape_steps=lf_reshape)
            acc_lf = jnp.mean(accs_lf.astype(float))
        rwm_rp, acc_rp = state.rwm_rp, jnp.zeros(())
        if n_rp:
            rwm_rp, path, accs_rp = residual_move(k_rp, rwm_rp, rm, pm, data.od, tr, path, n_rp, adapt=b < burn_blocks)
            acc_rp = jnp.mean(accs_rp.astype(float))
        # ---- accumulate post-burn-in state samples
        post = (b >= burn_blocks) & (b < n_blocks)
        wgt = post.astype(float)
        q = _summary_quantities(pm, path) - data.ref_q
        sum1 = state.sum1 + wgt * q
        sum2 = state.sum2 + wgt * q**2
        sidx = b - burn_blocks
        slot = jnp.where(post & (sidx % thin == 0), sidx // thin, n_draws)
        draws = state.draws.at[slot].set(path)
        # ---- state_every MH iterations given the path, each mh_steps steps
        def _steps(key_, r, target, j, aux=None):
            def _one(carry, inp2):
                r_, a_ = carry
                kk, s_ = inp2
                out_ = mh_step(kk, r_, target, adapt=j < burn_in,
                               reshape=jnp.any(j * n_mh + s_ == reshape_steps), target=target_acc, aux=a_)
                return (out_[0], out_[2] if aux is not None else None), out_[1].accepted

            (r, aux), accs_ = jax.lax.scan(_one, (r, aux), (jax.random.split(key_, n_mh), jnp.arange(n_mh)))
            return r, accs_, aux

        def _mh_iter(carry, inp):
            rwm, rwm_nc, path_, g_, tr_ = carry
            k_it, j = inp
            if not p:
                return carry, (rwm.x, jnp.zeros(()), jnp.zeros(()))
            k_c, k_nc = jax.random.split(k_it)

            def centred(x):
                return hyper.log_target_and_transition(pm, x, g_)

            # the conditioning path may have changed: refresh the current point's target
            rwm = rwm._replace(logdensity=hyper.log_target_given(tr_, rwm.x, g_))
            rwm, accs, tr_ = _steps(k_c, rwm, centred, j, aux=tr_)
            acc_nc = jnp.zeros(())
            if interweave:
                eps = whiten(tr_, g_)

                def noncentred(x):
                    return noncentred_log_target(hyper, pm, data.od, x, eps)

                # at the current point the rebuilt path is the current one (up to round-off);
                # the path is kept bit-for-bit when nothing moves (no round-off drift)
                rwm_nc = rwm_nc._replace(x=rwm.x, logdensity=hyper.log_prior(rwm.x)
                                         + observation_log_likelihood(pm, data.od, path_))
                rwm_nc, accs_nc, (g_, path_, tr_) = _steps(k_nc, rwm_nc, noncentred, j, aux=(g_, path_, tr_))
                rwm = rwm._replace(x=rwm_nc.x)
                acc_nc = jnp.mean(accs_nc.astype(float))
            return (rwm, rwm_nc, path_, g_, tr_), (rwm.x, jnp.mean(accs.astype(float)), acc_nc)

        js = b * k_every + jnp.arange(k_every)
        (rwm, rwm_nc, path_end, _, tr_end), (xs, accs, accs_nc) = jax.lax.scan(
            _mh_iter, (state.rwm, state.rwm_nc, path, pm.latent(path), tr), (jax.random.split(k_mh, k_every), js))
        theta = hyper.to_constrained(xs)
        fp = path[tpoints][:, pm.nm + pm.kdim * np.arange(pm.nforce)]
        new = ChainState(key, path_end, rwm, rwm_nc, rwm_lf, rwm_rp, tr_end, b + 1, sum1, sum2, state.count + wgt,
                         draws)
        info = BlockInfo(theta, accs, accs_nc, acc_lf, acc_rp, out.info.log_likelihood, out.info.switched,
                         jnp.mean(out.info.ess), fp)
        return new, info

    return _block


def observe_through(model, channels, y, mask):
    """``(model, y, mask)`` with the channels ``channels``, ``(quantity, dof)`` pairs, in that order.

    Each sensor moves to the channel of its quantity and DOF, with its noise;
    a channel no sensor reads gets a sensor of unit noise that is never
    observed (``y`` NaN, ``mask`` False there), which leaves the likelihood,
    hence the posterior, unchanged.
    """
    from latentforce.models import LatentForceModel, Sensor

    channels = [(str(q), int(d)) for q, d in channels]
    if len(set(channels)) != len(channels):
        raise ValueError(f"channels must be distinct, got {channels}")
    where = {c: i for i, c in enumerate(channels)}
    sensors = [Sensor(q, d, 1.0, f"unobserved {q} at DOF {d}") for q, d in channels]
    cols = []
    for s in model.sensors:
        i = where.get((s.quantity, s.dof))
        if i is None or i in cols:
            raise ValueError(f"channels {channels} have no channel of their own for the sensor {s}")
        cols.append(i)
        sensors[i] = s
    y, mask = np.asarray(y, dtype=float), np.asarray(mask, dtype=bool)
    if y.ndim != 2 or y.shape[1] != len(model.sensors) or mask.shape != y.shape:
        raise ValueError(f"y and mask must both be (T, {len(model.sensors)}), one column per sensor; "
                         f"got {y.shape} and {mask.shape}")
    y_all = np.full((y.shape[0], len(channels)), np.nan)
    mask_all = np.zeros(y_all.shape, dtype=bool)
    y_all[:, cols], mask_all[:, cols] = y, mask
    return LatentForceModel(model.system, model.kernel, sensors), y_all, mask_all


def run_pgas(key: Array, model, params: dict, free: dict, y, mask, dt: float, *,
             particles: int = 50, iterations: int = 1000, burn_in: int = 500, state_every: int = 1,
             chains: int = 4, mh_steps: int = 1, discretisation: str = "rk4", proposal: str = "optimal",
             resampling: str = "multinomial", thin_draws: int = 200, initial=None,
             progress: Callable | None = None, chunk_blocks: int = 1000, unroll: int = 1,
             time_points: int = 5, ancestor_sampling: bool = True, interweave: bool = True,
             lowfreq_modes: int = 16, lowfreq_steps: int = 5, residual_modes: int = 16,
             residual_steps: int = 60, channels=None) -> PGASOutput:
    r"""Blocked particle Gibbs (Algorithm 5, Vibration 2020) with the PGAS kernel of :mod:`smc`.

    ``params``: every model parameter (free hyperparameters too: their values
    are ignored except as fixed defaults). ``free``: ``name -> (prior, init)``
    for a subset of ``force_variance, force_lengthscale`` (may be empty: the
    trajectory is then sampled at fixed :math:`\theta`). ``y`` ``(T, d)`` may
    hold NaN where ``mask`` is False. ``iterations`` are kept after
    ``burn_in``; a PGAS sweep runs on iterations ``j % state_every == 0``,
    and every iteration makes ``mh_steps`` Metropolis steps on
    :math:`\theta` given the current path (the value recorded for the
    iteration is the last); with ``interweave`` each iteration then makes
    ``mh_steps`` non-centred steps (module doc). After each sweep,
    ``lowfreq_steps`` Metropolis steps (:func:`lowfreq_move`; 0 disables)
    move the path's ``lowfreq_modes`` slowest innovation modes and its
    initial mechanical state at fixed :math:`\theta`; the moved path is the
    next reference and the recorded sample. Then ``residual_steps``
    residual-preserving steps (:func:`residual_move`; 0 disables; skipped
    when no channel sees the force) move the ``residual_modes`` slowest
    modes of the mechanical within-step noise, the force following so that
    the acceleration predictions are kept. ``initial = (mean, sd)`` or ``(mean, cov)`` of
    the initial mechanical state, else the default of :class:`smc.ParticleModel`
    (linear systems: the joint stationary start at the current hyperparameters). ``progress(done,
    total, accept_rate)`` is called between scan chunks.

    ``channels``: ``(quantity, dof)`` pairs through which the compiled programs
    observe the system (default: the sensors'; :func:`observe_through`).
    Channels no sensor reads are never observed, so the posterior is the same
    (the draws too, unless an unobserved channel is the one that lets the
    residual-preserving move apply: an exact move either way, so still the same
    posterior); two runs whose models differ only in their sensors then compile the same
    programs, and run side by side in one process they compile them once
    (:func:`latentforce.compile.shared_jit`). The programs take the record and
    the noise covariance as arguments, never as constants.
    """
    if channels is not None:
        model, y, mask = observe_through(model, channels, y, mask)
    pm = smc.ParticleModel(model, params, dt, discretisation, initial)
    hyper = Hyper(params, free)
    y = jnp.asarray(y, dtype=float)
    mask = jnp.asarray(mask, dtype=bool) & jnp.isfinite(y)
    T = y.shape[0]
    p = len(hyper.names)
    sched = schedule(burn_in, iterations, state_every, mh_steps, thin_draws)
    tpoints = np.unique(np.linspace(0, T - 1, time_points).round().astype(int))
    nq = 2 * pm.ndof + pm.nforce
    basis = lowfreq_basis(T, lowfreq_modes)

    # ---- initialisation (outside the loop; never from the truth), in compiled programs:
    # run op by op it compiled some hundred tiny programs, most of a quick run's start-up
    x0 = hyper.to_unconstrained(hyper.init) if p else jnp.zeros(0)
    R = pm.R
    od = shared_jit(lambda y_, m_, R_: observation_density(pm, y_, m_, R_))(y, mask, R)
    k_theta, k_chains = jax.random.split(key)

    @shared_jit
    def _start_transitions(k):
        # the chains' dispersed starts theta_0 exp(0.5 eps), and the transitions at theta_0
        # and at those, from one place in the program (each place compiles its own matrix
        # exponentials: they dominated the compile time)
        xs = x0 + 0.5 * jax.random.normal(k, (chains, p))
        trs = jax.vmap(lambda x: pm.transition(*hyper.values(x)))(jnp.concatenate([x0[None], xs]))
        return xs, jax.tree_util.tree_map(lambda a: a[0], trs), jax.tree_util.tree_map(lambda a: a[1:], trs)

    xs0, tr0, trs0 = _start_transitions(k_theta)
    rm = ResidualMove(pm, T, residual_modes, np.sqrt(np.diagonal(np.asarray(tr0.Q))[pm.nfx:]))
    # (make_block checks the step counts)
    block = make_block(pm, hyper, sched, rm, basis, tpoints, particles=particles, proposal=proposal,
                       resampling=resampling, ancestor_sampling=ancestor_sampling, unroll=unroll,
                       interweave=interweave, lowfreq_steps=lowfreq_steps, residual_steps=residual_steps)
    with_rp = rm.applies and int(residual_steps) > 0

    @shared_jit
    def _smooth(y, mask, R, tr0):
        eks = extended_kalman_smoother(pm, tr0, y, mask, R)
        # ref_q: centring of the running sums (numerical stability)
        return eks, _summary_quantities(pm, eks)

    # One program shapes the path moves (Gauss-Newton, a Jacobian through the path
    # rebuild: a large program) at the smoother's path and, for nonlinear models, at
    # each chain's path between burn-in chunks; inside the block it compiled again.
    @shared_jit
    def _shapes(od, trs, paths):
        return jax.vmap(lambda tr_, x_: path_move_shapes(pm, rm, basis, od, tr_, x_, with_rp))(trs, paths)

    @shared_jit
    def _init_chains(k_chains, tr0, eks, xs0, trs0, lfs, rps):
        frame0 = LowFrequencyFrame(tr0, basis)

        def _init_chain(ck, x, tr, lf, rp):
            k_path, k_run = jax.random.split(ck)
            ref = dispersed_start(k_path, pm, frame0, lf, eks)
            # the log density is set at the first block
            rwm = init_proposal(hyper, lambda x_: jnp.zeros(()), x)
            return ChainState(k_run, ref, rwm, rwm, lf, rp, tr, jnp.zeros((), jnp.int32),
                              jnp.zeros((T, nq)), jnp.zeros((T, nq)), jnp.zeros(()),
                              jnp.zeros((sched.n_draws + 1, T, pm.n_state)))

        return jax.vmap(_init_chain)(jax.random.split(k_chains, chains), xs0, trs0, lfs, rps)

    eks, ref_q = _smooth(y, mask, R, tr0)

    def per_chain(a):
        return np.broadcast_to(np.asarray(a), (chains,) + np.shape(a))

    lfs, rps = _shapes(od, jax.tree_util.tree_map(per_chain, tr0), per_chain(eks))
    states = _init_chains(k_chains, tr0, eks, xs0, trs0, lfs, rps)

    n_blocks = sched.n_blocks
    scan_len, segments, reshape_at = reshape_chunks(n_blocks, sched.burn_blocks, chunk_blocks, not pm.is_linear)

    # the data are arguments, not constants of the program: a compiled program (and
    # JAX's persistent cache entry) then serves every record of the same shape
    data = BlockData(y, mask, R, od, ref_q)
    # traced once inside the chunk's trace: for the shapes of its output (the skipped
    # blocks') and in the scan
    vblock = jax.jit(jax.vmap(block, (0, None, None)))

    @shared_jit
    def _run_chunk(states, blocks, end, data):
        # here, not before: the whole trace then happens under the one lowering turn
        # (latentforce.compile.shared_jit)
        info_shapes = jax.eval_shape(vblock, states, jax.ShapeDtypeStruct((), jnp.int32), data)[1]

        def skip(s):
            return s, jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), info_shapes)

        def body(s, b):
            return jax.lax.cond(b < end, lambda s_: vblock(s_, b, data), skip, s)

        states, info = jax.lax.scan(body, states, blocks)
        return states, jax.tree_util.tree_map(lambda a: jnp.swapaxes(a, 0, 1), info)  # chains first

    infos = []
    for start, end in segments:
        if start in reshape_at:  # new shapes, the adapted scales kept
            lfs, rps = _shapes(od, states.tr, states.reference)
            states = states._replace(rwm_lf=_with_scale_of(lfs, states.rwm_lf),
                                     rwm_rp=_with_scale_of(rps, states.rwm_rp))
        states, info = _run_chunk(states, np.arange(start, start + scan_len, dtype=np.int32), np.int32(end), data)
        infos.append(jax.tree_util.tree_map(lambda a: np.asarray(a)[:, :end - start], info))
        if progress is not None:
            acc = float(np.mean(infos[-1].accept))
            progress(end * sched.state_every, n_blocks * sched.state_every, acc)
    info = jax.tree_util.tree_map(lambda *a: np.concatenate(a, axis=1), *infos)  # the segments tile the blocks
    return _assemble(pm, hyper, states, info, ref_q, sched.burn_in, sched.total, sched.burn_blocks, sched.n_draws,
                     tpoints)


def _assemble(pm, hyper, states: ChainState, info: BlockInfo, ref_q, burn_in, total, burn_blocks,
              n_draws, tpoints) -> PGASOutput:
    chains = info.accept.shape[0]
    theta = np.reshape(info.theta, (chains, info.accept.shape[1] * info.accept.shape[2], len(hyper.names)))[:, :total]
    accept = np.reshape(info.accept, (chains, -1))[:, :total]
    th_post = {n: theta[:, burn_in:, i] for i, n in enumerate(hyper.names)}
    th_burn = {n: theta[:, :burn_in, i] for i, n in enumerate(hyper.names)}
    count = np.asarray(states.count)[:, None, None]
    s1 = np.asarray(states.sum1)
    s2 = np.asarray(states.sum2)
    # pool the chains: mean and sd over every post-burn-in state sample
    n_all = count.sum()
    mean_c = s1.sum(0) / n_all
    var = np.maximum(s2.sum(0) / n_all - mean_c**2, 0.0)
    mean = mean_c + np.asarray(ref_q)
    sd = np.sqrt(var)
    nd, nf = pm.ndof, pm.nforce
    sl = {"displacement": slice(0, nd), "velocity": slice(nd, 2 * nd), "force": slice(2 * nd, 2 * nd + nf)}
    state_mean = {k: mean[:, v] for k, v in sl.items()}
    state_sd = {k: sd[:, v] for k, v in sl.items()}
    cov = np.asarray(jax.vmap(proposal_covariance)(states.rwm))
    mh_sd = np.sqrt(np.diagonal(cov, axis1=1, axis2=2))
    mh_corr = cov / np.maximum(mh_sd[:, :, None] * mh_sd[:, None, :], 1e-300)
    post = slice(burn_blocks, None)
    switch = info.switch_rate[:, post]
    ess = info.ess[:, post]
    fp = info.force_points[:, post]
    diag = {
        "acceptance": accept[:, burn_in:].mean(axis=1).tolist() if hyper.names else [],
        "switch_rate": switch.mean(axis=1).tolist(),
        "ess_per_particle": ess.mean(axis=1).tolist(),
        "nonfinite_log_likelihood": int(np.sum(~np.isfinite(info.log_likelihood))),
        "mh_proposal_sd": mh_sd.tolist(),
        "mh_proposal_corr": mh_corr.tolist(),
        "mh_sampling_space": "log",
        "acceptance_noncentred": np.reshape(info.accept_noncentred, (chains, -1))[:, burn_in:total].mean(axis=1).tolist()
        if hyper.names else [],
        "acceptance_lowfreq": info.accept_lowfreq[:, burn_blocks:].mean(axis=1).tolist(),
        "acceptance_residual": info.accept_residual[:, burn_blocks:].mean(axis=1).tolist(),
    }
    diag.update(convergence_diagnostics(th_post, fp, tpoints))
    return PGASOutput(hyper.names, th_post, th_burn, np.asarray(states.draws)[:, :n_draws], state_mean, state_sd,
                      accept[:, burn_in:].mean(axis=1) if hyper.names else np.zeros(chains), switch, ess,
                      info.log_likelihood[:, post], fp, tpoints, diag, mh_sd)


def convergence_diagnostics(theta: dict, force_points: np.ndarray, tpoints) -> dict:
    """R-hat and bulk ESS (arviz) of the hyperparameters and of the force at the recorded time points."""
    import warnings

    import arviz as az

    out = {"rhat": {}, "ess_bulk": {}}
    series = dict(theta)
    for j, t in enumerate(tpoints):
        for f in range(force_points.shape[-1]):
            series[f"force[{int(t)}]" + (f"[{f}]" if force_points.shape[-1] > 1 else "")] = force_points[:, :, j, f]
    for name, arr in series.items():
        if arr.shape[1] < 4:
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            out["rhat"][name] = float(az.rhat(np.asarray(arr)))
            out["ess_bulk"][name] = float(az.ess(np.asarray(arr)))
    return out


def to_run_result(out: PGASOutput, model, y, dt: float, *, columns=None, truth: dict | None = None,
                  seed: int = 0, wall_time_s: float = 0.0, fixed: dict | None = None):
    """Convert a :class:`PGASOutput` to the results layer's :class:`~latentforce.results.RunResult`.

    ``columns``: names of the measured channels (default: the sensors' names,
    or ``"<quantity>_<dof>"``). The point estimate is the posterior mean of
    each free hyperparameter; ``log_likelihood`` the mean particle-filter
    estimate over the last sweeps (an estimate, not exact).
    """
    from latentforce.results import RunResult

    y = np.asarray(y, dtype=float)
    T = y.shape[0]
    if columns is None:
        columns = [s.name or f"{s.quantity}_{s.dof}" for s in model.sensors]
    nd, nm, kd = model.ndof, model.n_mech, model.kernel.dim
    force_idx = nm + kd * np.arange(model.nforce)
    tr = out.trajectories
    path_draws = {"displacement": tr[..., :nd], "velocity": tr[..., nd:nm], "force": tr[..., force_idx]}
    sample_stats = {"log_likelihood": out.log_likelihood, "switch_rate": out.switch_rate,
                    "ess_per_particle": out.ess}
    ll = out.log_likelihood
    return RunResult(
        method="pgas",
        time=np.arange(T) * float(dt),
        ndof=nd,
        nforce=model.nforce,
        state_mean={k: np.asarray(v) for k, v in out.state_mean.items()},
        state_sd={k: np.asarray(v) for k, v in out.state_sd.items()},
        param_draws={k: np.asarray(v) for k, v in out.theta.items()},
        path_draws=path_draws,
        sample_stats=sample_stats,
        acceptance=[float(a) for a in out.acceptance],
        log_likelihood=float(np.mean(ll[:, -max(1, ll.shape[1] // 10):])) if ll.size else float("nan"),
        observed={c: y[:, i] for i, c in enumerate(columns)},
        truth=dict(truth or {}),
        point_estimate={k: float(np.mean(v)) for k, v in out.theta.items()},
        diagnostics=_jsonable_diag(out.diagnostics),
        seed=int(seed),
        wall_time_s=float(wall_time_s),
        fixed=dict(fixed or {}),
    )


def _jsonable_diag(d):
    if isinstance(d, dict):
        return {k: _jsonable_diag(v) for k, v in d.items()}
    if isinstance(d, (list, tuple)):
        return [_jsonable_diag(v) for v in d]
    if isinstance(d, np.ndarray):
        return d.tolist()
    if isinstance(d, np.generic):
        return d.item()
    return d
