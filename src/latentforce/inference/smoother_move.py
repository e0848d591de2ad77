r"""The smoother move: Metropolis-Hastings steps whose proposals come from the linearised model's smoother.

Where the particle sweep stops renewing the path (smooth forces, Matérn-5/2 and
7/2: ancestor switch rates of 0.01 and 1e-4, ``docs/nonlinear.md``), the
posterior of the latent path is often close to a Gaussian: with a displacement
channel the Laplace approximation at the mode carried 94-95 % of an
independence sampler's proposals at Matérn-3/2 to 7/2
(``benchmarks/results/independence_probe.md``). This move makes that an
O(T) kernel of the Gibbs block.

The target is the latent path's posterior at the block's :math:`\theta`,

.. math:: \pi(g) \propto p_\theta(g)\; p\big(y \mid \mathrm{path}(g)\big),

:math:`g = (x_f, w)` the sampler's Markov latent and :math:`\mathrm{path}`
the mechanical rebuild (:mod:`latentforce.inference.particle_model`). Fix a
*centre* path :math:`\bar x` (a function of the data and of the run's
history before the current block, never of the current path) and replace the
rebuild by its first-order expansion about it,

.. math:: \mathrm{mech}^{\rm lin}_t = \Phi(\bar x_{t-1}) + \Phi'(\bar x_{t-1})
          (x^{\rm lin}_{t-1} - \bar x_{t-1}) + w_t ,

and the sensors by theirs, :math:`h(\bar x_t) + H_t (x_t - \bar x_t)`. The
map :math:`g \mapsto x^{\rm lin}(g)` is affine, so

.. math:: q(g) \propto p_\theta(g)\; N\big(y;\, h(\bar x) + H (x^{\rm lin}(g) - \bar x), R\big)

is a Gaussian: the smoothing distribution of a linear-Gaussian state-space
model in :math:`x = (\mathrm{mech}, x_f)` with the transition
:math:`f(\bar x_{t-1}) + F_t(x_{t-1} - \bar x_{t-1})` (``F_t`` the Jacobian
of :meth:`~particle_model.ParticleModel.state_step`) and the latent's joint
noise. A draw is made by the simulation smoother of Durbin & Koopman (2002) in the
whitened innovations :math:`\varepsilon` (:func:`_draw`): one covariance recursion
shared by the move's proposals, then per draw a simulated record and two smoothing
passes of the means. Not forward filtering, backward sampling in :math:`x`: its
draws' increments leave the range of the latent's noise covariance by round-off
(its condition number is 1e20 at Matérn-7/2), whitened they became innovations
of size ~100, and the path moves that work in whitened coordinates then
sampled a posterior 3.5 times too wide (measured on a linear SDOF, Matérn-7/2).
The prior cancels from the importance weight, which
needs only the two observation terms:

.. math:: \log \frac{\pi(g)}{q(g)} = \log p\big(y \mid \mathrm{path}(g)\big)
          - \log N\big(y;\, h(\bar x) + H (x^{\rm lin}(g) - \bar x), R\big) + c,

and the proposal is accepted with :math:`\min\{1, \exp(\log w' - \log w)\}`
(Tierney 1994). For a linear system the expansion is exact, :math:`q = \pi`,
every proposal is accepted and each one is an exact draw of the conditional
path (tested). The move never linearises the target: where the Gaussian is a
poor fit (acceleration alone on a stiffening system: the probe's acceptance
was below 0.01) it is simply rejected and costs one filter pass.

*Crank-Nicolson steps.* Where the Gaussian is a fair fit locally but not over the whole
record (acceleration alone, a smooth force on a stiffening Duffing: the second-order terms of
the expansion add up over the samples and the independence step is never accepted), a small
step about :math:`q` still is. In the innovations :math:`\varepsilon` (``whiten`` of the
latent, in which :math:`q` is :math:`N(\hat\varepsilon, \Sigma)`) the step

.. math:: \varepsilon' = \hat\varepsilon + \sqrt{1-\beta^2}\,(\varepsilon - \hat\varepsilon)
          + \beta\,(\varepsilon^q - \hat\varepsilon), \qquad \varepsilon^q \sim q,

is an autoregression that leaves :math:`q` invariant and is reversible with respect to it, so
the Metropolis-Hastings ratio for :math:`\pi = q\,w` is again :math:`w(g')/w(g)`
(the preconditioned Crank-Nicolson proposal of Cotter et al. 2013, with the Gaussian :math:`q`
in place of the prior: Rudolf & Sprungk 2018). :math:`\beta = 1` is the independence step.
The move cycles through :data:`CN_BETAS`, one step each: on the acceleration-only Duffing
record of ``benchmarks/results/nonlinear_calibration_orders_acc.md`` at Matérn-5/2 the
independence step accepted 0 of its proposals and the ladder 4 % (the small steps), and the
force's coverage of the truth at +-1/2/3 sd went from 44/77/83 % to 81/92/99 % in the same
60 s (R-hat stayed above 2: the chains still hold apart, a segment of the record in another
local mode; what is left of that issue). Tested: on an acceleration-only Duffing record, where
:math:`q \ne \pi`, chains at (near) posterior draws keep every time's mean and sd through these
steps. The proposal's noise is the observation density's own (``od.R``): the weights assume
the proposal was built from the same density (a proposal built at another noise, with weights
at this one, was measured wrong).

The centre. :func:`iterated_centre` runs Gauss-Newton on the path (the
iterated extended Kalman smoother: the linearised model's smoothed mean,
re-linearised there) from a given path. The Gibbs driver sets it from the
extended Kalman smoother at the start and, for nonlinear systems, from each
chain's own path at the burn-in's re-shaping points
(:func:`latentforce.inference.pgas_schedule.reshape_chunks`); after the burn-in
it is fixed, so the post-burn-in kernel is a fixed one given :math:`\theta`.

The joint move (:func:`joint_move`). Given a path, a smooth force's
hyperparameters are pinned (the path's derivatives fix
:math:`\sigma_f^2/\ell^{2\nu}` to a few per cent), so Metropolis-within-Gibbs
on :math:`\theta` crawls: on a small Duffing record with a displacement
channel, hyperparameter ESS 9-20 in 2 000 draws. This move updates
:math:`(\theta, g)` together: :math:`\theta'` from a random walk (in
:math:`\log\theta`), then :math:`g' \sim q_{\theta'}`, the proposal above at
:math:`\theta'` (same centre). With :math:`q_\theta(g) = p_\theta(g)\,
\ell_{\rm lin}(g) / Z(\theta)`, :math:`Z(\theta)` the linearised model's marginal
likelihood (the filter's prediction-error decomposition, :func:`_log_marginal`),
the acceptance ratio is

.. math:: \frac{p(\theta')\, Z(\theta')\, w(g')}{p(\theta)\, Z(\theta)\, w(g)},
          \qquad w = \frac{p(y \mid \mathrm{path}(g))}{\ell_{\rm lin}(g)},

each :math:`w` with its own :math:`\theta`'s expansion: exact for any system.
For a linear system :math:`w` is constant and :math:`Z` the exact likelihood
(tested at every order), so the move is the marginal random walk of
``kalman-mcmc``, carrying an exact draw of the path; where the expansion is
good (a displacement channel) it mixes nearly as well. Measured on that
Duffing record: hyperparameter ESS 277-282 in the same 20 s.

System parameters (``m, c, k, k3`` ..., :class:`~latentforce.inference.hyper_moves.Hyper`)
join :math:`\theta` in this move and in no other: the model (its map :math:`\Phi`, its
linearisation, the transition's within-step noise) is rebuilt at the proposed values, and
:math:`g' = (x_f', w')` is mapped to its path by that model. The map from path to latent,
:math:`w_t = \mathrm{mech}_t - \Phi_\theta(\mathrm{mech}_{t-1}, x_{f,t-1})`, is
triangular with a unit diagonal, so the densities of path and latent are equal at every
:math:`\theta` and the ratio above stands unchanged. Given a path the within-step noise
(sd ~1e-8 m per step) pins a stiffness or damping to a tiny interval, which is why a
Metropolis-within-Gibbs step on them would not move.

*Re-centred.* A system parameter that reshapes the path's nonlinear part (Bouc-Wen's
``gamma`` reshapes the hysteretic force) makes the expansion about a centre found at the old
value a poor fit at the new one, and only small steps pass. With ``recentre`` the expansion at
each point :math:`\theta` is about ``recentre`` Gauss-Newton iterations from the fixed centre *at
that point's model*: still a function of :math:`\theta` (and of the fixed centre and the data)
alone, so the ratio above is unchanged, the current point evaluated as it was when proposed
(tested). Cost: ``recentre`` more filter-and-smoother passes per point.

*Adapting the walk.* Each proposal draws a fresh path, so :math:`w(g')` is noise on the
target (the move is a pseudo-marginal step with one importance draw): where the expansion is
loose, even a step of zero length is accepted only as often as two draws' weights allow. The walk's
scale therefore adapts (burn-in only) on the acceptance of :math:`p(\theta) Z(\theta)` alone, towards
the noiseless optimum, not on the step's own acceptance: that one stayed under its target at any
length and shrank the step towards zero. Measured on a Bouc-Wen record with a Matérn-7/2 force
(T = 65, the default start): adapted on its own acceptance the walk accepted 0.19-0.21 with steps
under 0.05 in a posterior of sd 0.36 (log variance), the four chains' means 7.62-8.00, R-hat 1.18;
adapted on :math:`p Z` it accepts 0.08-0.09 (near the 7 % that Sherlock et al. 2015 find optimal
for pseudo-marginal walks), the chains' means 7.905-7.910. Where :math:`Z` is much wider than the
marginal (a loose expansion) that rule alone would size a step the target almost never accepts: a
floor on the step's own running acceptance (:data:`~latentforce.inference.mcmc.ACCEPTANCE_FLOOR`,
:func:`~latentforce.inference.mcmc.step`) caps it.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from latentforce.inference import particle_model
from latentforce.inference.hyper_moves import mh_step
from latentforce.inference.latent import ObservationDensity, colour, observation_log_likelihood, whiten
from latentforce.linalg import cho_solve, cholesky, symmetrise

#: folded into a chain's key for the move's random numbers (its own stream)
SMOOTHER_STREAM = 0x5300
#: folded into a chain's key for the joint (theta, path) move's random numbers
JOINT_STREAM = 0x4A00

#: Gauss-Newton iterations of :func:`iterated_centre` (the Duffing cases converge to 1e-8 in 5-6
#: from the extended Kalman smoother; the centre need not be the exact mode, only close to it)
CENTRE_ITERATIONS = 3

#: Gauss-Newton iterations that re-centre the joint move's expansion at each point theta when
#: system parameters of a hysteretic system are sampled (:func:`joint_log_target`, module doc;
#: where, measured: latentforce.inference.pgas_block.make_block)
JOINT_RECENTRE = 2

#: the smoother move's step sizes, one step each in turn (module doc, "Crank-Nicolson steps";
#: 1: the independence step, exact draws for a linear system)
CN_BETAS = (1.0, 0.5, 0.2, 0.1)


class Linearisation(NamedTuple):
    """The sampler's model expanded about a centre path ``c``."""

    centre: Float[Array, "T n"]
    F: Float[Array, "T n n"]  # d f / d x at c_t (the transition from t to t + 1; the last is unused)
    f: Float[Array, "T n"]  # f(c_t)
    H: Float[Array, "T d n"]  # d h / d x at c_t
    h: Float[Array, "T d"]  # h(c_t)
    E: Float[Array, "nm nf"]  # the within-step noise's mean per force state (tr.A's noise-force block)


