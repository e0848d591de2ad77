r"""The profile move: the internal states' initial values stepped along the posterior's curved ridge.

**Why.** On the Bouc-Wen oscillator with a twice-differentiable force (Matérn-5/2) and the default
(wide) initial prior, the slowest coordinate of ``pgas`` was the initial hysteretic force
:math:`r_0` (posterior sd ~4-6 N): every move built before proposed it within 0.3-0.8 N of where it
was (docs/nonlinear.md, "Matérn-5/2: what still pins r0"). A change of :math:`r_0` must be met by a
change of the motion and the force over the record's first samples, along a *curved* ridge; a
Gaussian expanded at one path offers a straight line (the line probe: 6-45 % accepted, 0.5-1.7 N).

**The move.** Re-expand the Gaussian at each value of :math:`r_0`. For a proposed
:math:`r_0' = r_0 + A_j z` (``z`` standard normal, :math:`A_j` a fixed factor, so a symmetric step):

* :math:`c(r_0')`: :data:`ITERATIONS` Gauss-Newton iterations with :math:`r_0` pinned at
  :math:`r_0'`, from the chain's fixed centre (the smoother move's, ``ChainState.centre``): each the
  linearised model's smoothed mean conditioned on the linear functional :math:`r_0`. A function of
  :math:`r_0'` (and of the fixed centre, the transition and the data) alone;
* the path drawn from :math:`q_{c(r_0')}`, the linearised posterior about that centre
  (:mod:`~latentforce.inference.smoother_move`), conditioned on :math:`r_0 = r_0'`: a draw of it
  moved along :math:`r_0`'s regression direction :math:`\Sigma C (C^\top \Sigma C)^{-1}` (Matheron's
  rule; :math:`r_0 = o + C\varepsilon` is exactly linear in the innovations :math:`\varepsilon`,
  since the first state is the initial mean plus the first noise);
* accepted with :math:`\min\{1, \exp(L' - L)\}`,

.. math:: L(r_0, g) = \log Z_c + \log q_c(r_0) + \log w_c(g), \qquad c = c(r_0),

:math:`Z_c` the linearised model's marginal likelihood, :math:`q_c(r_0)` its posterior's marginal
density of :math:`r_0` (Gaussian: mean :math:`o + C\hat\varepsilon`, covariance
:math:`C^\top\Sigma C`), :math:`w_c = p(y \mid g) / \ell_c(g)` the smoother move's weight.
Why: :math:`\pi(g) / q_c(g) = Z_c\, w_c(g)` (the joint move's identity) and
:math:`q_c(g \mid r_0) = q_c(g) / q_c(r_0)`, so the Metropolis-Hastings ratio of this proposal is
:math:`\exp(L(r_0', g') - L(r_0, g))`: exact for any system, the current point's :math:`L` computed
the same way at its own :math:`r_0`. For a linear system :math:`w` is constant and :math:`L` the
exact log marginal density of :math:`r_0` (up to a constant): the move is a random walk on
:math:`r_0`'s marginal carrying an exact conditional draw of the path. Where the Gaussian given
:math:`r_0` is close to the conditional posterior (the virgin-start Bouc-Wen record's smoother move
accepted 94 %), nearly so.

**Steps.** Their factors :math:`A_j` cycle over :data:`PRIOR_SCALES` times the Cholesky factor of
the internal states' initial prior covariance, and :data:`GAUSSIAN_SCALE` times that of
:math:`q`'s marginal at the fixed centre (for a record that pins :math:`r_0` far below its prior
width): all fixed within a block, so each step is a Metropolis step with a symmetric proposal.

**Measured** (``benchmarks/profile_move_probe.py``, the Bouc-Wen Matérn-5/2 record, default start,
from each of four chains' paths after 200 ``pgas`` iterations, the move alone): acceptance 0.80-0.87
/ 0.66-0.75 / 0.45-0.56 at steps of 3 / 6 / 12 N with three Gauss-Newton iterations, 0.59-0.68 at
6 N with one (1.8 ms a step at T = 450, one chain, against 4.5 ms), :math:`r_0` ranging over
5-7 N (sd) within 200 steps. In ``pgas`` (:data:`PROFILE_STEPS` a block, one iteration) that record,
never converged before at the 180 s cap (R-hat 1.13-1.83), converged in 93-99 s; the frame of
``demo frame``, whose brace's :math:`r_0` was not slow, took 25-115 % longer to the same verdict
(docs/nonlinear.md, "The profile move").
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from latentforce.inference import particle_model
from latentforce.inference import smoother_move as sm
from latentforce.inference.latent import ObservationDensity, colour
from latentforce.linalg import cho_solve, cholesky, symmetrise

#: folded into a chain's key for the move's random numbers (a run without it draws what it drew before)
PROFILE_STREAM = 0x5046

#: the move's steps in each Gibbs block (``run_pgas(profile_steps=...)``)
PROFILE_STEPS = 4

#: Gauss-Newton iterations with r0 pinned, from the chain's fixed centre (three accepted 0.05-0.1
#: more at 2.5 times the cost a step, and converged no sooner: 104-107 against 99 s, module doc)
ITERATIONS = 1

#: the steps' multiples of the initial prior's Cholesky factor of the internal states, used in turn
#: with :data:`GAUSSIAN_SCALE` (module doc; on the Bouc-Wen record, prior sd 14 N, steps of 3 and
#: 12 N accepted 0.8 and 0.5)
PRIOR_SCALES = (0.25, 0.75)

#: the step's multiple of the Cholesky factor of the linearised posterior's marginal covariance of the
#: internal states' initial values at the fixed centre (2.4: a random walk's optimum in one dimension)
GAUSSIAN_SCALE = 2.4


def applies(pm: particle_model.ParticleModel) -> bool:
    """Whether the system has internal states to move."""
    return pm.internal.size > 0


class _Conditioned:
    """The functional :math:`r_0 = o + C \\varepsilon` under the linearised posterior ``q``: its mean
    ``m``, covariance ``S`` (and its Cholesky factor), and the regression directions ``V``
    (:math:`\\Sigma C S^{-1}`, one per internal state)."""

    def __init__(self, pm, tr, od: ObservationDensity, prep: sm.Prepared, idx):
        lin, gains, eps_hat = prep
        zero = jnp.zeros_like(eps_hat)

        def r0(e):
            return sm.linear_path(pm, lin, colour(tr, e))[0, idx]

        self.off = r0(zero)
        self.C = jax.jacrev(r0)(zero)  # (k, T, nl)

        def pred(e):
            x = sm.linear_path(pm, lin, colour(tr, e))
            return jnp.einsum("tij,tj->ti", lin.H, x - lin.centre) * od.maskf

        p0 = pred(zero)
        # Sigma c = c - (eps_hat(y + J c) - eps_hat(y)): the smoother is affine in the data
        sigma_c = jax.vmap(lambda c: c - (sm._smooth(pm, lin, gains, od.y + pred(c) - p0)[0] - eps_hat))(self.C)
        self.S = symmetrise(jnp.einsum("ktn,jtn->kj", self.C, sigma_c))
        self.L = cholesky(self.S)
        self.V = jnp.einsum("ktn,kj->jtn", sigma_c, cho_solve(self.L, jnp.eye(self.S.shape[0])))
        self.m = self.off + jnp.einsum("ktn,tn->k", self.C, eps_hat)

    def condition(self, eps, r0):
        """``eps`` moved along the regression directions so that its :math:`r_0` is ``r0``."""
        return eps + jnp.einsum("k,ktn->tn", r0 - self.off - jnp.einsum("ktn,tn->k", self.C, eps), self.V)

    def log_density(self, r0):
        """:math:`\\log q(r_0)`."""
        z = jax.scipy.linalg.solve_triangular(self.L, r0 - self.m, lower=True)
        return -0.5 * jnp.sum(z**2) - jnp.sum(jnp.log(jnp.diagonal(self.L))) - 0.5 * z.shape[0] * jnp.log(2 * jnp.pi)


def expanded(pm, tr, od: ObservationDensity, centre):
    """``(prep, cond)``: the linearised model about ``centre`` and its :math:`r_0` functional there."""
    prep = sm.prepare(pm, tr, od, centre)
    return prep, _Conditioned(pm, tr, od, prep, jnp.asarray(pm.internal))


def pinned_centre(pm, tr, od: ObservationDensity, start, r0, iterations: int = ITERATIONS, first=None):
    """Gauss-Newton from ``start`` with the internal states' initial values pinned at ``r0``;
    ``first``: :func:`expanded` at ``start``, where the caller already has it (the move's steps
    share one fixed start)."""

    def shift(prep, cond):
        return sm.linear_path(pm, prep.lin, colour(tr, cond.condition(prep.eps_hat, r0)))

    cen = shift(*(expanded(pm, tr, od, start) if first is None else first))

    def one(c, _):
        return shift(*expanded(pm, tr, od, c)), None

    cen, _ = jax.lax.scan(one, cen, None, length=int(iterations) - 1)
    return cen


def log_target(key, pm, tr, od: ObservationDensity, start, r0, path=None, iterations: int = ITERATIONS, first=None):
    """``(L, path)`` at ``r0`` (module doc): ``path=None`` a proposed point, its path drawn with
    ``key``; else the current point, whose path is ``path`` (its :math:`r_0` must be ``r0``).
    ``first``: :func:`expanded` at ``start`` (:func:`pinned_centre`)."""
    prep, cond = expanded(pm, tr, od, pinned_centre(pm, tr, od, start, r0, iterations, first))
    lin, gains, eps_hat = prep
    _, v = sm._filter_means(pm, lin, gains, od.y)
    base = sm._log_marginal(gains, v) + cond.log_density(r0)
    if path is None:
        eps = cond.condition(sm._draw_eps(key, pm, tr, lin, gains, od, eps_hat), r0)
        lw, path = sm.log_weight(pm, lin, od, colour(tr, eps))
    else:
        lw = sm._log_weight(pm, lin, od, pm.latent(path), path)
    return base + lw, path


def step_factors(pm, cond: _Conditioned) -> Float[Array, "s k k"]:
    """The steps' factors :math:`A_j` (module doc): :data:`PRIOR_SCALES` times the initial prior's
    Cholesky factor of the internal states, then :data:`GAUSSIAN_SCALE` times that of the linearised
    posterior's marginal ``cond`` at the fixed centre."""
    idx = pm.internal
    prior = particle_model._chol(jnp.asarray(pm.mech0_cov)[np.ix_(idx, idx)])
    return jnp.stack([s * prior for s in PRIOR_SCALES] + [GAUSSIAN_SCALE * cond.L])


