"""Small dense linear-algebra helpers shared by kernels, models and filters.

Everything here is pure JAX and traceable, so the matrices may depend on
parameters that are being sampled or differentiated.

**No LAPACK inside our compiled programs.** The factorisations and solves the
samplers need (:func:`cholesky`, :func:`solve_lower`, :func:`cho_solve`,
:func:`solve`, :func:`inv`, :func:`psd_sqrt`) are written here as short loops
of JAX operations instead of ``jnp.linalg``/``jax.scipy.linalg``, whose CPU
lowering calls LAPACK through jaxlib. In jaxlib 0.10.0 to 0.11.0 a *batched*
LAPACK call (every factorisation vmapped over chains is one) splits its batch
over XLA's intra-op thread pool and blocks its thread until the pieces are
done; when the thunk executor runs such calls on every thread of that pool at
once, nobody is left to run the pieces and the program never finishes. We
caught this with native stacks (gdb) of a hung test: both pool threads
(2 cores) parked in ``BlockingCounter::Wait`` under ``ParallelBatchMap``,
``lapack_dpotrf_ffi``, the main thread in ``BlockUntilReady``; it hung the
project's CI twice. Our matrices are a few states across (at most a few
dozen rows), so these loops cost no more than the library calls, and XLA can
fuse them into the surrounding loops, which it cannot do with a library call
(see ``latentforce.compile``). ``tests/test_linalg.py`` checks them against
NumPy; ``tests/test_cli.py`` checks that the compiled programs of a run of
every sampling method hold no LAPACK call.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

# Pade-13 coefficients and the 1-norm bound for double precision (Higham 2005, Table 2.3)
_PADE13 = np.array(
    [
        64764752532480000.0,
        32382376266240000.0,
        7771770303897600.0,
        1187353796428800.0,
        129060195264000.0,
        10559470521600.0,
        670442572800.0,
        33522128640.0,
        1323241920.0,
        40840800.0,
        960960.0,
        16380.0,
        182.0,
        1.0,
    ]
)
_THETA13 = 5.371920351148152
_MAX_SQUARINGS = 32


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
    P = solve(kron_sum, -W.reshape(-1)).reshape(n, n)
    return symmetrise(P)


def expm(F: Float[Array, "n n"]) -> Float[Array, "n n"]:
    r"""Matrix exponential by scaling and squaring with the degree-13 Padé approximant.

    Higham (2005), Algorithm 2.3 with the order fixed at 13 (accurate to
    double precision for any norm up to :math:`\theta_{13}`; the lower orders
    only save flops, which do not matter for our small matrices) and the
    number of squarings :math:`s = \lceil\log_2(\|F\|_1/\theta_{13})\rceil^+`
    data-dependent (at most 32: NaN beyond, i.e. for norms above about 2e10,
    which only absurd parameter proposals reach and samplers reject). Same result as
    ``jax.scipy.linalg.expm`` to round-off (tested) but a fraction of its
    program: the samplers evaluate transitions at several places of one
    compiled program, and its compile time was dominated by ``expm``.
    Forward-mode differentiable (``jacfwd``), not reverse-mode (a while loop).
    """
    n = F.shape[0]
    norm = jnp.max(jnp.sum(jnp.abs(F), axis=0))
    # s <= _MAX_SQUARINGS (norms up to ~2e10); beyond, and for a non-finite matrix, no
    # squaring and a NaN result (a rejected proposal), never a runaway loop
    s = jnp.ceil(jnp.log2(jnp.maximum(norm, 1e-300) / _THETA13))
    too_big = ~(s <= _MAX_SQUARINGS)
    s = jnp.where(too_big, 0, jnp.maximum(s, 0)).astype(jnp.int32)
    A = F * jnp.exp2(-s.astype(F.dtype))
    b = _PADE13
    eye = jnp.eye(n, dtype=F.dtype)
    A2 = A @ A
    A4 = A2 @ A2
    A6 = A4 @ A2
    U = A @ (A6 @ (b[13] * A6 + b[11] * A4 + b[9] * A2) + b[7] * A6 + b[5] * A4 + b[3] * A2 + b[1] * eye)
    V = A6 @ (b[12] * A6 + b[10] * A4 + b[8] * A2) + b[6] * A6 + b[4] * A4 + b[2] * A2 + b[0] * eye
    R = solve(V - U, V + U)
    # a while loop on s: a fixed-length scan with a conditional squaring (as in jax's
    # expm) compiled 2.5x slower and ran 2x slower
    R = jax.lax.fori_loop(0, s, lambda _, X: X @ X, R)
    return jnp.where(too_big, jnp.nan, R)


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

    def _sweep(_, d):
        scaled = off * (d[None, :] / d[:, None])
        col = jnp.sum(scaled, axis=0)
        row = jnp.sum(scaled, axis=1)
        ok = (col > 0) & (row > 0)
        factor = jnp.where(ok, jnp.sqrt(row / jnp.where(ok, col, 1.0)), 1.0)
        return d * jnp.exp2(jnp.round(jnp.log2(factor)))

    # a loop, not unrolled: each unrolled sweep was a few more kernels to compile
    return jax.lax.fori_loop(0, sweeps, _sweep, jnp.ones(n, dtype=F.dtype))


def expm_balanced(F: Float[Array, "n n"]) -> Float[Array, "n n"]:
    """``expm(F)`` computed on the balanced matrix (see :func:`balance`)."""
    d = balance(F)
    return expm(F * (d[None, :] / d[:, None])) * (d[:, None] / d[None, :])


#: Van Loan's step is halved at most this often (|F| dt up to 2^40)
_MAX_DOUBLINGS = 40


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
    # The block's exponential holds e^{+F^T h} beside e^{F h}: Q = E12 A^T cancels like
    # e^{2|F|h} eps. A step long against the fastest time scale (a force lengthscale of 4 ms at
    # 20 Hz: |F| dt = 22) lost every digit of Q, and the Kalman log-likelihood was 160 nats off
    # with no warning. So the block is exponentiated over h = dt / 2^k with |F| h <= 1 and the
    # step rebuilt by doubling, Q(2h) = Q(h) + A(h) Q(h) A(h)^T: sums of PSD terms, no
    # cancellation (tests/test_kernels.py, against the stationary form P - A P A^T).
    norm = jnp.max(jnp.sum(jnp.abs(Fb), axis=1)) * dt
    k = jnp.ceil(jnp.log2(jnp.maximum(norm, 1.0)))
    k = jnp.where(jnp.isfinite(k), jnp.clip(k, 0, _MAX_DOUBLINGS), 0).astype(jnp.int32)
    h = dt * jnp.exp2(-k.astype(Fb.dtype))
    # Q is linear in W: a W more than 1e6 times F's size is scaled down to it. Its own size is the
    # force's (a Matérn-5/2 force of variance 2500 N^2 and lengthscale 0.01 s has W ~ 7e15): the
    # block's norm, 1.5e11 at 750 Hz, then needed more squarings than expm allows and Q was NaN.
    # Below that W is left as it is: scaling every W to F's size moved a Kalman log-likelihood
    # against the dense Gaussian from within 1e-9 to 1.3e-9 (tests/test_vendor_io.py).
    ratio = jnp.max(jnp.abs(Wb)) / jnp.maximum(jnp.max(jnp.abs(Fb)), 1.0 / h)
    w_scale = jnp.where(ratio > 1e6, ratio, 1.0)
    zeros = jnp.zeros_like(F)
    block = jnp.block([[Fb, Wb / w_scale], [zeros, -Fb.T]]) * h
    E = expm(block)
    Ab = E[:n, :n]
    Qb = E[:n, n:] @ Ab.T

    def _double(_, AQ):
        A_, Q_ = AQ
        return A_ @ A_, Q_ + A_ @ Q_ @ A_.T

    Ab, Qb = jax.lax.fori_loop(0, k, _double, (Ab, symmetrise(Qb)))
    Qb = w_scale * Qb
    A = Ab * (d[:, None] / d[None, :])
    Q = Qb * (d[:, None] * d[None, :])
    return A, symmetrise(Q)


# ---------------------------------------------------------------------------
# Factorisations and solves without LAPACK (module doc). Each works on one
# matrix (and a vector or matrix right-hand side); vmap batches them. They are
# jitted so that a call outside a compiled program reuses one compiled loop
# (inside one they are inlined).
# ---------------------------------------------------------------------------
@jax.jit
def cholesky(A: Float[Array, "n n"]) -> Float[Array, "n n"]:
    r"""Lower Cholesky factor :math:`L L^T = A` of a symmetric positive-definite matrix.

    Column by column (left-looking): column :math:`j` is
    :math:`v = A_{:,j} - L_{:,<j} L_{j,<j}^T`, scaled by :math:`\sqrt{v_j}`
    below the diagonal. Only the lower triangle of ``A`` is read. Like
    ``jnp.linalg.cholesky``, a matrix that is not positive definite (a pivot
    :math:`\le 0` or not finite) gives a matrix of NaN, so a sampler rejects it.
    """
    L, ok = _cholesky_columns(A, semidefinite=False)
    return jnp.where(ok, L, jnp.nan)


@functools.partial(jax.jit, static_argnames="rtol")
def psd_sqrt(A: Float[Array, "n n"], rtol: float = 1e-12) -> Float[Array, "n n"]:
    r"""A square root :math:`S S^T = A` of a symmetric positive *semi*-definite matrix.

    Cholesky without the failure: a pivot at or below ``rtol`` times the
    largest diagonal entry (a direction of zero variance, up to round-off)
    gets a zero column. For a semi-definite matrix the rest of such a column is
    zero too (:math:`|A_{ij}|^2 \le A_{ii} A_{jj}`), so nothing is lost; this is
    what backward sampling needs, whose covariances are often rank-deficient up
    to round-off. Any square root gives the same Gaussian draw :math:`m + S z`.
    """
    S, _ = _cholesky_columns(A, semidefinite=True, rtol=rtol)
    return S


def _cholesky_columns(A, semidefinite: bool, rtol: float = 0.0):
    n = A.shape[-1]
    rows = jnp.arange(n)
    tol = rtol * jnp.max(jnp.abs(jnp.diagonal(A)))

    def column(j, carry):
        L, ok = carry
        v = A[:, j] - L @ L[j, :]  # the columns >= j of L are still zero
        pivot = v[j]
        good = pivot > tol
        d = jnp.sqrt(jnp.where(good, pivot, 1.0))
        col = jnp.where(rows > j, v / d, 0.0) + jnp.where(rows == j, d, 0.0)
        if semidefinite:
            col = jnp.where(good, col, 0.0)
        return L.at[:, j].set(col), ok & good & jnp.isfinite(pivot)

    return jax.lax.fori_loop(0, n, column, (jnp.zeros_like(A), jnp.array(True)))


@functools.partial(jax.jit, static_argnames="transpose")
def solve_lower(L: Float[Array, "n n"], B: Float[Array, "n ..."], transpose: bool = False) -> Float[Array, "n ..."]:
    r"""Solve :math:`L X = B` (or :math:`L^T X = B` with ``transpose``) for lower-triangular ``L``.

    Forward (backward) substitution, one row per step; ``B`` a vector or a matrix.
    """
    n = L.shape[-1]
    U = L.T if transpose else L

    def row(k, X):
        i = n - 1 - k if transpose else k
        # X's rows not yet solved are zero, so the whole row of U may be used
        xi = (B[i] - U[i] @ X) / U[i, i]
        return X.at[i].set(xi)

    return jax.lax.fori_loop(0, n, row, jnp.zeros(B.shape, jnp.result_type(L, B)))


@jax.jit
def cho_solve(L: Float[Array, "n n"], B: Float[Array, "n ..."]) -> Float[Array, "n ..."]:
    r"""Solve :math:`A X = B` given the Cholesky factor ``L`` of :math:`A = L L^T`."""
    return solve_lower(L, solve_lower(L, B), transpose=True)


@jax.jit
def solve(A: Float[Array, "n n"], B: Float[Array, "n ..."]) -> Float[Array, "n ..."]:
    r"""Solve :math:`A X = B` for a general square ``A``: Gauss--Jordan with partial pivoting.

    At step :math:`k` the row with the largest :math:`|a_{ik}|`, :math:`i \ge k`,
    is swapped up, divided by its pivot and subtracted from every other row, on
    ``A`` and ``B`` together. A singular matrix gives infinities or NaN, as
    LAPACK's solve does.
    """
    n = A.shape[-1]
    vector = B.ndim == 1
    dtype = jnp.result_type(A, B)
    M = jnp.concatenate([A.astype(dtype), (B[:, None] if vector else B).astype(dtype)], axis=1)
    rows = jnp.arange(n)

    def eliminate(k, M):
        p = jnp.argmax(jnp.where(rows >= k, jnp.abs(M[:, k]), -1.0))
        top, piv_row = M[k], M[p]
        M = M.at[p].set(top).at[k].set(piv_row)
        row = piv_row / piv_row[k]
        factors = jnp.where(rows == k, 0.0, M[:, k])
        return (M - factors[:, None] * row[None, :]).at[k].set(row)

    X = jax.lax.fori_loop(0, n, eliminate, M)[:, n:]
    return X[:, 0] if vector else X


@jax.jit
def inv(A: Float[Array, "n n"]) -> Float[Array, "n n"]:
    """Inverse of a general square matrix (:func:`solve` with the identity)."""
    return solve(A, jnp.eye(A.shape[-1], dtype=A.dtype))


@jax.jit
def log_abs_det(A: Float[Array, "n n"]) -> Float[Array, ""]:
    r""":math:`\log|\det A|` of a general square matrix: Gaussian elimination with partial pivoting,
    the sum of the pivots' log magnitudes (``-inf`` for a singular matrix, as ``jnp.linalg.slogdet``)."""
    n = A.shape[-1]
    rows = jnp.arange(n)

    def eliminate(k, carry):
        M, acc = carry
        p = jnp.argmax(jnp.where(rows >= k, jnp.abs(M[:, k]), -1.0))
        top, piv_row = M[k], M[p]
        M = M.at[p].set(top).at[k].set(piv_row)
        pivot = piv_row[k]
        factors = jnp.where(rows > k, M[:, k] / jnp.where(pivot == 0, 1.0, pivot), 0.0)
        return M - factors[:, None] * piv_row[None, :], acc + jnp.log(jnp.abs(pivot))

    return jax.lax.fori_loop(0, n, eliminate, (A, jnp.zeros((), A.dtype)))[1]