def linearise(pm: particle_model.ParticleModel, tr: particle_model.Transition, centre) -> Linearisation:
    """The transition and the sensors expanded about ``centre`` (Jacobians by forward mode)."""

    def f(x):
        return pm.state_step(tr, x)

    F = jax.vmap(jax.jacfwd(f))(centre)
    H = jax.vmap(jax.jacfwd(pm.readout))(centre)
    G = pm.latent_layout
    return Linearisation(centre, F, jax.vmap(f)(centre), H, jax.vmap(pm.readout)(centre), tr.A[G.noise, G.force])


def _predict_mech(pm, lin: Linearisation, x_prev, t_prev):
    r""":math:`\Phi(\bar x) + \Phi'(\bar x)(x - \bar x)` at the step from ``t_prev`` (vectorised over it):
    the linearised transition's mechanical rows without the within-step noise's mean ``E x_f``."""
    L = pm.layout
    dx = x_prev - lin.centre[t_prev]
    full = lin.f[t_prev, L.mech] + jnp.einsum("tij,tj->ti", lin.F[t_prev][:, L.mech], dx)
    return full - x_prev[:, L.force_states] @ lin.E.T


def linear_path(pm: particle_model.ParticleModel, lin: Linearisation, g: Float[Array, "T nl"]) -> Float[Array, "T n"]:
    r""":math:`x^{\rm lin}(g)`: the path rebuilt with the expanded mechanical step (module doc)."""
    G, L = pm.latent_layout, pm.layout
    xf, w = g[:, G.force], g[:, G.noise]
    mech1 = pm.mech0_mean + w[0]

    def _step(mech, inp):
        t, xf_prev, w_t = inp
        x_prev = jnp.concatenate([mech, xf_prev])[None]
        nxt = _predict_mech(pm, lin, x_prev, t[None])[0] + w_t
        return nxt, nxt

    T = g.shape[0]
    _, mechs = jax.lax.scan(_step, mech1, (jnp.arange(T - 1), xf[:-1], w[1:]))
    mech = jnp.concatenate([mech1[None], mechs])
    out = jnp.zeros((T, pm.n_state))
    return out.at[:, L.mech].set(mech).at[:, L.force_states].set(xf)