def profile_move(
    key: Array,
    pm: particle_model.ParticleModel,
    tr: particle_model.Transition,
    od: ObservationDensity,
    centre: Float[Array, "T n"],
    path: Float[Array, "T n"],
    n_steps: int,
    iterations: int = ITERATIONS,
) -> tuple[Float[Array, "T n"], Float[Array, " n_steps"]]:
    """``n_steps`` Metropolis-Hastings steps of the profile move (module doc) from ``path``, about the
    chain's fixed ``centre``, at the transition ``tr``. Returns the path (the input when nothing was
    accepted) and each step's acceptance."""
    idx = jnp.asarray(pm.internal)
    first = expanded(pm, tr, od, centre)  # shared by every step's Gauss-Newton
    factors = step_factors(pm, first[1])
    L0, _ = log_target(None, pm, tr, od, centre, path[0, idx], path, iterations, first)

    def _one(carry, inp):
        L, x = carry
        k, j = inp
        k_step, k_draw, k_acc = jax.random.split(k, 3)
        r0 = x[0, idx] + factors[j % factors.shape[0]] @ jax.random.normal(k_step, idx.shape)
        L_p, x_p = log_target(k_draw, pm, tr, od, centre, r0, None, iterations, first)
        ok = jnp.isfinite(L_p) & (jnp.log(jax.random.uniform(k_acc)) < L_p - L)
        return (jnp.where(ok, L_p, L), jnp.where(ok, x_p, x)), ok

    (_, path), accepted = jax.lax.scan(
        _one, (L0, path), (jax.random.split(key, int(n_steps)), jnp.arange(int(n_steps)))
    )
    return path, accepted
