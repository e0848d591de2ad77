r"""Trajectory moves at fixed hyperparameters that the PGAS sweep cannot make: the low-frequency
move and the residual-preserving move (their derivation: :mod:`latentforce.inference.pgas`)."""

from __future__ import annotations

import copy
import math
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from latentforce.inference import mcmc, particle_model
from latentforce.inference.hyper_moves import mh_step
from latentforce.inference.latent import (
    ObservationDensity,
    _whiten,
    colour,
    observation_log_likelihood,
    predicted_observations,
    whiten,
)
from latentforce.linalg import cho_solve, cholesky, inv, solve, symmetrise


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

    tr: particle_model.Transition
    basis: Float[Array, "T K"]


def lowfreq_coordinates(
    pm: particle_model.ParticleModel, frame: LowFrequencyFrame, path: Float[Array, "T n"]
) -> tuple[Float[Array, " q"], Float[Array, "T nl"]]:
    """``(w, eps_perp)`` of a path (inverse of :func:`lowfreq_path`)."""
    eps = whiten(frame.tr, pm.latent(path))
    W = frame.basis.T @ eps
    return W.ravel(), eps - frame.basis @ W


def lowfreq_path(
    pm: particle_model.ParticleModel, frame: LowFrequencyFrame, eps_perp: Float[Array, "T nl"], w: Float[Array, " q"]
) -> Float[Array, "T n"]:
    """The full path with low-frequency coordinates ``w`` (``colour`` then
    :meth:`~particle_model.ParticleModel.path`)."""
    W = jnp.reshape(w, (frame.basis.shape[1], pm.nl))
    return pm.path(colour(frame.tr, eps_perp + frame.basis @ W))