def _linear_log_likelihood(pm, lin: Linearisation, od: ObservationDensity, x) -> Float[Array, ""]:
    """:math:`\\log N(y; h(\\bar x) + H(x - \\bar x), R)` over the observed channels."""
    pred = lin.h + jnp.einsum("tij,tj->ti", lin.H, x - lin.centre)
    r = (od.y - pred) * od.maskf
    return jnp.sum(od.const) - 0.5 * jnp.einsum("ti,tij,tj->", r, od.Rinv, r)


def log_weight(pm, lin: Linearisation, od: ObservationDensity, g) -> tuple[Float[Array, ""], Float[Array, "T n"]]:
    r"""``(log pi(g) - log q(g) + c, path(g))`` (module doc): the exact rebuild's likelihood less the
    expanded one's."""
    path = pm.path(g)
    return _log_weight(pm, lin, od, g, path), path


def _log_weight(pm, lin: Linearisation, od: ObservationDensity, g, path) -> Float[Array, ""]:
    """:func:`log_weight` of ``g`` whose rebuilt path ``path`` is already known."""
    return observation_log_likelihood(pm, od, path) - _linear_log_likelihood(pm, lin, od, linear_path(pm, lin, g))


class _Gains(NamedTuple):
    """The linearised model's Kalman filter, the parts that do not depend on the data."""

    P: Float[Array, "T n n"]  # predicted covariance of x_t given y_{1:t-1}
    Sinv: Float[Array, "T d d"]  # inverse innovation covariance (zero rows/columns: missing channels)
    M: Float[Array, "T n d"]  # filter gain P H^T S^-1
    Hm: Float[Array, "T d n"]  # H_t with the missing channels' rows zeroed
    L1: Float[Array, "n nl"]  # x_1 = m_1 + L1 eps_1
    Lq: Float[Array, "n nl"]  # the state's noise is Lq eps_t
    mask: Float[Array, "T d"]  # 1 where a channel is observed
    logdet: Float[Array, " T"]  # log |S_t| over the observed channels (the marginal likelihood)


