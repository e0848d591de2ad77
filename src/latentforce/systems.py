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
"""

from __future__ import annotations

from typing import Callable

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

    def input_matrix(self) -> jnp.ndarray:
        B = np.zeros((self.ndof, self.nforce))
        for j, dof in enumerate(self.force_dofs):
            B[dof, j] = 1.0
        return jnp.asarray(B)

    def mass(self, params: Params):  # pragma: no cover - abstract
        raise NotImplementedError

    def restoring(self, params: Params, z, v):  # pragma: no cover - abstract
        raise NotImplementedError

    def linear_part(self, params: Params):  # pragma: no cover - abstract
        raise NotImplementedError

    def acceleration(self, params: Params, z, v, u):
        r""":math:`\ddot z = M^{-1}(B u - h(z, \dot z))` for one state (no batch dims)."""
        rhs = self.input_matrix() @ u - self.restoring(params, z, v)
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

    def restoring(self, params, z, v):
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

    def __init__(self):
        self.ndof = 1
        self.force_dofs = (0,)

    def __repr__(self) -> str:
        return "Duffing()"

    def mass(self, params):
        return jnp.reshape(jnp.asarray(params["m"], dtype=float), (1, 1))

    def restoring(self, params, z, v):
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

    def restoring(self, params, z, v):
        return jnp.reshape(self.h(z, v, params), (1,))

    def linear_part(self, params):
        zero = jnp.zeros(1)
        K = jax.jacfwd(lambda z: self.restoring(params, z, zero))(zero)
        C = jax.jacfwd(lambda v: self.restoring(params, zero, v))(zero)
        return self.mass(params), jnp.reshape(C, (1, 1)), jnp.reshape(K, (1, 1))


SYSTEM_TYPES = ("linear", "duffing")
