r"""Mechanical systems: equations of motion :math:`M \ddot z + h(z, \dot z) = B u`.

A system object holds structure only (number of DOFs, which DOFs the latent
forces act on, the form of :math:`h`); the numbers live in a ``dict`` pytree
keyed by the config names (``m, c, k, k3`` for SDOF systems, ``M, C, K`` for
linear MDOF systems), so MCMC can update any subset by name and JAX can
vmap over chains.

Every system provides

* ``mass(params)``: the mass matrix :math:`M` (``ndof x ndof``);
* ``restoring(params, z, v)``: the internal force :math:`h(z, \dot z)`;
* ``input_matrix()``: :math:`B` (``ndof x nforce``), from ``force_dofs``;
* ``linear_part(params)``: ``(M, C, K)`` of the system linearised about rest,
  exact for linear systems; the nonlinear sampler uses it for the transition
  covariance (see :mod:`latentforce.inference.pgas`).

Internal states. A hysteretic element carries a state of its own, the
hysteretic force :math:`r` of the Bouc-Wen model, with its own ODE
:math:`\dot r = g(z, \dot z, r)`: a system declares ``n_internal`` such states,
``restoring(params, z, v, r)`` and ``internal_rate(params, z, v, r)`` read them,
and ``internal_linear(params)`` gives their linearisation about rest,
``(S, R_z)``: :math:`h = \ldots + S r` and :math:`r \approx R_z z` (the linear
part then has the stiffness :math:`K + S R_z`). The mechanical state is
``(z, zdot, r)`` (:class:`latentforce.models.StateLayout`).
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from latentforce.linalg import solve

Params = dict


class System:
    """Base class for a mechanical system with ``ndof`` degrees of freedom."""

    ndof: int
    force_dofs: tuple[int, ...]
    is_linear: bool = False
    type_name: str = ""
    #: names of the scalar or matrix parameters this system reads from ``params``
    param_names: tuple[str, ...] = ()
    #: internal (hysteretic) states beyond z, zdot (module doc)
    n_internal: int = 0
    #: integration steps of the mechanical ODE per sample in the samplers' model
    #: (:meth:`latentforce.inference.particle_model.ParticleModel.phi`)
    substeps: int = 1

    @property
    def nforce(self) -> int:
        return len(self.force_dofs)

    # A system is structure only (its numbers are in the params dict): two systems of one type
    # with the same attributes are equal, so that compiled programs keyed by the model serve both.
    def _key(self) -> tuple:
        return (type(self),) + tuple(sorted(vars(self).items()))

    def __eq__(self, other) -> bool:
        return type(other) is type(self) and self._key() == other._key()

    def __hash__(self) -> int:
        return hash(self._key())

    def internal_bound(self, params: Params):
        """Per internal state, a bound on its magnitude that its own rate enforces (inf: none)."""
        return jnp.full(self.n_internal, jnp.inf)

    def input_matrix(self) -> jnp.ndarray:
        B = np.zeros((self.ndof, self.nforce))
        for j, dof in enumerate(self.force_dofs):
            B[dof, j] = 1.0
        return jnp.asarray(B)

    def mass(self, params: Params):  # pragma: no cover - abstract
        raise NotImplementedError

    def restoring(self, params: Params, z, v, r=None):  # pragma: no cover - abstract
        raise NotImplementedError

    def linear_part(self, params: Params):  # pragma: no cover - abstract
        raise NotImplementedError

    def internal_rate(self, params: Params, z, v, r):
        r""":math:`\dot r = g(z, \dot z, r)` of the internal states (none by default)."""
        return jnp.zeros(0)

    def internal_linear(self, params: Params):
        """``(S, R_z)`` of the internal states about rest (module doc): ``(ndof, 0)``, ``(0, ndof)``
        when there are none."""
        return jnp.zeros((self.ndof, 0)), jnp.zeros((0, self.ndof))

    def tangent_deviation(self, params: Params, r_sd):
        r"""Per internal state, the relative deviation of :math:`\partial\dot r/\partial\dot z` from its
        value at rest at :math:`|r| = 2\,` ``r_sd``, capped at 1 (the independent within-step noise
        of :func:`latentforce.inference.particle_model.internal_noise`)."""
        return jnp.zeros(0)

    def acceleration(self, params: Params, z, v, u, r=None):
        r""":math:`\ddot z = M^{-1}(B u - h(z, \dot z, r))` for one state (no batch dims)."""
        rhs = self.input_matrix() @ u - self.restoring(params, z, v, r)
        return solve(self.mass(params), rhs)


class LinearSystem(System):
    r"""Linear system :math:`M \ddot z + C \dot z + K z = B u`.

    SDOF systems read scalars ``m, c, k``; MDOF systems read matrices
    ``M, C, K`` (``ndof x ndof``).
    """

    is_linear = True
    type_name = "linear"

    def __init__(self, ndof: int = 1, force_dofs=(0,)):
        self.ndof = int(ndof)
        self.force_dofs = tuple(int(d) for d in force_dofs)
        self.param_names = ("m", "c", "k") if self.ndof == 1 else ("M", "C", "K")

    def __repr__(self) -> str:
        return f"LinearSystem(ndof={self.ndof}, force_dofs={self.force_dofs})"

    def matrices(self, params: Params):
        if self.ndof == 1:
            as_mat = lambda x: jnp.reshape(jnp.asarray(x, dtype=float), (1, 1))
            return as_mat(params["m"]), as_mat(params["c"]), as_mat(params["k"])
        return (
            jnp.asarray(params["M"], dtype=float),
            jnp.asarray(params["C"], dtype=float),
            jnp.asarray(params["K"], dtype=float),
        )

    def mass(self, params):
        return self.matrices(params)[0]

    def restoring(self, params, z, v, r=None):
        _, C, K = self.matrices(params)
        return C @ v + K @ z

    def linear_part(self, params):
        return self.matrices(params)


class ShearFrame(LinearSystem):
    r"""A shear frame (chain of storeys) with a scalar parameter per floor and storey.

    Floor :math:`i` has mass ``m_i``; storey :math:`i` joins floor
    :math:`i` to floor :math:`i-1` (storey 0 to the ground) with stiffness
    ``k_i`` and damping ``c_i``, so

    .. math:: M = \operatorname{diag}(m_i), \qquad
              K_{ii} = k_i + k_{i+1}, \; K_{i,i+1} = K_{i+1,i} = -k_{i+1}

    (and :math:`C` from the ``c_i`` likewise). Every entry is a scalar
    parameter, so each may be fixed or inferred by name, as ``m, c, k`` of
    a single-DOF system (the form of the storey models engineers identify
    from floor accelerations).
    """

    type_name = "linear"

    def __init__(self, ndof: int, force_dofs=(0,)):
        super().__init__(ndof, force_dofs)
        self.param_names = tuple(f"{kind}_{i}" for kind in ("m", "c", "k") for i in range(self.ndof))

    def __repr__(self) -> str:
        return f"ShearFrame(ndof={self.ndof}, force_dofs={self.force_dofs})"

    def matrices(self, params: Params):
        n = self.ndof
        get = lambda kind: jnp.stack([jnp.asarray(params[f"{kind}_{i}"], dtype=float) for i in range(n)])
        M = jnp.diag(get("m"))
        # Storey i acts between floor i and floor i-1: the chain's incidence matrix.
        D = jnp.asarray(np.eye(n) - np.eye(n, k=-1))
        return M, D.T @ jnp.diag(get("c")) @ D, D.T @ jnp.diag(get("k")) @ D


class Duffing(System):
    r"""Duffing oscillator :math:`m\ddot z + c\dot z + k z + k_3 z^3 = u` (Eq. 26, Vibration 2020)."""

    type_name = "duffing"
    param_names = ("m", "c", "k", "k3")

    def __init__(self, substeps: int = 1):
        self.ndof = 1
        self.force_dofs = (0,)
        self.substeps = int(substeps)

    def __repr__(self) -> str:
        return "Duffing()" if self.substeps == 1 else f"Duffing(substeps={self.substeps})"

    def mass(self, params):
        return jnp.reshape(jnp.asarray(params["m"], dtype=float), (1, 1))

    def restoring(self, params, z, v, r=None):
        return params["c"] * v + params["k"] * z + params["k3"] * z**3

    def linear_part(self, params):
        r = lambda x: jnp.reshape(jnp.asarray(x, dtype=float), (1, 1))
        return r(params["m"]), r(params["c"]), r(params["k"])


class NonlinearSDOF(System):
    r"""General SDOF system :math:`m \ddot z + h(z, \dot z) = u` with a Python ``h``.

    ``h(z, v, params)`` takes scalars (or shape-``(1,)`` arrays) and the
    parameter dict, and must be written in ``jax.numpy`` so that it can be
    traced. Library API only: a config file never executes code.
    """

    type_name = "sdof"
    param_names = ("m",)

    def __init__(self, h: Callable, extra_params: tuple[str, ...] = ()):
        self.ndof = 1
        self.force_dofs = (0,)
        self.h = h
        self.param_names = ("m",) + tuple(extra_params)

    def mass(self, params):
        return jnp.reshape(jnp.asarray(params["m"], dtype=float), (1, 1))

    def restoring(self, params, z, v, r=None):
        return jnp.reshape(self.h(z, v, params), (1,))

    def linear_part(self, params):
        zero = jnp.zeros(1)
        K = jax.jacfwd(lambda z: self.restoring(params, z, zero))(zero)
        C = jax.jacfwd(lambda v: self.restoring(params, zero, v))(zero)
        return self.mass(params), jnp.reshape(C, (1, 1)), jnp.reshape(K, (1, 1))


def signed_power(r, nu):
    r""":math:`|r|^{\nu - 1} r` and :math:`|r|^\nu`, with finite derivatives in ``r`` and ``nu`` at
    :math:`r = 0` for :math:`\nu \ge 1` (``jnp.abs(r) ** nu`` differentiated in ``nu`` at 0 gives
    ``0 * log 0 = nan``: the mode search differentiates the filter at rest)."""
    a = jnp.abs(r)
    nz = a > 0
    p = jnp.where(nz, jnp.exp(nu * jnp.log(jnp.where(nz, a, 1.0))), 0.0)
    return jnp.sign(r) * p, p


def linearised_stability(system, params: Params) -> tuple[np.ndarray, bool]:
    """The eigenvalues of ``system``'s (z, zdot) state matrix linearised about rest (its linear part),
    and whether they are all in the open left half-plane. Undamped modes have real parts of round-off
    size and either sign (an MDOF C = 0: -1e-15, which passed a test of >= 0 and failed later as a
    non-finite log-likelihood), so the test is relative; a singular M is unstable."""
    M, C, K = (np.asarray(a, dtype=float) for a in system.linear_part(params))
    n = M.shape[0]
    try:
        Minv = np.linalg.inv(M)
    except np.linalg.LinAlgError:
        return np.full(2 * n, np.nan), False
    eig = np.linalg.eigvals(np.block([[np.zeros((n, n)), np.eye(n)], [-Minv @ K, -Minv @ C]]))
    stable = bool(np.all(np.isfinite(eig)) and np.max(eig.real) < -1e-9 * max(np.max(np.abs(eig)), 1e-300))
    return eig, stable


def saturation(alpha, beta, gamma, nu):
    r"""The hysteretic force's bound on a loading branch, :math:`(\alpha / (\beta + \gamma))^{1/\nu}`
    (there :math:`\dot r = \dot z (\alpha - (\beta + \gamma) |r|^\nu)`, whichever the direction);
    inf where :math:`\beta + \gamma \le 0` (the branch stiffens without bound)."""
    s = jnp.asarray(beta, dtype=float) + jnp.asarray(gamma, dtype=float)
    safe = jnp.where(s > 0, s, 1.0)
    return jnp.where(
        s > 0, (jnp.abs(jnp.asarray(alpha, dtype=float)) / safe) ** (1.0 / jnp.asarray(nu, dtype=float)), jnp.inf
    )


#: the largest relative tangent deviation :meth:`System.tangent_deviation` reports. The Bouc-Wen
#: benchmark's loops reach 7.6 (a tangent of 1.1e5 to 4.8e5 N/m against alpha = 5e4 at |r| = 200 N),
#: but with the cap at 10 instead of 1 its demo's pgas run lost its ancestor switching (0.26 ->
#: 0.07) and the smoother and joint moves accepted nothing: r loosely tied to z leaves the force and
#: r separated only by r's nonlinear dynamics, where the linearised proposals fail.
TANGENT_DEVIATION_CAP = 1.0

#: RK4 substeps per sample of a Bouc-Wen system's mechanical step (measured: tests/test_bouc_wen.py)
DEFAULT_BOUC_WEN_SUBSTEPS = 4


class BoucWen(System):
    r"""Bouc-Wen hysteretic oscillator, in the form of the nonlinear system identification
    benchmark of Noël & Schoukens (2016):

    .. math:: m \ddot z + c \dot z + k z + r = u, \qquad
              \dot r = \alpha \dot z - \beta |\dot z| |r|^{\nu-1} r - \gamma \dot z |r|^\nu

    (the benchmark's :math:`\beta\gamma` and :math:`\beta\delta` are ``beta`` and ``gamma``;
    its values: ``m = 2, c = 10, k = 5e4, alpha = 5e4, beta = 1e3 * 0.8, gamma = 1e3 * -1.1,
    nu = 1``). The hysteretic force :math:`r` is an internal state (module doc); about rest
    :math:`\dot r = \alpha \dot z`, so from a virgin state :math:`r \approx \alpha z` and the linear part
    has the stiffness :math:`k + \alpha`. ``nu >= 1`` (below 1 the rate is not Lipschitz at
    :math:`r = 0`).
    """

    type_name = "bouc-wen"
    param_names = ("m", "c", "k", "alpha", "beta", "gamma", "nu")
    n_internal = 1

    def __init__(self, substeps: int = DEFAULT_BOUC_WEN_SUBSTEPS):
        self.ndof = 1
        self.force_dofs = (0,)
        self.substeps = int(substeps)

    def __repr__(self) -> str:
        return f"BoucWen(substeps={self.substeps})"

    def mass(self, params):
        return jnp.reshape(jnp.asarray(params["m"], dtype=float), (1, 1))

    def restoring(self, params, z, v, r=None):
        return params["c"] * v + params["k"] * z + r

    def internal_rate(self, params, z, v, r):
        sp, p = signed_power(r, params["nu"])
        return params["alpha"] * v - params["beta"] * jnp.abs(v) * sp - params["gamma"] * v * p

    def internal_linear(self, params):
        return jnp.ones((1, 1)), jnp.reshape(jnp.asarray(params["alpha"], dtype=float), (1, 1))

    def internal_bound(self, params):
        return saturation(params["alpha"], params["beta"], params["gamma"], params["nu"])[None]

    def tangent_deviation(self, params, r_sd):
        # d(rdot)/d(zdot) = alpha - (beta sign(zdot r) + gamma) |r|^nu: off alpha by at most
        # (|beta| + |gamma|) |r|^nu
        _, p = signed_power(2.0 * r_sd, params["nu"])
        dev = (jnp.abs(params["beta"]) + jnp.abs(params["gamma"])) * p / jnp.maximum(jnp.abs(params["alpha"]), 1e-300)
        return jnp.minimum(dev, TANGENT_DEVIATION_CAP)

    def linear_part(self, params):
        r = lambda x: jnp.reshape(jnp.asarray(x, dtype=float), (1, 1))
        return r(params["m"]), r(params["c"]), r(params["k"] + params["alpha"])


#: the kinds of nonlinear element a ``[[system.elements]]`` table may give, with their keys
ELEMENT_KEYS = {"cubic": ("k3",), "bouc-wen": ("alpha", "beta", "gamma", "nu")}


def element_param(index: int, key: str) -> str:
    """The parameter name of an element's key: ``element0_k3``, ``element1_alpha``."""
    return f"element{index}_{key}"