def noise_factors(pm, tr) -> tuple[Float[Array, "n nl"], Float[Array, "n nl"]]:
    """``(L1, Lq)``: the latent's whitening factors with rows in the state's order, so that the first
    state is ``m1 + L1 eps_1`` and each later step's noise ``Lq eps_t`` (:func:`_gains`)."""
    G = pm.latent_layout
    latent = np.arange(G.n)
    perm = np.r_[latent[G.noise], latent[G.force]]  # the latent's entries in the state's order
    return particle_model._chol(tr.Pinf)[perm], particle_model._chol(tr.Q)[perm]


def _gains(pm, tr, lin: Linearisation, od: ObservationDensity) -> _Gains:
    """The covariance recursion of the linearised model in prediction form (Durbin & Koopman 2012,
    Sec. 4.3), its noise factored as the latent's whitening factors (state order) so that the
    draws are exactly ``colour`` of innovations (:func:`_draw`); the sensors' noise is ``od.R``."""
    R = od.R
    L1, Lq = noise_factors(pm, tr)
    Q = Lq @ Lq.T
    mf = od.maskf
    Hm = lin.H * mf[:, :, None]

    def _step(P, inp):
        F_t, H_t, m = inp
        S = symmetrise(H_t @ P @ H_t.T + R) * jnp.outer(m, m) + jnp.diag(1.0 - m)
        C = cholesky(S)
        Sinv = cho_solve(C, jnp.eye(S.shape[0])) * jnp.outer(m, m)
        M = P @ H_t.T @ Sinv
        P_f = symmetrise(P - M @ H_t @ P)
        return symmetrise(F_t @ P_f @ F_t.T + Q), (P, Sinv, M, 2.0 * jnp.sum(jnp.log(jnp.diagonal(C))))

    _, (P, Sinv, M, logdet) = jax.lax.scan(_step, symmetrise(L1 @ L1.T), (lin.F, Hm, mf))
    return _Gains(P, Sinv, M, Hm, L1, Lq, mf, logdet)


