"""Small dense linear-algebra helpers shared by kernels, models and filters.

Everything here is pure JAX and traceable, so the matrices may depend on
parameters that are being sampled or differentiated.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax.scipy.linalg import expm
from jaxtyping import Array, Float


def symmetrise(P: Float[Array, "n n"]) -> Float[Array, "n n"]:
    """Return ``(P + P^T) / 2``; applied after every covariance update."""
    return 0.5 * (P + P.T)


def solve_lyapunov(F: Float[Array, "n n"], W: Float[Array, "n n"]) -> Float[Array, "n n"]:
    r"""Solve the continuous Lyapunov equation :math:`F P + P F^T + W = 0`.

    Used for the stationary covariance :math:`P_\infty` of a stable linear SDE
    :math:`dx = F x\,dt + L\,d\beta` with :math:`W = L Q_c L^T`
    (Särkkä & Solin 2019, Eq. 6.69). Solved through the Kronecker form
    :math:`(F \oplus F)\,\mathrm{vec}(P) = -\mathrm{vec}(W)`, which is exact and
    cheap for the state sizes we meet (n up to a few dozen).
    """
    n = F.shape[0]
    eye = jnp.eye(n, dtype=F.dtype)
    kron_sum = jnp.kron(F, eye) + jnp.kron(eye, F)
    P = jnp.linalg.solve(kron_sum, -W.reshape(-1)).reshape(n, n)
    return symmetrise(P)


def van_loan(
    F: Float[Array, "n n"], W: Float[Array, "n n"], dt: float
) -> tuple[Float[Array, "n n"], Float[Array, "n n"]]:
    r"""Exact discretisation of :math:`dx = F x\,dt + L\,d\beta`, :math:`W = L Q_c L^T`.

    Returns :math:`A = e^{F \Delta t}` and
    :math:`Q = \int_0^{\Delta t} e^{F s} W e^{F^T s} ds` (Eq. 7a and 8 of ISMA
    2018) from one matrix exponential of the Van Loan block matrix
    :math:`\begin{pmatrix} F & W \\ 0 & -F^T \end{pmatrix}\Delta t`, whose
    top-right block times :math:`A^T` is :math:`Q` (Van Loan 1978).
    """
    n = F.shape[0]
    zeros = jnp.zeros_like(F)
    block = jnp.block([[F, W], [zeros, -F.T]]) * dt
    E = expm(block)
    A = E[:n, :n]
    Q = E[:n, n:] @ A.T
    return A, symmetrise(Q)
