r"""Time-invariant linear recurrences over long records, in blocks.

In steady state the Kalman filter's and the RTS smoother's means obey
recurrences with constant matrices,

.. math:: x_t = F x_{t-1} + u_t, \qquad t = 0, \dots, T-1,

(``u`` the data's contribution, or a backward-sampling draw's noise). A
``lax.scan`` over ``T`` steps does a few vector operations per step and is
bound by XLA's per-step cost, not by arithmetic; on long records it also
runs outside XLA CPU's merged small loops (:mod:`latentforce.compile`), at a
few microseconds per operation per step. Cut the record into ``nb`` blocks
of ``L`` steps: the recurrence from a zero start runs inside every block at
once (``L`` steps on ``nb`` rows), the blocks' starting states follow from
one another (``nb`` steps, with :math:`F^L`), and each block adds its start
propagated by the powers :math:`F^{j+1}` (one matrix product). The same
:math:`O(T n^2)` arithmetic in about :math:`2\sqrt T` dependent steps
instead of :math:`T`; the result is the scan's to rounding (the powers are
formed by repeated products, exact to a few ulps times ``L`` for a stable
``F``). Differentiable in forward and reverse mode.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float


def block_length(T: int) -> int:
    """Steps per block: about :math:`\\sqrt T` (fewest dependent steps), at least 1."""
    return max(1, int(math.ceil(math.sqrt(T))))


def linear_recurrence(
    F: Float[Array, "n n"],
    u: Float[Array, "T n"],
    x_init: Float[Array, " n"],
    *,
    reverse: bool = False,
    block: int | None = None,
) -> Float[Array, "T n"]:
    r"""All states of :math:`x_t = F x_{t-1} + u_t` (``t = 0..T-1``) from :math:`x_{-1}` = ``x_init``.

    ``reverse``: :math:`x_t = F x_{t+1} + u_t` from :math:`x_T` = ``x_init``.
    ``block``: steps per block (default :func:`block_length`).
    """
    if reverse:
        return linear_recurrence(F, u[::-1], x_init, block=block)[::-1]
    T, n = u.shape
    L = block_length(T) if block is None else int(block)
    nb = -(-T // L)
    U = jnp.concatenate([u, jnp.zeros((nb * L - T, n), u.dtype)]).reshape(nb, L, n)

    # Inside every block at once, from a zero start: z[b, j] = F z[b, j-1] + U[b, j].
    def inner(z, u_j):
        z = z @ F.T + u_j
        return z, z

    z_end, Z = jax.lax.scan(inner, jnp.zeros((nb, n), u.dtype), jnp.swapaxes(U, 0, 1))
    Z = jnp.swapaxes(Z, 0, 1)  # (nb, L, n)

    # Powers F^(j+1), j = 0..L-1.
    def power(P, _):
        P = F @ P
        return P, P

    FL, powers = jax.lax.scan(power, jnp.eye(n, dtype=F.dtype), None, length=L)

    # The state before each block: s_0 = x_init, s_{b+1} = F^L s_b + z[b, L-1].
    def outer(s, z_last):
        return FL @ s + z_last, s

    _, S = jax.lax.scan(outer, x_init, z_end)
    X = jnp.einsum("jik,bk->bji", powers, S) + Z
    return X.reshape(nb * L, n)[:T]