def _filter_means(pm, lin: Linearisation, gains: _Gains, y):
    """``(a, v)``: the linearised model's predicted means and innovations (zero on missing channels)."""
    m1 = jnp.concatenate([pm.mech0_mean, jnp.zeros(pm.nfx)])
    d = lin.h - jnp.einsum("tij,tj->ti", lin.H, lin.centre)  # y = H x + d + v
    e = lin.f - jnp.einsum("tij,tj->ti", lin.F, lin.centre)  # x_{t+1} = F x_t + e + noise

    def _forward(a, inp):
        y_t, d_t, e_t, F_t, Hm_t, M_t = inp
        v = y_t - Hm_t @ a - d_t
        return F_t @ (a + M_t @ v) + e_t, (a, v)

    d, y = d * gains.mask, y * gains.mask
    _, (a, v) = jax.lax.scan(_forward, m1, (y, d, e, lin.F, gains.Hm, gains.M))
    return a, v


def _log_marginal(gains: _Gains, v) -> Float[Array, ""]:
    r""":math:`\log q(y \mid \theta)`, the linearised model's marginal likelihood, by the prediction-error
    decomposition :math:`\sum_t -\tfrac12 (\log|2\pi S_t| + v_t^\top S_t^{-1} v_t)` over the observed channels."""
    quad = jnp.einsum("ti,tij,tj->", v, gains.Sinv, v)
    return -0.5 * (jnp.sum(gains.logdet) + quad + jnp.sum(gains.mask) * jnp.log(2.0 * jnp.pi))


