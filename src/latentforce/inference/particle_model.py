r"""The sampler's discrete model: the latent path, its transition and the mechanical states.

:class:`ParticleModel` is the static view of a
:class:`~latentforce.models.LatentForceModel` that the particle methods
(:mod:`latentforce.inference.smc`), the path moves and the Kalman-based
samplers share: the re-parametrised Markov latent (force states and the
mechanical states' within-step noise), its exact linear-Gaussian
:class:`Transition` at given hyperparameters, the one-step map of the
mechanical states and its linearisation (:meth:`ParticleModel.linear_discrete`).

The model (re-parametrised so that it has no degenerate transition)
-------------------------------------------------------------------
The state is :math:`x_t = (\mathrm{mech}_t, x_{f,t})` with
:math:`\mathrm{mech} = (z, \dot z, r)` (``2 ndof`` plus the system's internal, hysteretic
states :math:`r` if any: their within-step noise is :func:`internal_noise`) and the force states
:math:`x_f` (``nforce * kernel.dim``). In the model of Rogers et al.
(Vibration 2020, Eq. 18-20) discretised by Euler-Maruyama the mechanical
states get no process noise, so the transition density of :math:`x_t` is
singular and the ancestor weights of Eq. (22) degenerate. That is an
artefact of the discretisation: over a step the force varies, and the
mechanical states' response to that variation is random. Its exact
covariance is tiny but not zero (Duffing case: about 1e-4 m/s in velocity,
2e-8 m in displacement per step), and leaving it out makes the mechanical
states' posterior too narrow against a continuous-time truth.

We take as the Markov latent :math:`g_t = (x_{f,t}, w_t)`: the force states
and the mechanical states' within-step noise, a linear-Gaussian process

.. math:: g_1 \sim N(0, \mathrm{diag}(P_{\infty,f}, P_0)), \qquad
          g_t = A g_{t-1} + q_t,\; q_t \sim N(0, Q),\qquad
          A = \begin{pmatrix} A_f & 0 \\ E & 0 \end{pmatrix},

where :math:`(A_f, Q)` is the exact (Van Loan) discretisation of the force
SDE stacked on the system linearised about rest, with :math:`Q` the joint
covariance of the force-state innovation and the mechanical response to it
(:meth:`ParticleModel.transition`). The mechanical states are a
deterministic function of the latent path,

.. math:: \mathrm{mech}_1 = m_0 + w_1, \qquad
          \mathrm{mech}_t = \Phi(\mathrm{mech}_{t-1}, x_{f,t-1}) + w_t,

:math:`\Phi` one RK4 (or Euler) step of :math:`M\ddot z + h(z,\dot z) = B u`
with the force held as the Taylor polynomial of the Matérn derivative
states (:class:`ParticleModel.phi`, independent of the hyperparameters), and
:math:`E x_{f,t-1}` the mean correction from that hold to the force's
conditional mean within the step. For linear systems this *is* the exact
discretisation of the continuous model up to RK4's error in the homogeneous
step (tested); for nonlinear ones the within-step noise is that of the
linearised system, an error of relative order :math:`(\Delta t)^2` times the
change of stiffness. Every sensor is linear in :math:`x_{f,t}` given
:math:`\mathrm{mech}_t`:

.. math:: y_t = c(\mathrm{mech}_t) + D x_{f,t} + v_t,\qquad v_t \sim N(0, R).

The model is non-Markovian in :math:`g`; conditional SMC with ancestor
sampling for non-Markovian models is Lindsten, Jordan & Schön (2014, JMLR,
Sec. 4-5).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from latentforce.compile import jit
from latentforce.kernels import KernelParams, Matern, n_terms
from latentforce.linalg import cholesky, inv, solve_lyapunov, symmetrise, van_loan

#: Jitter added to covariances before a Cholesky factorisation, relative to
#: each diagonal entry: keeps Q of smooth (high-order) Matérn kernels and
#: the proposal covariance Q - K S K^T (rank-deficient up to roundoff when a
#: sensor sees a force state almost noise-free) factorisable.
JITTER = 1e-10

DISCRETISATIONS = ("rk4", "euler")


# ---------------------------------------------------------------------------
# The model in the form the particle methods need
# ---------------------------------------------------------------------------
class Transition(NamedTuple):
    r"""Linear-Gaussian transition of the latent :math:`g_t = (x_{f,t}, w_t)` at one value of the hyperparameters.

    :math:`g_1 \sim N(0, P_\infty)`, :math:`g_t = A g_{t-1} + q_t`,
    :math:`q_t \sim N(0, Q)` (``A`` acts on the force block only; module doc).
    """

    A: Float[Array, "nl nl"]
    Q: Float[Array, "nl nl"]
    Pinf: Float[Array, "nl nl"]


@jax.tree_util.register_pytree_node_class
class ParticleModel:
    r"""The sampler's view of a :class:`~latentforce.models.LatentForceModel` for particle methods.

    Holds the model, the fixed system/sensor parameters ``params``, ``dt``,
    the discretisation, the channels' noise covariance ``R`` and the prior of
    the initial state; everything that depends on the GP hyperparameters is
    computed by :meth:`transition` from a traced ``(variance, lengthscale)``.

    A pytree: its numbers (``params``, ``R`` and what is derived from them)
    are leaves, its structure (the model, ``dt``, the discretisation, whether
    the start is the stationary one) its tree definition, so a compiled
    program that takes it as an argument serves every parameter value of one
    structure (:mod:`latentforce.inference.pgas`). It can be built from traced
    ``params`` inside a program; there ``R`` must come from ``params`` (every
    :meth:`~latentforce.models.LatentForceModel.noise_params`) or the ``R``
    argument, not from the sensors.

    Initial state. By default (``initial=None``) a linear system's whole first
    state (mechanical and force states together) has the system's stationary
    distribution at the current hyperparameters: zero mean and the Lyapunov
    solution :math:`F P + P F^T + W = 0`, the correlations between the
    mechanical and the force states included: exactly the stationary start of
    the Kalman methods (with the force states alone stationary and the
    mechanical ones independent of them, as before, a linear SDOF's posterior
    mean differed from the exact smoother's by an NMSE of 2.7 %). A nonlinear
    system keeps the model's near-rest default
    (:meth:`~latentforce.models.LatentForceModel.default_initial`), its force
    states stationary and independent; the linearised stationary spread was
    measured too wide for the path moves' linearisations (notes, issue on
    nonlinear posteriors). ``initial = (mean, sd)`` or ``(mean, cov)`` (a
    ``(nm, nm)`` matrix) of the mechanical states instead: the force states
    then start at their stationary GP distribution, independent of the given
    mechanical state. ``mech0_mean`` and ``mech0_cov`` are the mechanical block
    (for a linear system at the hyperparameters in ``params``; a scale for the
    path moves).
    """

    #: the numbers (pytree leaves: arguments of a compiled program that takes the model)
    _LEAVES = ("params", "R", "_Minv", "_B", "D", "D_latent", "_phi_force", "_mech0_user", "mech0_mean", "mech0_cov")

    def __init__(self, model, params: dict, dt: float, discretisation: str = "rk4", initial=None, R=None):
        if discretisation not in DISCRETISATIONS:
            raise ValueError(f"unknown discretisation {discretisation!r}; valid: {DISCRETISATIONS}")
        # linear systems: the joint stationary start (class doc); nonlinear ones: the model's default
        self._structure(model, float(dt), discretisation, initial is None and bool(model.system.is_linear))
        self.params = {k: (jnp.asarray(v, dtype=float)) for k, v in params.items()}
        # R: the channels' noise covariance, by default an inferred (or a caller's) noise level in
        # params, else the sensor's; built inside a compiled program, the caller passes every noise
        # level in params (model.noise_params()) or R
        self.R = jnp.asarray(model.noise_covariance(self.params) if R is None else R, dtype=float)
        self._Minv = inv(model.system.mass(self.params))
        self._B = model.system.input_matrix()
        self.D = self.D_latent = self._phi_force = self._mech0_user = self.mech0_mean = self.mech0_cov = None
        (self.D, self.D_latent, self._phi_force, self._mech0_user, self.mech0_mean, self.mech0_cov) = _derived_program(
            self, initial
        )

    def with_params(self, new: dict) -> "ParticleModel":
        """This model with the system parameters in ``new`` replaced (traced values allowed: the
        sampler's per-chain model when system parameters are inferred). The same structure, so
        one compiled program serves both: the same noise covariance ``R`` and the same prior of
        the initial mechanical state (a linear system's stationary start is recomputed at the
        new parameters, as that start is defined)."""
        initial = None if self.stationary_start else self._mech0_user
        return ParticleModel(self.model, {**self.params, **new}, self.dt, self.discretisation, initial, R=self.R)

    def _structure(self, model, dt: float, discretisation: str, stationary_start: bool) -> None:
        """The static attributes (the pytree's tree definition): sizes and switches of ``model``."""
        self.model, self.dt, self.discretisation = model, dt, discretisation
        self.stationary_start = stationary_start
        # where each part sits (models.StateLayout, models.LatentLayout); the sizes by name
        self.layout, self.latent_layout = model.layout, model.latent_layout
        self.nm = self.layout.n_mech
        self.ndof = model.ndof
        self.nforce = model.nforce
        self.kdim = model.kernel.dim
        self.nfx = self.layout.n_force_states
        #: the internal (hysteretic) states' columns in a path, after the displacements and velocities
        self.internal = np.arange(2 * self.ndof, self.nm)
        self.nl = self.latent_layout.n
        self.n_state = model.n_state
        self.n_obs = model.n_obs
        self.is_linear = bool(model.system.is_linear)
        # Matérn: the force held as the Taylor polynomial of its derivative states;
        # composite kernels: zero-order hold of u = H_f x_f
        self._taylor = isinstance(model.kernel, Matern)

    # ----- the model as a pytree: numbers are leaves, structure is static ----
    def tree_flatten(self):
        return (
            tuple(getattr(self, n) for n in self._LEAVES),
            (self.model, self.dt, self.discretisation, self.stationary_start),
        )

    @classmethod
    def tree_unflatten(cls, aux, children):
        pm = object.__new__(cls)
        pm._structure(*aux)
        for n, v in zip(cls._LEAVES, children):
            setattr(pm, n, v)
        return pm

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
        return self.model.with_hyper(self.params, _unit(self.model), _unit(self.model))

    def acceleration(self, z, v, u, r=None):
        r""":math:`\ddot z = M^{-1}(B u - h(z, \dot z, r))`, as ``system.acceleration`` but with
        :math:`M^{-1}` precomputed: a batched ``linalg.solve`` per particle and RK4
        stage dominated the sweep's cost on CPU."""
        rhs = _mv1(self._B, u) - self.model.system.restoring(self.params, z, v, r)
        return _mv1(self._Minv, rhs)

    def _rates(self, z, v, r, u):
        """``(zdot, vdot, rdot)`` of one mechanical state under force ``u``."""
        return v, self.acceleration(z, v, u, r), self.model.system.internal_rate(self.params, z, v, r)

    def _rhs(self, mech, u):
        return jnp.concatenate(self._rates(*self.layout.split_mech(mech), u))

    def state_step(self, tr: "Transition", x):
        r"""The state's mean one step on, :math:`f(x) = (\Phi(\mathrm{mech}, x_f) + E x_f,\; A_f x_f)`
        (the mechanical step's noise held at zero)."""
        L, G = self.layout, self.latent_layout
        mech, xf = x[L.mech], x[L.force_states]
        return jnp.concatenate([self.phi(mech, xf) + tr.A[G.noise, G.force] @ xf, tr.A[G.force, G.force] @ xf])

    def readout(self, x):
        """The sensors' noise-free values of state ``x`` in the sampler's observation form:
        ``offset(mech) + D x_f``."""
        return self.offset(x[self.layout.mech]) + self.D @ x[self.layout.force_states]

    def phi(self, mech: Float[Array, " nm"], xf: Float[Array, " nf"]) -> Float[Array, " nm"]:
        r""":math:`\Phi(\mathrm{mech}_{t-1}, x_{f,t-1})`: one RK4 (or Euler) step of the mechanical ODE
        (``system.substeps`` steps of ``dt / substeps``)."""
        return self._step(self._rates, self.layout.split_mech(mech), xf, jnp.concatenate)

    def phi_particles(self, mech: Float[Array, "N nm"], xf: Float[Array, "N nf"]) -> Float[Array, "N nm"]:
        """:meth:`phi` for a batch of particles, with displacement, velocity (and internal states)
        carried as separate arrays through the stages: XLA then fuses the whole step into one
        loop (stacking ``(z, v)`` at every stage made it materialise each stage)."""
        rates = jax.vmap(self._rates)
        return self._step(
            rates, self.layout.split_mech(mech), xf, lambda parts: jnp.concatenate(parts, axis=-1), jax.vmap
        )

    def _step(self, rates, parts, xf, join, vmap=None):
        """RK4 (or Euler) over ``system.substeps`` substeps of the state ``parts = (z, v, r)``, the
        force held as :meth:`_hold` at each stage's time into the step (several substeps: a
        ``lax.scan``, so that the compiled sweep does not grow with their number; unrolled, eight
        substeps took 22 s to compile the model's derived quantities against 2 s for one)."""
        n = self.model.system.substeps
        h = self.dt / n
        hold = (lambda s: jax.vmap(self._hold, (0, None))(xf, s)) if vmap else (lambda s: self._hold(xf, s))
        add = lambda x, c, k: tuple(a + c * b for a, b in zip(x, k))

        def substep(parts, s0):
            if self.discretisation == "euler":
                return add(parts, h, rates(*parts, hold(s0)))
            k1 = rates(*parts, hold(s0))
            k2 = rates(*add(parts, 0.5 * h, k1), hold(s0 + 0.5 * h))
            k3 = rates(*add(parts, 0.5 * h, k2), hold(s0 + 0.5 * h))
            k4 = rates(*add(parts, h, k3), hold(s0 + h))
            return tuple(
                a + (h / 6.0) * (b1 + 2.0 * b2 + 2.0 * b3 + b4) for a, b1, b2, b3, b4 in zip(parts, k1, k2, k3, k4)
            )

        if n == 1:
            return join(substep(parts, 0.0))
        parts, _ = jax.lax.scan(lambda c, s0: (substep(c, s0), None), parts, h * jnp.arange(n))
        return join(parts)

    def _observe(self, mech, xf):
        r"""Noise-free observation ``c(mech) + D x_f``; equals ``model.observe`` (tested), written
        out with the precomputed :math:`M^{-1}` for speed."""
        z, v, r = self.layout.split_mech(mech)
        return self.model.sensor_readout(
            z, v, lambda: self.acceleration(z, v, self._hold(xf, 0.0), r), lambda: self._hold(xf, 0.0)
        )

    def offset(self, mech: Float[Array, " nm"]) -> Float[Array, " d"]:
        """:math:`c(\\mathrm{mech})`: the observation with the force states at zero."""
        return self._observe(mech, jnp.zeros(self.nfx))

    def force_transition(self, variance, lengthscale):
        """``(A_f, Q_f, Pinf_f)`` of the force states alone (block diagonal over forces)."""
        kp = KernelParams(jnp.asarray(variance, dtype=float), jnp.asarray(lengthscale, dtype=float))
        A, Q = self.model.kernel.discretise(kp, self.dt)
        Pinf = self.model.kernel.state_space(kp).Pinf
        eye = jnp.eye(self.nforce)
        return jnp.kron(eye, A), symmetrise(jnp.kron(eye, Q)), symmetrise(jnp.kron(eye, Pinf))

    def transition(self, variance, lengthscale) -> Transition:
        r"""The latent's transition at :math:`\theta = (\sigma_f^2, \ell)` (module doc, "within-step noise").

        The joint covariance of the force-state innovation and the mechanical
        states' within-step response to it is the exact (Van Loan) one of the
        system linearised about rest; the force block is the kernel's own
        (robust for coarse steps). ``E`` corrects the mean of :math:`w_t` for
        the difference between the conditional-mean force within the step and
        :meth:`phi`'s Taylor hold, so that for linear systems the model is the
        exact discretisation up to the RK4 error of the homogeneous step.
        """
        L, G = self.layout, self.latent_layout
        A_f, Q_f, P_f = self.force_transition(variance, lengthscale)
        prm = self.model.with_hyper(self.params, variance, lengthscale)
        F, W = self.model.continuous(prm, linear_part=True)
        A, Q = van_loan(F, W, self.dt)
        state = np.arange(L.n_state)
        perm = np.r_[state[L.force_states], state[L.mech]]  # the state's entries in the latent's (x_f, mech) order
        Qg = Q[perm][:, perm].at[G.force, G.force].set(Q_f)
        if L.n_internal:  # the hysteretic states' independent within-step noise
            iz = self.nfx + np.arange(L.n_state)[L.displacement]
            ir = self.nfx + np.arange(L.n_state)[L.internal]
            Qg = Qg.at[np.ix_(ir, ir)].add(internal_noise(self.model, prm, Qg[np.ix_(iz, iz)]))
        E = A[L.mech, L.force_states] - self._phi_force
        Ag = jnp.zeros((self.nl, self.nl)).at[G.force, G.force].set(A_f).at[G.noise, G.force].set(E)
        if self.stationary_start:
            # the joint stationary covariance (class doc), force block the kernel's own
            Pg = solve_lyapunov(F, W)[perm][:, perm].at[G.force, G.force].set(P_f)
        else:
            Pg = jax.scipy.linalg.block_diag(P_f, self._mech0_user[1])
        return Transition(Ag, symmetrise(Qg), symmetrise(Pg))

    def initial_mech(self, initial=None):
        """``(mean, cov)`` of the initial mechanical state: ``initial = (mean, sd)`` or ``(mean, cov)``,
        else the mechanical block of the model's default start (stationary for a linear system,
        near rest for a nonlinear one) at the hyperparameters in ``params``."""
        if initial is not None:
            mean, spread = initial
            mean = jnp.broadcast_to(jnp.asarray(mean, dtype=float), (self.nm,))
            spread = jnp.asarray(spread, dtype=float)
            if spread.ndim == 2:
                return mean, symmetrise(spread)
            return mean, jnp.diag(jnp.broadcast_to(spread, (self.nm,)) ** 2)
        if self.is_linear:
            _, P0 = self.model.stationary_initial(self.params)
            return jnp.zeros(self.nm), symmetrise(P0[self.layout.mech, self.layout.mech])
        # at the force hyperparameters in params (the CLI's start, estimate_particles._mechanical_initial);
        # unit ones only where params has none: the near-rest spread scales with the force's variance
        unit = self.model.with_hyper({}, _unit(self.model), _unit(self.model))
        m0, P0 = self.model.default_initial({**unit, **self.params})
        return m0[self.layout.mech], symmetrise(P0[self.layout.mech, self.layout.mech])

    def path(self, g: Float[Array, "T nl"]) -> Float[Array, "T n"]:
        r"""The state path ``(mech, x_f)`` of a latent path :math:`g = (x_f, w)`:
        :math:`\mathrm{mech}_1 = m_0 + w_1`, :math:`\mathrm{mech}_t = \Phi(\mathrm{mech}_{t-1}, x_{f,t-1}) + w_t`."""
        xf, w = g[:, self.latent_layout.force], g[:, self.latent_layout.noise]
        mech1 = self.mech0_mean + w[0]

        def _step(mech, inputs):
            xf_prev, w_t = inputs
            nxt = self.phi(mech, xf_prev) + w_t
            return nxt, nxt

        _, mechs = jax.lax.scan(_step, mech1, (xf[:-1], w[1:]))
        return jnp.concatenate([jnp.concatenate([mech1[None], mechs]), xf], axis=1)

    def latent(self, path: Float[Array, "T n"]) -> Float[Array, "T nl"]:
        """The latent path of a state path (inverse of :meth:`path`, vectorised over time)."""
        mech, xf = path[:, self.layout.mech], path[:, self.layout.force_states]
        pred = self.phi_particles(mech[:-1], xf[:-1])
        w = jnp.concatenate([(mech[0] - self.mech0_mean)[None], mech[1:] - pred])
        return jnp.concatenate([xf, w], axis=1)

    def linear_discrete(self, tr: Transition):
        """The sampler's discrete model of the state ``(mech, x_f)`` as a linear-Gaussian one.

        Returns ``(A_d, Q_d, H, m_1, P_1)``: ``x_t = A_d x_{t-1} + q``,
        ``q ~ N(0, Q_d)``, ``y = H x + v``, ``x_1 ~ N(m_1, P_1)``: exact for
        linear systems (tests against the Kalman filter), the linearisation
        about rest otherwise; the extended Kalman smoother uses its pieces.
        """
        L, G = self.layout, self.latent_layout
        latent = np.arange(G.n)
        perm = np.r_[latent[G.noise], latent[G.force]]  # the latent's entries in the state's (mech, x_f) order
        x0 = jnp.zeros(self.n_state)
        A_d = jax.jacfwd(lambda x: self.state_step(tr, x))(x0)
        H = jax.jacfwd(lambda x: self._observe(x[L.mech], x[L.force_states]))(x0)
        m1 = jnp.concatenate([self.mech0_mean, jnp.zeros(self.nfx)])
        return A_d, tr.Q[perm][:, perm], H, m1, tr.Pinf[perm][:, perm]


def _unit(model):
    """Unit force hyperparameters (a scalar, or one per term of a kernel sum)."""
    n = n_terms(model.kernel)
    return 1.0 if n == 1 else jnp.ones(n)


def internal_noise(model, params: dict, Q_zz):
    r"""The independent within-step noise of the internal (hysteretic) states, a diagonal matrix.

    About rest an internal state's within-step response is exactly :math:`R_z` times the
    displacement's (:math:`r - R_z z` is conserved by the linear part): a direction of zero
    variance. Along a hysteresis loop the tangent :math:`\partial \dot r / \partial \dot z`
    moves away from :math:`R_z` (Bouc-Wen benchmark: by 30-100 % of alpha), so the true response
    leaves that direction by :math:`(\partial \dot r/\partial \dot z - R_z)\, w_z`. The
    independent part is that deviation's variance, :math:`\kappa^2 R_z Q_{zz} R_z^T`, with
    :math:`\kappa` the system's relative tangent deviation at twice the stationary sd of
    :math:`r` under the linear part (``system.tangent_deviation``, capped at
    ``systems.TANGENT_DEVIATION_CAP``): zero without hysteresis, so that the model is then exactly
    the linear system's (tested against the Kalman smoother)."""
    S, Rz = model.system.internal_linear(params)
    _, P = model.stationary_initial(params, linear_part=True)
    r_sd = jnp.sqrt(jnp.clip(jnp.diagonal(P)[model.layout.internal], 0.0))
    kappa = model.system.tangent_deviation(params, r_sd)
    return jnp.diag(kappa**2 * jnp.diagonal(Rz @ Q_zz @ Rz.T))


@jit
def _derived_program(pm: ParticleModel, initial):
    """``(D, D_latent, phi_force, mech0_user, mech0_mean, mech0_cov)`` of a partly built ``pm``: one
    compiled program for every model of one structure (op by op, each primitive compiled on its own);
    inlined where ``pm`` is built inside another program (:func:`latentforce.compile.jit`)."""
    zero_mech, zero_f = jnp.zeros(pm.nm), jnp.zeros(pm.nfx)
    D = jax.jacfwd(lambda xf: pm.model.observe(pm._gp_dummy(), jnp.concatenate([zero_mech, xf])))(zero_f)
    # Observation Jacobian in the latent (x_f, w) about rest: the proposal's linearisation
    D_latent = jnp.concatenate([D, jax.jacfwd(pm.offset)(zero_mech)], axis=1)
    # d Phi / d x_f of the step's hold (the linear part's force response of phi)
    phi_force = jax.jacfwd(pm.phi, argnums=1)(zero_mech, zero_f)
    mech0 = pm.initial_mech(initial)
    return D, D_latent, phi_force, None if pm.stationary_start else mech0, *mech0


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
    """Cholesky factor with a jitter relative to each diagonal entry (the latent's covariances
    span many orders of magnitude: the force innovation and the within-step displacement;
    zero diagonal entries get the mean diagonal's scale)."""
    d = jnp.diagonal(P)
    d = jnp.where(d > 0, d, jnp.mean(jnp.abs(d)))
    return cholesky(symmetrise(P) + JITTER * jnp.diag(d))
