r"""Gaussian-process kernels in time and their state-space (linear SDE) forms.

A stationary kernel :math:`k(\tau)` whose spectral density is rational is the
covariance of the output :math:`f = H x` of a linear SDE

.. math:: \dot{x}(t) = F x(t) + L w(t), \qquad E[w(t) w(s)] = Q_c\,\delta(t-s),

started in its stationary distribution :math:`x \sim N(0, P_\infty)` with
:math:`F P_\infty + P_\infty F^T + L Q_c L^T = 0`; then
:math:`k(\tau) = H e^{F \tau} P_\infty H^T` for :math:`\tau \ge 0`
(Hartikainen & Särkkä 2010). Every kernel here exposes ``F, L, Qc, H, Pinf``
and the exact discrete transition ``A(dt), Q(dt)``; one convention
throughout: column states, ``x_next = A @ x``.

A kernel object holds structure only (its family and order); the numbers
live in :class:`KernelParams`, a pytree that can be traced, vmapped over
chains and differentiated. Kernels compose with ``+`` (independent sum:
block-diagonal SDE) and ``*`` (product: Kronecker-sum SDE, Solin 2016, §4.2).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import jax.scipy.linalg  # noqa: F401  (block_diag)
import numpy as np
from jaxtyping import Array, Float
from scipy import special

from latentforce.linalg import expm_balanced, solve_lyapunov, symmetrise, van_loan


class KernelParams(NamedTuple):
    """Hyperparameters of one Matérn kernel: signal variance and lengthscale."""

    variance: Float[Array, ""]
    lengthscale: Float[Array, ""]


class StateSpace(NamedTuple):
    """Continuous state-space form of a stationary GP (see module docstring)."""

    F: Float[Array, "d d"]
    L: Float[Array, "d s"]
    Qc: Float[Array, "s s"]
    H: Float[Array, "1 d"]
    Pinf: Float[Array, "d d"]


class Kernel:
    """Base class: structure of a temporal GP kernel with a state-space form."""

    dim: int
    name: str

    def state_space(self, params) -> StateSpace:  # pragma: no cover - abstract
        raise NotImplementedError

    def covariance(self, tau, params):  # pragma: no cover - abstract
        raise NotImplementedError

    def discretise(self, params, dt: float):
        r"""Exact discrete transition ``(A, Q)`` over a step ``dt``.

        :math:`A = e^{F\Delta t}` (balanced). For a stationary process
        :math:`Q = P_\infty - A P_\infty A^T` exactly; that form is stable for
        coarse steps but cancels catastrophically for fine ones, where Van
        Loan's integral is accurate instead, and vice versa (Van Loan's block
        exponential grows like :math:`e^{\lambda\Delta t}`). We use the
        stationary identity when the step exceeds the kernel's slowest time
        scale by far (``|F| dt > 4`` in the balanced norm) and Van Loan otherwise.
        """
        ss = self.state_space(params)
        A = expm_balanced(ss.F * dt)
        rate = self.decay_rate(params)
        coarse = rate * dt > 4.0
        # Van Loan at a harmless step where its result is not used, so that neither
        # branch (nor its gradient) holds a NaN.
        _, Q_vl = van_loan(ss.F, ss.L @ ss.Qc @ ss.L.T, jnp.where(coarse, 1.0 / rate, dt))
        Q_st = symmetrise(ss.Pinf - A @ ss.Pinf @ A.T)
        return A, jnp.where(coarse, Q_st, Q_vl)

    def decay_rate(self, params):  # pragma: no cover - abstract
        """The slowest decay rate of the SDE (smallest ``|Re eig(F)|``)."""
        raise NotImplementedError

    def state_covariance(self, tau, params):
        r"""Covariance ``H expm(F |tau|) Pinf H^T`` computed from the SDE form."""
        ss = self.state_space(params)
        tau = jnp.abs(jnp.asarray(tau, dtype=float))
        return jnp.vectorize(lambda s: (ss.H @ expm_balanced(ss.F * s) @ ss.Pinf @ ss.H.T)[0, 0])(tau)

    # A kernel is structure only (its numbers are in KernelParams): equal by type and name.
    def __eq__(self, other) -> bool:
        return type(other) is type(self) and (self.name, self.dim) == (other.name, other.dim)

    def __hash__(self) -> int:
        return hash((type(self), self.name, self.dim))

    def __add__(self, other: "Kernel") -> "Kernel":
        # Matérns and their sums add to a MaternSum (a model's kernel: the force its first state);
        # anything else to the general Sum (parameters a tuple, H = [H1, H2]: not a model's kernel)
        terms = [t for k in (self, other) for t in (k.terms if isinstance(k, MaternSum) else (k,))]
        if all(isinstance(t, Matern) for t in terms):
            return MaternSum(tuple(terms))
        return Sum(self, other)

    def __mul__(self, other: "Kernel") -> "Kernel":
        return Product(self, other)


class Matern(Kernel):
    r"""Matérn kernel of smoothness :math:`\nu = p + 1/2`, any integer ``p >= 0``.

    .. math::
        k(\tau) = \sigma_f^2 \frac{2^{1-\nu}}{\Gamma(\nu)}
        \left(\frac{\sqrt{2\nu}\,\tau}{\ell}\right)^{\nu}
        K_\nu\!\left(\frac{\sqrt{2\nu}\,\tau}{\ell}\right)

    (Eq. 9, Vibration 2020). With :math:`\lambda = \sqrt{2\nu}/\ell`, its
    spectral density is proportional to :math:`(\lambda^2+\omega^2)^{-(p+1)}`
    (Eq. 12); the stable factor :math:`(\lambda + i\omega)^{-(p+1)}` (Eq. 13 of
    ISMA 2018) gives an SDE of order :math:`p+1` in companion form (Eq. 16)
    with coefficients :math:`a_j = \binom{p+1}{j}\lambda^{p+1-j}` and white
    noise spectral density (Eq. 13 / Eq. 17)

    .. math:: q = \frac{2\sigma_f^2 \sqrt{\pi}\,\lambda^{2p+1}\,\Gamma(p+1)}{\Gamma(p+1/2)}.

    Erratum: Eq. (15) of Vibration 2020 prints :math:`\dot{l} = l/\ell + w`;
    the stable Matérn-1/2 (Ornstein–Uhlenbeck) SDE is :math:`\dot{l} = -l/\ell + w`.
    """

    def __init__(self, p: int):
        if int(p) != p or p < 0:
            raise ValueError(f"Matérn order p must be a non-negative integer, got {p!r}")
        self.p = int(p)
        self.dim = self.p + 1
        self.nu = self.p + 0.5
        self.name = f"matern{2 * self.p + 1}2"
        # Binomial coefficients of (lambda + s)^(p+1), lowest power of s first.
        self._binom = np.array([math.comb(self.p + 1, j) for j in range(self.p + 1)], dtype=float)
        self._q_const = 2.0 * math.sqrt(math.pi) * math.gamma(self.p + 1) / math.gamma(self.p + 0.5)

    def __repr__(self) -> str:
        return f"Matern(p={self.p})"

    def __eq__(self, other) -> bool:
        return isinstance(other, Matern) and other.p == self.p

    def __hash__(self) -> int:
        return hash(("Matern", self.p))

    def lam(self, lengthscale):
        return jnp.sqrt(2.0 * self.nu) / lengthscale

    def decay_rate(self, params: KernelParams):
        # F is the companion matrix of (s + lambda)^(p+1): every eigenvalue is -lambda.
        return self.lam(params.lengthscale)

    def spectral_density_q(self, params: KernelParams):
        """White-noise spectral density ``q`` of Eq. (13), Vibration 2020."""
        lam = self.lam(params.lengthscale)
        return self._q_const * params.variance * lam ** (2 * self.p + 1)

    def spectral_density(self, omega, params: KernelParams):
        r"""Two-sided spectral density in angular frequency, :math:`S(\omega) = q\,(\lambda^2 + \omega^2)^{-(p+1)}`.

        The Fourier transform of :math:`k(\tau)` (Rasmussen & Williams 2006,
        Eq. 4.15), normalised so that :math:`\int_{-\infty}^{\infty} S(\omega)\,
        d\omega / 2\pi = k(0) = \sigma_f^2`; ``q`` is :meth:`spectral_density_q`.
        """
        lam = self.lam(params.lengthscale)
        omega = jnp.asarray(omega, dtype=float)
        return self.spectral_density_q(params) / (lam**2 + omega**2) ** (self.p + 1)

    def state_space(self, params: KernelParams) -> StateSpace:
        d = self.dim
        lam = self.lam(params.lengthscale)
        powers = jnp.arange(d, 0, -1)  # lambda^(p+1-j) for j = 0..p
        coeffs = jnp.asarray(self._binom) * lam**powers
        F = jnp.diag(jnp.ones(d - 1), k=1) if d > 1 else jnp.zeros((1, 1))
        F = F.at[-1, :].set(-coeffs)
        L = jnp.zeros((d, 1)).at[-1, 0].set(1.0)
        Qc = jnp.reshape(self.spectral_density_q(params), (1, 1))
        H = jnp.zeros((1, d)).at[0, 0].set(1.0)
        Pinf = solve_lyapunov(F, L @ Qc @ L.T)
        return StateSpace(F, L, Qc, H, Pinf)

    def covariance(self, tau, params: KernelParams):
        r"""The kernel :math:`k(\tau)` in closed form (for tests and simulation).

        Closed forms for ``p = 0, 1, 2``; the general polynomial form
        (Rasmussen & Williams 2006, Eq. 4.16) for larger ``p``.
        """
        tau = jnp.abs(jnp.asarray(tau, dtype=float))
        r = jnp.sqrt(2.0 * self.nu) * tau / params.lengthscale
        p = self.p
        poly = 0.0
        for i in range(p + 1):
            c = math.factorial(p + i) / (math.factorial(i) * math.factorial(p - i))
            poly = poly + c * (2.0 * r) ** (p - i)
        pref = math.factorial(p) / math.factorial(2 * p)
        return params.variance * jnp.exp(-r) * pref * poly


def matern_bessel(tau, nu: float, variance: float, lengthscale: float) -> np.ndarray:
    """Matérn kernel from the Bessel-function definition (Eq. 9); NumPy, for tests."""
    tau = np.abs(np.asarray(tau, dtype=float))
    r = np.sqrt(2.0 * nu) * tau / lengthscale
    with np.errstate(invalid="ignore"):
        k = variance * 2 ** (1 - nu) / special.gamma(nu) * r**nu * special.kv(nu, r)
    return np.where(r == 0, variance, k)


class Sum(Kernel):
    """Sum of independent GPs: block-diagonal SDE, ``H = [H1, H2]``."""

    def __init__(self, k1: Kernel, k2: Kernel):
        self.k1, self.k2 = k1, k2
        self.dim = k1.dim + k2.dim
        self.name = f"({k1.name}+{k2.name})"

    def state_space(self, params) -> StateSpace:
        a, b = self.k1.state_space(params[0]), self.k2.state_space(params[1])
        blk = lambda X, Y: jnp.block(
            [[X, jnp.zeros((X.shape[0], Y.shape[1]))], [jnp.zeros((Y.shape[0], X.shape[1])), Y]]
        )
        return StateSpace(
            blk(a.F, b.F), blk(a.L, b.L), blk(a.Qc, b.Qc), jnp.concatenate([a.H, b.H], axis=1), blk(a.Pinf, b.Pinf)
        )

    def covariance(self, tau, params):
        return self.k1.covariance(tau, params[0]) + self.k2.covariance(tau, params[1])

    def decay_rate(self, params):
        return jnp.minimum(self.k1.decay_rate(params[0]), self.k2.decay_rate(params[1]))


class Product(Kernel):
    r"""Product of two stationary kernels (Solin 2016, §4.2).

    :math:`F = F_1 \oplus F_2`, :math:`H = H_1 \otimes H_2`,
    :math:`P_\infty = P_{\infty,1} \otimes P_{\infty,2}`; the noise enters
    through :math:`L Q_c L^T = -(F P_\infty + P_\infty F^T)`, stored as
    ``L = I`` and ``Qc`` equal to that matrix.
    """

    def __init__(self, k1: Kernel, k2: Kernel):
        self.k1, self.k2 = k1, k2
        self.dim = k1.dim * k2.dim
        self.name = f"({k1.name}*{k2.name})"

    def state_space(self, params) -> StateSpace:
        a, b = self.k1.state_space(params[0]), self.k2.state_space(params[1])
        F = jnp.kron(a.F, jnp.eye(b.F.shape[0])) + jnp.kron(jnp.eye(a.F.shape[0]), b.F)
        Pinf = jnp.kron(a.Pinf, b.Pinf)
        W = symmetrise(-(F @ Pinf + Pinf @ F.T))
        return StateSpace(F, jnp.eye(self.dim), W, jnp.kron(a.H, b.H), Pinf)

    def covariance(self, tau, params):
        return self.k1.covariance(tau, params[0]) * self.k2.covariance(tau, params[1])

    def decay_rate(self, params):
        # eigenvalues of a Kronecker sum are sums of the factors' eigenvalues
        return self.k1.decay_rate(params[0]) + self.k2.decay_rate(params[1])


class MaternSum(Kernel):
    r"""A sum of independent Matérn GPs, each with its own variance and lengthscale.

    ``f = f_0 + f_1 + ...`` (a slow and a fast component, say). The terms' SDEs stack
    block-diagonally; the state is then changed by :math:`x' = T x`, :math:`T` the identity with
    the first row replaced by the sum of the blocks' first rows, so that the force itself is the
    first state (:math:`H = e_1^\top`) as for a single Matérn (every reader of "the force
    value" in the models and samplers relies on that). Its parameters are a :class:`KernelParams`
    of arrays, one entry per term.
    """

    def __init__(self, terms: tuple[Matern, ...]):
        terms = tuple(terms)
        if len(terms) < 2 or not all(isinstance(t, Matern) for t in terms):
            raise ValueError(f"a Matérn sum needs at least two Matérn terms, got {terms!r}")
        self.terms = terms
        self.dim = sum(t.dim for t in terms)
        self.name = "+".join(t.name for t in terms)
        self.n_terms = len(terms)
        starts = np.cumsum([0] + [t.dim for t in terms])
        T = np.eye(self.dim)
        T[0, starts[1:-1]] = 1.0
        self._T = T
        self._Tinv = np.linalg.inv(T)  # I minus the same row entries (exact)

    def __repr__(self) -> str:
        return f"MaternSum({self.terms!r})"

    def _term(self, params: KernelParams, i: int) -> KernelParams:
        return KernelParams(jnp.reshape(params.variance, (-1,))[i], jnp.reshape(params.lengthscale, (-1,))[i])

    def _block(self, mats):
        return jax.scipy.linalg.block_diag(*mats)

    def state_space(self, params: KernelParams) -> StateSpace:
        parts = [t.state_space(self._term(params, i)) for i, t in enumerate(self.terms)]
        T, Ti = jnp.asarray(self._T), jnp.asarray(self._Tinv)
        F = T @ self._block([p.F for p in parts]) @ Ti
        L = T @ self._block([p.L for p in parts])
        Qc = self._block([p.Qc for p in parts])
        Pinf = symmetrise(T @ self._block([p.Pinf for p in parts]) @ T.T)
        H = jnp.zeros((1, self.dim)).at[0, 0].set(1.0)
        return StateSpace(F, L, Qc, H, Pinf)

    def discretise(self, params, dt: float):
        """Each term's own exact, robust transition (:meth:`Kernel.discretise`), stacked and
        changed to the summed state: a fast term never forces a slow one's Van Loan integral
        into its overflowing regime."""
        parts = [t.discretise(self._term(params, i), dt) for i, t in enumerate(self.terms)]
        T, Ti = jnp.asarray(self._T), jnp.asarray(self._Tinv)
        A = T @ self._block([a for a, _ in parts]) @ Ti
        Q = symmetrise(T @ self._block([q for _, q in parts]) @ T.T)
        return A, Q

    def decay_rate(self, params):
        return jnp.min(jnp.stack([t.decay_rate(self._term(params, i)) for i, t in enumerate(self.terms)]))

    def covariance(self, tau, params):
        return sum(t.covariance(tau, self._term(params, i)) for i, t in enumerate(self.terms))

    def spectral_density(self, omega, params):
        """The terms' densities summed (independent processes)."""
        return sum(t.spectral_density(omega, self._term(params, i)) for i, t in enumerate(self.terms))


KERNELS = {"matern12": 0, "matern32": 1, "matern52": 2, "matern72": 3}


def kernel_from_name(name: str) -> Matern | MaternSum:
    """Build a kernel from its config name: ``matern12`` ... ``matern72``, or a sum of them
    written with ``+`` (``"matern12 + matern52"``: independent terms, each with its own
    variance and lengthscale)."""
    parts = [p.strip() for p in str(name).split("+")]
    if any(p not in KERNELS for p in parts):
        raise KeyError(name)
    if len(parts) == 1:
        return Matern(KERNELS[parts[0]])
    return MaternSum(tuple(Matern(KERNELS[p]) for p in parts))


def n_terms(kernel: Kernel) -> int:
    """How many (variance, lengthscale) pairs the kernel has: 1 for a Matérn, one per term of a sum."""
    return int(getattr(kernel, "n_terms", 1))