def _smooth(pm, lin: Linearisation, gains: _Gains, y) -> tuple[Float[Array, "T nl"], Float[Array, "T n"]]:
    r"""``(eps_hat, x_hat)``: the smoothed mean of the innovations and of the state given ``y``.

    The mean recursion of the filter, then the backward recursion
    :math:`r_{t-1} = H_t^T S_t^{-1} v_t + L_t^T r_t`, :math:`L_t = F_t(I - M_t H_t)`;
    :math:`\hat\varepsilon_1 = L_1^T r_0`, :math:`\hat\varepsilon_{t+1} = L_q^T r_t`,
    :math:`\hat x_t = a_t + P_t r_{t-1}` (Durbin & Koopman 2012, Sec. 4.4-4.5). The innovations come
    out as :math:`L^T r`, never through an inverse of the (ill-conditioned) noise covariance.
    """
    a, v = _filter_means(pm, lin, gains, y)
    return _smooth_from(pm, lin, gains, a, v)


def _smooth_from(pm, lin: Linearisation, gains: _Gains, a, v):
    """:func:`_smooth` given the filter's predicted means ``a`` and innovations ``v``."""

    def _backward(r, inp):
        v_t, F_t, Hm_t, M_t, Sinv_t = inp
        r_prev = Hm_t.T @ (Sinv_t @ v_t) + (F_t @ (jnp.eye(F_t.shape[0]) - M_t @ Hm_t)).T @ r
        return r_prev, r_prev

    _, r_prev = jax.lax.scan(_backward, jnp.zeros(pm.n_state), (v, lin.F, gains.Hm, gains.M, gains.Sinv), reverse=True)
    eps = jnp.concatenate([(gains.L1.T @ r_prev[0])[None], r_prev[1:] @ gains.Lq])
    return eps, a + jnp.einsum("tij,tj->ti", gains.P, r_prev)


def _draw(key, pm, tr, lin: Linearisation, gains: _Gains, od: ObservationDensity, eps_hat) -> Float[Array, "T nl"]:
    r"""One latent path of the proposal, by the simulation smoother of Durbin & Koopman (2002):
    :math:`\varepsilon^* \sim N(0, I)` and data :math:`y^*` simulated from the linearised model
    through it; then :math:`\varepsilon = \varepsilon^* - \hat\varepsilon(y^*) + \hat\varepsilon(y)`
    and the latent is ``colour`` of it (``eps_hat``: :math:`\hat\varepsilon(y)`)."""
    return colour(tr, _draw_eps(key, pm, tr, lin, gains, od, eps_hat))


def _draw_eps(key, pm, tr, lin: Linearisation, gains: _Gains, od: ObservationDensity, eps_hat) -> Float[Array, "T nl"]:
    """:func:`_draw`'s innovations (before ``colour``)."""
    k_eps, k_obs = jax.random.split(key)
    T = lin.centre.shape[0]
    eps_star = jax.random.normal(k_eps, (T, pm.nl))
    x_star = linear_path(pm, lin, colour(tr, eps_star))
    # each channel its own stream: a record observed through extra, never-observed channels
    # (pgas.observe_through) draws what it draws through its own sensors
    z = jax.vmap(lambda i: jax.random.normal(jax.random.fold_in(k_obs, i), (T,)), out_axes=1)(jnp.arange(od.y.shape[1]))
    noise = z @ cholesky(symmetrise(od.R)).T
    y_star = lin.h + jnp.einsum("tij,tj->ti", lin.H, x_star - lin.centre) + noise
    return eps_star - _smooth(pm, lin, gains, y_star)[0] + eps_hat


def proposal_draws(key, pm, tr, od: ObservationDensity, centre, n: int) -> Float[Array, "n T n"]:
    """``n`` independent draws of the proposal as latent paths :math:`g` (tests and diagnostics)."""
    lin = linearise(pm, tr, centre)
    gains = _gains(pm, tr, lin, od)
    eps_hat = _smooth(pm, lin, gains, od.y)[0]
    return jax.vmap(lambda k: _draw(k, pm, tr, lin, gains, od, eps_hat))(jax.random.split(key, n))