def lowfreq_log_target(
    pm: particle_model.ParticleModel,
    od: ObservationDensity,
    frame: LowFrequencyFrame,
    eps_perp: Float[Array, "T nf"],
    w: Float[Array, " q"],
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


def lowfreq_init(
    pm: particle_model.ParticleModel, od: ObservationDensity, frame: LowFrequencyFrame, path: Float[Array, "T n"]
) -> mcmc.RWMState:
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


def lowfreq_move(
    key: Array,
    rwm: mcmc.RWMState,
    pm: particle_model.ParticleModel,
    od: ObservationDensity,
    frame: LowFrequencyFrame,
    path: Float[Array, "T n"],
    n_steps: int,
    *,
    adapt: Array,
    step0: Array,
    reshape_steps: Array,
    target: float = 0.25,
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

    return _walk(
        key, rwm, log_target, path, n_steps, adapt=adapt, step0=step0, reshape_steps=reshape_steps, target=target
    )


@jax.tree_util.register_pytree_node_class
class ResidualMove:
    r"""The pieces of the residual-preserving move for one model and record length.

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
    *value* states) is invertible, and, for the force's other states :math:`b`
    (Matérn derivatives), the remainders :math:`h_t = e_{b,t} - K_t e_{u,t}` of
    their innovations :math:`e_t = x_{f,t} - A x_{f,t-1}` (:math:`e_1 = x_{f,1}`)
    after the gains :math:`K_t` of the force prior's Kalman filter observing
    the force values :math:`u` exactly (:func:`_value_gains`; at :math:`t = 1` the
    regression on :math:`u_1` and :math:`w_1` under the whole initial state's prior,
    which for a linear system correlates them). Given :math:`w`
    the force values follow sample by sample,
    :math:`u_t = D_S^{-1}(y_{S,t} - \rho_t - c_S(\mathrm{mech}_t))`, then the
    other states :math:`x_{b,t} = (A x_{f,t-1})_b + K_t e_{u,t} + h_t`, and
    :math:`\mathrm{mech}_{t+1} = \Phi(\mathrm{mech}_t, x_{f,t}) + w_{t+1}`:
    a move in :math:`w` at fixed :math:`\rho` keeps the noise-free prediction
    :math:`c_S(\mathrm{mech}_t) + D_S x_{f,t}` of every sample, observed or
    missing, and only the other channels' residuals change. The map is
    triangular in time with a constant diagonal block, so its Jacobian is
    constant (for any fixed gains; the filter's make the derivatives follow a
    changed force value as the prior expects, through a stable recursion).

    Holding the derivative *states* instead (the first version) is a valid map
    too, but for a smooth force (Matérn-3/2 and up) a changed force value with
    unchanged derivatives is a path the prior all but excludes: on a Duffing
    record seen by an accelerometer alone (Matérn-3/2, T = 256) `pgas` then
    stayed at R-hat 1.9 with the truth inside ±3 sd on 79 % of samples.

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

    A pytree: whether it applies, the channels and states it solves for and the
    sizes are static (decided here, with NumPy, from the concrete ``pm.D``); the
    inverse block, the basis and the scales are leaves.
    """

    def __init__(self, pm: particle_model.ParticleModel, T: int, K: int, noise_sd: Float[Array, " nm"]):
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

    def at(self, pm: particle_model.ParticleModel) -> "ResidualMove":
        """This move for ``pm``, a model of the same structure at other system parameters (traced
        allowed): the inverse force block from ``pm.D`` (the mass enters it), the rest kept."""
        if not self.applies:
            return self
        rm = copy.copy(self)
        rm.Dinv = inv(pm.D[np.ix_(self.rows, self.cols)])
        return rm

    def tree_flatten(self):
        return (
            (self.Dinv, self.basis, self.scale_w, self.scale_0),
            (tuple(int(i) for i in self.cols), tuple(int(i) for i in self.rows), self.applies, self.K, self.dim),
        )

    @classmethod
    def tree_unflatten(cls, aux, children):
        rm = object.__new__(cls)
        cols, rows, rm.applies, rm.K, rm.dim = aux
        rm.cols, rm.rows = np.asarray(cols, dtype=int), np.asarray(rows, dtype=int)
        rm.Dinv, rm.basis, rm.scale_w, rm.scale_0 = children
        return rm

    def delta_w(self, c: Float[Array, " q"]) -> Float[Array, "T nm"]:
        """The change of the within-step noise for coordinates ``c``."""
        C = jnp.reshape(c, (self.K + 1, -1))
        return ((self.basis @ C[: self.K]) * self.scale_w).at[0].set(C[self.K] * self.scale_0)

    def builder(
        self,
        pm: particle_model.ParticleModel,
        od: ObservationDensity,
        tr: particle_model.Transition,
        path: Float[Array, "T n"],
        kinematic: bool = False,
    ):
        """``build(c, at=None) -> (latent, path)``: the path with noise ``w + delta_w(c)``, the
        residuals of ``path`` kept.

        The force's other states follow their innovations' regression on the solved-for
        ones at ``tr`` (class doc), the regression's remainders of ``path`` kept.
        ``at = (pm_b, tr_b)``: the coordinates are those of ``path`` under ``pm`` and ``tr``,
        the path is rebuilt under ``pm_b`` and ``tr_b`` (the same structure at other system
        parameters, the same hyperparameters: :mod:`latentforce.inference.system_moves`).
        ``kinematic``: the displacements and velocities of ``path`` are held too, in place of
        their within-step noise (which then follows: the rebuilt latent's); the internal states
        keep theirs (:mod:`latentforce.inference.system_moves`).
        """
        rows, cols = self.rows, self.cols
        lay = pm.latent_layout
        nfx = pm.nfx
        b = np.setdiff1d(np.arange(nfx), cols)  # the force's other states: they follow
        g0 = pm.latent(path)
        xf0, w0 = g0[:, lay.force], g0[:, lay.noise]
        # y_S,t - rho_t is the path's own noise-free prediction on S: the map keeps it,
        # whether or not y_S,t was observed
        target = predicted_observations(pm, path)[:, rows]
        mech_held = path[:, pm.layout.mech]
        kin = jnp.asarray(np.arange(pm.nm) < 2 * pm.ndof)  # the displacements and velocities
        # scatter matrices (no indexed updates inside the scan: batched over chains
        # they were slow on CPU)
        to_u = jnp.zeros((nfx, len(cols))).at[cols, jnp.arange(len(cols))].set(1.0)
        to_b = jnp.zeros((nfx, len(b))).at[b, jnp.arange(len(b))].set(1.0)
        Af = tr.A[lay.force, lay.force]  # the force block's own transition (it does not see w)
        K = _value_gains(tr, lay.force, cols, b, path.shape[0])
        # at t = 1 the derivatives' regression on the force values *and* the initial offset w_1
        # under the whole initial state's prior (a linear system's joint stationary start
        # correlates them with the mechanical states): one step, no recursion to destabilise
        idx = np.arange(pm.nl)
        a1 = np.concatenate([idx[lay.force][cols], idx[lay.noise]])
        b1 = idx[lay.force][b]
        K1 = _regression(tr.Pinf, a1, b1)
        # the remainders h_t = e_b,t - K_t e_u,t of the path's force innovations (e_1 = g_1)
        e0 = jnp.concatenate([xf0[:1], xf0[1:] - xf0[:-1] @ Af.T])
        h = e0[:, b] - jnp.einsum("tbu,tu->tb", K, e0[:, cols])
        h = h.at[0].set(g0[0, b1] - K1 @ g0[0, a1]) if len(b) else h

        def build(c, at=None):
            # the map at the rebuilding model: the force block (hence A_f and the gains K_t) is the
            # hyperparameters' and the same; the first step's regression may see other system
            # parameters (a linear part's stationary start)
            pm_b, tr_b = (pm, tr) if at is None else at
            Dinv = self.Dinv if at is None else self.at(pm_b).Dinv
            K1_b = K1 if at is None else _regression(tr_b.Pinf, a1, b1)

            def _values(mech, target_t):
                # products as broadcast-multiply-sums: XLA fuses them (a dot per step,
                # batched over chains, cost ten times the whole step on CPU)
                return particle_model._mv1(Dinv, target_t - pm_b.offset(mech)[rows])

            def _state(mech, target_t, K_t, h_t, pred):
                u = _values(mech, target_t)
                if len(b) == 0:
                    return particle_model._mv1(to_u, u)
                x_b = pred[b] + particle_model._mv1(K_t, u - pred[cols]) + h_t
                return particle_model._mv1(to_u, u) + particle_model._mv1(to_b, x_b)

            def _first(mech1, w1):
                u = _values(mech1, target[0])
                if len(b) == 0:
                    return particle_model._mv1(to_u, u)
                x_b = particle_model._mv1(K1_b, jnp.concatenate([u, w1])) + h[0]
                return particle_model._mv1(to_u, u) + particle_model._mv1(to_b, x_b)

            w = w0 + self.delta_w(c)
            mech1 = pm_b.mech0_mean + w[0]
            if kinematic:
                mech1 = jnp.where(kin, mech_held[0], mech1)
            xf1 = _first(mech1, mech1 - pm_b.mech0_mean)

            def _step(carry, inp):
                mech, xf = carry
                target_n, K_n, h_n, w_n, held_n = inp
                pred_n = pm_b.phi(mech, xf)
                mech_n = pred_n + w_n
                if kinematic:
                    mech_n = jnp.where(kin, held_n, mech_n)
                xf_n = _state(mech_n, target_n, K_n, h_n, particle_model._mv1(Af, xf))
                # one stacked output: two (mech and xf), batched over chains, made XLA's
                # CPU loop several times slower
                return (mech_n, xf_n), jnp.concatenate([mech_n, xf_n, mech_n - pred_n])

            _, rows_ = jax.lax.scan(_step, (mech1, xf1), (target[1:], K[1:], h[1:], w[1:], mech_held[1:]))
            nm_, nx_ = pm.nm, pm.nfx
            new_path = jnp.concatenate([jnp.concatenate([mech1, xf1])[None], rows_[:, : nm_ + nx_]])
            if kinematic:  # the within-step noise that the held kinematics imply
                w = jnp.concatenate([(mech1 - pm_b.mech0_mean)[None], rows_[:, nm_ + nx_ :]])
            return jnp.concatenate([new_path[:, pm.layout.force_states], w], axis=1), new_path

        return build


def _regression(S: Float[Array, "n n"], a, b) -> Float[Array, "nb na"]:
    r""":math:`S_{ba} S_{aa}^{-1}`, a Gaussian's regression of its ``b`` block on its ``a`` block.

    On the correlation scale (the latent's variances span ~15 orders of magnitude),
    with a ridge of 1e-12 (as for :func:`_value_gains`, any fixed matrix keeps the
    move exact).
    """
    if len(b) == 0:
        return jnp.zeros((0, len(a)))
    d = jnp.sqrt(jnp.diagonal(S))
    d = jnp.where(d > 0.0, d, 1.0)
    C = S / (d[:, None] * d[None, :])
    Gc = solve(C[np.ix_(a, a)] + 1e-12 * jnp.eye(len(a)), C[np.ix_(a, b)]).T
    return Gc * d[b][:, None] / d[a][None, :]


def _value_gains(tr: particle_model.Transition, force: slice, cols, b, T: int) -> Float[Array, "T nb nu"]:
    r"""Gains :math:`K_t` of the force's other states ``b`` on its values ``cols``, :math:`t = 1..T`.

    ``cols`` and ``b`` index the force states (the latent's ``force`` slice).
    The Kalman filter of the force's prior (its block of ``tr``: :math:`x_{f,1}
    \sim N(0, P_\infty)`, :math:`x_{f,t} = A x_{f,t-1} + q_t`) observing the
    force values exactly at every step: :math:`K_t = P_{bu} P_{uu}^{-1}` of its
    predicted covariance. :math:`x_{b,t} = (A x_{f,t-1})_b + K_t(u_t - (A
    x_{f,t-1})_u) + h_t` is then a stable recursion (closed-loop spectral radius
    0.27 / 0.43 / 0.54 for Matérn-3/2 / 5/2 / 7/2 at :math:`\lambda\Delta t \le
    0.2`). The one-step regression on :math:`Q` alone (:math:`P_{t-1}` taken as
    exact) has radius 0.5, 2.1 and 5.9 on the force values (unstable from 5/2 on);
    regressed on the values and :math:`w` together it rebuilt an unchanged Matérn-3/2
    path into 1e33 from round-off over 60 samples. Computed on the correlation scale with a ridge of
    1e-12: any fixed gains give the move a constant Jacobian, so the ridge costs no
    exactness.
    """
    if len(b) == 0:
        return jnp.zeros((T, 0, len(cols)))
    Af, Qf, P1 = tr.A[force, force], tr.Q[force, force], tr.Pinf[force, force]
    every = np.arange(len(cols) + len(b))

    def gain_and_update(P):
        # conditioning on the values: the rows of every state on them, then the update
        Kc = _regression(P, cols, every)
        return Kc[b], symmetrise(P - Kc @ P[cols, :])

    K1, Pf1 = gain_and_update(P1)

    def _step(Pf, _):
        K, Pf = gain_and_update(Af @ Pf @ Af.T + Qf)
        return Pf, K

    _, Ks = jax.lax.scan(_step, Pf1, None, length=T - 1)
    return jnp.concatenate([K1[None], Ks])


def residual_log_target(
    tr: particle_model.Transition,
    pm: particle_model.ParticleModel,
    od: ObservationDensity,
    build,
    c: Float[Array, " q"],
    cP=None,
    cQ=None,
) -> tuple[Float[Array, ""], Float[Array, "T n"]]:
    r"""Log target of the residual-preserving move up to a constant, and the path.

    :math:`-\tfrac12|\varepsilon(c)|^2 + \log p(y \mid x_{1:T}(c))`, :math:`\varepsilon`
    the latent's whitened innovations (its prior density up to a constant);
    the map's Jacobian is constant (:class:`ResidualMove`).
    """
    cP = particle_model._chol(tr.Pinf) if cP is None else cP
    cQ = particle_model._chol(tr.Q) if cQ is None else cQ
    g, path = build(c)
    return -0.5 * jnp.sum(_whiten(tr, g, cP, cQ) ** 2) + observation_log_likelihood(pm, od, path), path


def gauss_newton_covariance(
    pm: particle_model.ParticleModel,
    od: ObservationDensity,
    tr: particle_model.Transition,
    build: Callable,
    coordinates: Callable,
    q: int,
    cP,
    cQ,
) -> Float[Array, "q q"]:
    r""":math:`(J_\varepsilon^\top J_\varepsilon + J_y^\top R^{-1} J_y)^{-1}` at :math:`a = 0`: the Jacobians
    of the whitened latent and of the predicted observations of the path ``build(coordinates(a))``
    (a :meth:`ResidualMove.builder`'s map) with respect to ``q`` coordinates :math:`a`."""

    def features(a):
        g, x = build(coordinates(a))
        return _whiten(tr, g, cP, cQ).ravel(), predicted_observations(pm, x) * od.maskf

    Je, Jy = jax.jacfwd(features)(jnp.zeros(q))
    prec = symmetrise(Je.T @ Je + jnp.einsum("tim,tij,tjn->mn", Jy, od.Rinv, Jy))
    return symmetrise(cho_solve(cholesky(prec), jnp.eye(q)))


def residual_init(
    rm: ResidualMove,
    pm: particle_model.ParticleModel,
    od: ObservationDensity,
    tr: particle_model.Transition,
    path: Float[Array, "T n"],
) -> mcmc.RWMState:
    r"""Adaptation state of the residual-preserving walk, its shape a Gauss-Newton covariance at ``path``.

    :math:`(2.38^2/q)(J_\varepsilon^\top J_\varepsilon + J_y^\top R^{-1} J_y)^{-1}`, the
    Jacobians of the whitened innovations and of the predicted observations
    with respect to the :math:`q` coordinates at ``path`` (the exact
    posterior covariance of the coordinates for a linear model).
    """
    build = rm.builder(pm, od, tr, path)
    q = rm.dim
    cP, cQ = particle_model._chol(tr.Pinf), particle_model._chol(tr.Q)
    cov = gauss_newton_covariance(pm, od, tr, build, lambda c: c, q, cP, cQ)
    chol = cholesky(cov) * (2.38 / math.sqrt(q))
    return mcmc.RWMState(jnp.zeros(q), jnp.zeros(()), jnp.zeros(()), chol, jnp.zeros(q), cov, jnp.zeros(()))


def residual_move(
    key: Array,
    rwm: mcmc.RWMState,
    rm: ResidualMove,
    pm: particle_model.ParticleModel,
    od: ObservationDensity,
    tr: particle_model.Transition,
    path: Float[Array, "T n"],
    n_steps: int,
    *,
    adapt: Array,
    target: float = 0.25,
) -> tuple[mcmc.RWMState, Float[Array, "T n"], Float[Array, " n_steps"]]:
    r"""``n_steps`` residual-preserving Metropolis steps (:class:`ResidualMove`) at fixed :math:`\theta`.

    The coordinates are re-origined at ``path`` (``c = 0``); the proposal
    :math:`c' = c + s L \xi` keeps ``rwm``'s shape :math:`L`, and its scale
    :math:`s` follows Robbins-Monro towards ``target`` only where ``adapt``
    (the frozen kernel is a plain Metropolis kernel). Returns the walk state,
    the new path (the input path bit-for-bit when nothing was accepted) and
    the acceptances.
    """
    build = rm.builder(pm, od, tr, path)
    cP, cQ = particle_model._chol(tr.Pinf), particle_model._chol(tr.Q)

    def log_target(c):
        return residual_log_target(tr, pm, od, build, c, cP, cQ)

    ld0 = -0.5 * jnp.sum(_whiten(tr, pm.latent(path), cP, cQ) ** 2) + observation_log_likelihood(pm, od, path)
    rwm = rwm._replace(x=jnp.zeros_like(rwm.x), logdensity=ld0)
    return _walk(
        key,
        rwm,
        log_target,
        path,
        n_steps,
        adapt=adapt,
        step0=jnp.zeros((), jnp.int32),
        reshape_steps=jnp.asarray((-1,)),
        target=target,
    )


def _walk(key, rwm: mcmc.RWMState, log_target: Callable, path, n_steps: int, *, adapt, step0, reshape_steps, target):
    """``n_steps`` of :func:`mh_step` whose target also returns the path (kept bit-for-bit on rejection)."""

    def _one(carry, inp):
        r, x = carry
        k, s = inp
        r, info, x = mh_step(
            k, r, log_target, adapt=adapt, reshape=jnp.any(step0 + s == reshape_steps), target=target, aux=x
        )
        return (r, x), info.accepted

    (rwm, path), accs = jax.lax.scan(_one, (rwm, path), (jax.random.split(key, n_steps), jnp.arange(n_steps)))
    return rwm, path, accs