class Element(NamedTuple):
    r"""A nonlinear element of an MDOF structure: its kind (``"cubic"`` or ``"bouc-wen"``) and its
    DOFs, ``(i, j)`` between two DOFs or ``(i,)`` to the ground. Its relative displacement is
    :math:`\delta = z_i - z_j` (:math:`z_i` to the ground), and it pushes DOF ``i`` by
    :math:`-f` and DOF ``j`` by :math:`+f`: :math:`h \mathrel{+}= d f` with the incidence
    vector :math:`d = e_i - e_j`."""

    kind: str
    dofs: tuple[int, ...]

    def incidence(self, ndof: int) -> np.ndarray:
        d = np.zeros(ndof)
        d[self.dofs[0]] = 1.0
        if len(self.dofs) > 1:
            d[self.dofs[1]] = -1.0
        return d


class NonlinearMDOF(System):
    r"""A linear structure (``base``: matrices or a shear frame) with nonlinear elements:

    .. math:: M \ddot z + C \dot z + K z
              + \sum_{e\ \mathrm{cubic}} k_{3,e}\, d_e (d_e^T z)^3 + S r = B u,

    with :math:`S = [d_e]` the incidence vectors of the Bouc-Wen elements and :math:`r_e`
    their hysteretic forces, internal states with the rate of :class:`BoucWen` on the relative
    velocity :math:`d_e^T \dot z`. A cubic element is a Duffing spring between two DOFs; a
    Bouc-Wen element adds its hysteretic force to the stiffness ``K`` already there (so a
    storey's linear spring stays in ``K``). Parameters: the base's, then each element's keys as
    ``element<e>_<key>`` (:func:`element_param`). Linear part: :math:`K + S\,
    \mathrm{diag}(\alpha) S^T` (the hysteretic forces about rest, :math:`r = \mathrm{diag}(\alpha)
    S^T z`, as :class:`BoucWen`'s :math:`k + \alpha`).
    """

    type_name = "elements"

    def __init__(self, base: LinearSystem, elements, substeps: int = 1):
        self.base = base
        self.ndof = base.ndof
        self.force_dofs = base.force_dofs
        self.elements = tuple(Element(e.kind, tuple(int(d) for d in e.dofs)) for e in elements)
        self.substeps = int(substeps)
        self.param_names = tuple(base.param_names) + tuple(
            element_param(i, key) for i, e in enumerate(self.elements) for key in ELEMENT_KEYS[e.kind]
        )
        self._cubic = tuple(i for i, e in enumerate(self.elements) if e.kind == "cubic")
        self._hysteretic = tuple(i for i, e in enumerate(self.elements) if e.kind == "bouc-wen")
        self.n_internal = len(self._hysteretic)

    def __repr__(self) -> str:
        return f"NonlinearMDOF({self.base!r}, elements={list(self.elements)}, substeps={self.substeps})"

    def _incidence(self, which) -> jnp.ndarray:
        """``(ndof, len(which))``: the incidence vectors of elements ``which``, as columns."""
        cols = [self.elements[i].incidence(self.ndof) for i in which]
        return jnp.asarray(np.stack(cols, axis=1) if cols else np.zeros((self.ndof, 0)))

    def _values(self, params, which, key):
        return (
            jnp.stack([jnp.asarray(params[element_param(i, key)], dtype=float) for i in which])
            if which
            else jnp.zeros(0)
        )

    def mass(self, params):
        return self.base.mass(params)

    def restoring(self, params, z, v, r=None):
        h = self.base.restoring(params, z, v)
        if self._cubic:
            D = self._incidence(self._cubic)
            h = h + D @ (self._values(params, self._cubic, "k3") * (D.T @ z) ** 3)
        if self._hysteretic:
            h = h + self._incidence(self._hysteretic) @ r
        return h

    def internal_rate(self, params, z, v, r):
        if not self._hysteretic:
            return jnp.zeros(0)
        dv = self._incidence(self._hysteretic).T @ v
        get = lambda key: self._values(params, self._hysteretic, key)
        sp, p = signed_power(r, get("nu"))
        return get("alpha") * dv - get("beta") * jnp.abs(dv) * sp - get("gamma") * dv * p

    def internal_linear(self, params):
        S = self._incidence(self._hysteretic)
        return S, self._values(params, self._hysteretic, "alpha")[:, None] * S.T

    def internal_bound(self, params):
        get = lambda key: self._values(params, self._hysteretic, key)
        return saturation(get("alpha"), get("beta"), get("gamma"), get("nu"))

    def tangent_deviation(self, params, r_sd):
        if not self._hysteretic:
            return jnp.zeros(0)
        get = lambda key: self._values(params, self._hysteretic, key)
        _, p = signed_power(2.0 * r_sd, get("nu"))
        dev = (jnp.abs(get("beta")) + jnp.abs(get("gamma"))) * p / jnp.maximum(jnp.abs(get("alpha")), 1e-300)
        return jnp.minimum(dev, TANGENT_DEVIATION_CAP)

    def linear_part(self, params):
        M, C, K = self.base.linear_part(params)
        S, Rz = self.internal_linear(params)
        return M, C, K + S @ Rz


SYSTEM_TYPES = ("linear", "duffing", "bouc-wen")