def iterated_centre(
    pm, tr, od: ObservationDensity, path: Float[Array, "T n"], iterations: int = CENTRE_ITERATIONS
) -> Float[Array, "T n"]:
    """Gauss-Newton from ``path``: the linearised model's smoothed mean, ``iterations`` times re-expanded there."""

    def _one(c, _):
        lin = linearise(pm, tr, c)
        return _smooth(pm, lin, _gains(pm, tr, lin, od), od.y)[1], None

    c, _ = jax.lax.scan(_one, path, None, length=int(iterations))
    return c


class Prepared(NamedTuple):
    """The linearised model about a centre, its covariance recursion and its smoothed innovations: what
    the smoother move's steps share (:func:`prepare`; also ``benchmarks/line_probe.py``'s)."""

    lin: Linearisation
    gains: _Gains
    eps_hat: Float[Array, "T nl"]


def prepare(pm, tr, od: ObservationDensity, centre) -> Prepared:
    """The proposal's parts about ``centre`` (:class:`Prepared`): one expansion, one covariance recursion,
    one smoothing pass."""
    lin = linearise(pm, tr, centre)
    gains = _gains(pm, tr, lin, od)
    return Prepared(lin, gains, _smooth(pm, lin, gains, od.y)[0])


def smoother_move(
    key, pm, tr, od: ObservationDensity, centre, path: Float[Array, "T n"], n_steps: int, betas=CN_BETAS
) -> tuple[Float[Array, "T n"], Float[Array, " k"]]:
    r"""``n_steps`` Metropolis-Hastings steps from the proposal about ``centre`` (module doc).

    Step ``j`` is a Crank-Nicolson step of size :math:`\beta_j` = ``betas[j % len(betas)]`` in the
    innovations: :math:`\varepsilon' = \hat\varepsilon + \sqrt{1-\beta^2}(\varepsilon - \hat\varepsilon)
    + \beta(\varepsilon^q - \hat\varepsilon)`, :math:`\varepsilon^q` a draw of the proposal
    (module doc, "Crank-Nicolson steps"); :math:`\beta = 1` is the independence step. The draws do
    not depend on the chain, so all are made at once (one filter pass, ``n_steps`` backward passes)
    and the steps then run in order. Returns the new path and each step's acceptance (bool).
    """
    lin, gains, eps_hat = prepare(pm, tr, od, centre)
    k_draw, k_acc = jax.random.split(key)
    ds = jax.vmap(lambda k: _draw_eps(k, pm, tr, lin, gains, od, eps_hat))(jax.random.split(k_draw, n_steps))
    beta = jnp.asarray([float(betas[j % len(betas)]) for j in range(int(n_steps))])
    g_cur = pm.latent(path)
    lw_cur = _log_weight(pm, lin, od, g_cur, path)  # the current path: no rebuild
    logu = jnp.log(jax.random.uniform(k_acc, (n_steps,)))

    def _step(carry, inp):
        lw, x, eps = carry
        d, b, lu = inp
        eps_p = eps_hat + jnp.sqrt(1.0 - b**2) * (eps - eps_hat) + b * (d - eps_hat)
        lw_p, x_p = log_weight(pm, lin, od, colour(tr, eps_p))
        ok = jnp.isfinite(lw_p) & (lu < lw_p - lw)
        return (jnp.where(ok, lw_p, lw), jnp.where(ok, x_p, x), jnp.where(ok, eps_p, eps)), ok

    (_, out, _), acc = jax.lax.scan(_step, (lw_cur, path, whiten(tr, g_cur)), (ds, beta, logu))
    return out, acc


class JointProposal(NamedTuple):
    """What the joint move needs of a point :math:`\\theta`: its log target and, for a proposed one, its path."""

    log_target: Float[Array, ""]  # log p(theta) + log q(y | theta) + log w(g) (sampling coordinates)
    path: Float[Array, "T n"]
    tr: particle_model.Transition
    base: Float[Array, ""]  # log p(theta) + log Z(theta): the target less the path's weight


