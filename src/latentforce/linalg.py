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


def balance(F: Float[Array, "n n"], sweeps: int = 6) -> Float[Array, " n"]:
    r"""Diagonal scaling ``d`` that balances ``diag(d)^{-1} F diag(d)`` (Parlett & Reinsch).

    Companion matrices of Matérn SDEs have entries from 1 to :math:`\lambda^{p+1}`
    and stiff structures add :math:`k/m`; the matrix exponential of such a
    badly scaled matrix loses accuracy or overflows (JAX's ``expm`` returns
    NaN). A similarity scaling fixes that exactly. Fixed number of sweeps, so
    it is jittable and differentiable; scales are rounded to powers of two so
    the scaling itself is exact in floating point.
    """
    n = F.shape[0]
    off = jnp.abs(F) * (1.0 - jnp.eye(n, dtype=F.dtype))
    d = jnp.ones(n, dtype=F.dtype)
    for _ in range(sweeps):
        scaled = off * (d[None, :] / d[:, None])
        col = jnp.sum(scaled, axis=0)
        row = jnp.sum(scaled, axis=1)
        ok = (col > 0) & (row > 0)
        factor = jnp.where(ok, jnp.sqrt(row / jnp.where(ok, col, 1.0)), 1.0)
        d = d * jnp.exp2(jnp.round(jnp.log2(factor)))
    return d


def expm_balanced(F: Float[Array, "n n"]) -> Float[Array, "n n"]:
    """``expm(F)`` computed on the balanced matrix (see :func:`balance`)."""
    d = balance(F)
    return expm(F * (d[None, :] / d[:, None])) * (d[:, None] / d[None, :])


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
    # Balance first: x = D x~ turns F into D^-1 F D and W into D^-1 W D^-1.
    d = balance(F)
    Fb = F * (d[None, :] / d[:, None])
    Wb = W / (d[:, None] * d[None, :])
    zeros = jnp.zeros_like(F)
    block = jnp.block([[Fb, Wb], [zeros, -Fb.T]]) * dt
    E = expm(block)
    Ab = E[:n, :n]
    Qb = E[:n, n:] @ Ab.T
    A = Ab * (d[:, None] / d[None, :])
    Q = Qb * (d[:, None] * d[None, :])
    return A, symmetrise(Q)