def joint_log_target(
    key, pm, tr, od: ObservationDensity, centre, log_prior, path=None, recentre: int = 0
) -> JointProposal:
    r"""The joint move's target at the transition ``tr`` (module doc, "The joint move").

    ``path=None``: a proposed point, its path drawn from the proposal about ``centre`` at ``tr``
    with ``key``; else the current point, whose path is ``path``. ``log_prior`` is the
    hyperparameters' log prior density in the sampling coordinates at this point. ``recentre``:
    Gauss-Newton iterations from ``centre`` at this point's model first (module doc).
    """
    if recentre:
        centre = iterated_centre(pm, tr, od, centre, recentre)
    lin = linearise(pm, tr, centre)
    gains = _gains(pm, tr, lin, od)
    a, v = _filter_means(pm, lin, gains, od.y)
    base = log_prior + _log_marginal(gains, v)
    if path is None:
        g = _draw(key, pm, tr, lin, gains, od, _smooth_from(pm, lin, gains, a, v)[0])
        lw, path = log_weight(pm, lin, od, g)
    else:
        lw = _log_weight(pm, lin, od, pm.latent(path), path)
    return JointProposal(base + lw, path, tr, base)


def joint_move(
    key,
    rwm,
    pm,
    hyper,
    od: ObservationDensity,
    centre,
    tr,
    path: Float[Array, "T n"],
    n_steps: int,
    *,
    adapt,
    reshape_steps,
    step0,
    target: float,
    recentre: int = 0,
):
    r"""``n_steps`` joint Metropolis-Hastings steps on :math:`(\theta, \text{path})` (module doc, "The joint move").

    ``rwm`` (:class:`~latentforce.inference.mcmc.RWMState`): the walk on :math:`x = \log\theta`, at
    the chain's current ``x`` (its log density is refreshed here); ``tr`` the transition there and
    ``path`` the chain's path. With system parameters sampled (``hyper.sys_names``) ``x`` is
    ``(x, x_sys)`` (:attr:`~latentforce.inference.hyper_moves.Hyper.joint_names`), ``pm`` the
    model at any system parameters (it is rebuilt at each point, :meth:`Hyper.model_at`) and
    ``tr`` the transition at the current point's. Adapts the walk where ``adapt`` (burn-in), re-shaping it from its
    running covariance after the steps numbered ``reshape_steps`` (counted from ``step0``); its scale
    adapts on the acceptance of :math:`p(\theta) Z(\theta)` alone (module doc, "Adapting the walk").
    ``recentre``: the expansion at each point is re-centred by that many Gauss-Newton iterations
    from ``centre`` (module doc). Returns ``(rwm, path, tr, accepted)``.
    """
    p = len(hyper.names)
    cur = joint_log_target(
        None, hyper.model_at(pm, rwm.x[p:]), tr, od, centre, hyper.joint_log_prior(rwm.x), path, recentre
    )
    rwm = rwm._replace(logdensity=cur.log_target)

    def _one(carry, s):
        r, aux = carry
        k_step, k_draw = jax.random.split(jax.random.fold_in(key, s))

        def _target(x):
            pm_x = hyper.model_at(pm, x[p:])  # the model at the proposed system parameters
            jp = joint_log_target(
                k_draw, pm_x, pm_x.transition(*hyper.values(x)), od, centre, hyper.joint_log_prior(x), None, recentre
            )
            return jp.log_target, (jp.path, jp.tr, jp.base)

        j = step0 + s
        r, info, aux = mh_step(
            k_step,
            r,
            _target,
            adapt=adapt,
            reshape=jnp.any(j == reshape_steps),
            target=target,
            aux=aux,
            adapt_density=lambda a: a[2],
        )
        return (r, aux), info.accepted

    (rwm, (path, tr, _)), accepted = jax.lax.scan(_one, (rwm, (path, tr, cur.base)), jnp.arange(int(n_steps)))
    return rwm, path, tr, accepted
