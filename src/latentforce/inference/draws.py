r"""Resampling schemes and the particle methods' random draws.

Resampling maps ``(key, log_weights, n)`` to ancestor indices (multinomial,
systematic, stratified) by the inverse CDF; the normal and uniform draws are
float32 from raw 32-bit words (:func:`uniform32`, :func:`box_muller`, with a
polynomial :func:`unit_circle`): the sweep's draws dominated its cost in
float64 (:mod:`latentforce.inference.pgas` module doc). Split from
:mod:`latentforce.inference.smc`, which re-exports them.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int


# ---------------------------------------------------------------------------
# Resampling: (key, log_weights, n) -> indices
# ---------------------------------------------------------------------------
def _points(scheme: str, u: Float[Array, " n"]) -> Float[Array, " n"]:
    """Map ``n`` i.i.d. U(0,1) draws to the scheme's points in [0, 1)."""
    n = u.shape[-1]
    if scheme == "multinomial":
        return u
    if scheme == "stratified":
        return (jnp.arange(n) + u) / n
    if scheme == "systematic":
        return (jnp.arange(n) + u[..., :1]) / n
    raise ValueError(f"unknown resampling scheme {scheme!r}; valid: {RESAMPLING}")


def _inverse_cdf(log_weights: Float[Array, " N"], points: Float[Array, " n"]) -> Int[Array, " n"]:
    """Indices ``i`` with ``cdf[i-1] <= p < cdf[i]`` for the normalised weights."""
    w = jnp.exp(log_weights - jnp.max(log_weights))
    cdf = jnp.cumsum(w)
    # compare_all is the fastest search for the few dozen particles we use on CPU.
    idx = jnp.searchsorted(cdf, points * cdf[-1], side="right", method="compare_all")
    return jnp.minimum(idx, log_weights.shape[0] - 1).astype(jnp.int32)


def _resampler(scheme: str):
    def resample(key: Array, log_weights: Float[Array, " N"], n: int) -> Int[Array, " n"]:
        u = jax.random.uniform(key, (n,), dtype=log_weights.dtype)
        return _inverse_cdf(log_weights, _points(scheme, u))

    resample.__name__ = scheme
    resample.__doc__ = (
        f"{scheme.capitalize()} resampling: ``n`` ancestor indices drawn with probabilities "
        "proportional to ``exp(log_weights)`` (unnormalised log weights accepted)."
    )
    return resample


multinomial = _resampler("multinomial")
systematic = _resampler("systematic")
stratified = _resampler("stratified")
RESAMPLING = {"multinomial": multinomial, "systematic": systematic, "stratified": stratified}


_TWO_M32 = 2.0**-32


def uniform32(key: Array, shape: tuple, dtype=float) -> Float[Array, "..."]:
    """Uniforms on ``(0, 1)`` from one 32-bit word each: ``(b + 1/2) 2^-32``.

    In double precision exactly representable and never 0 or 1. Half the random
    bits of ``jax.random.uniform`` in double precision (which uses 64 per
    number); a resampling point needs no finer grid than ``2^-32``. In single
    precision the values are rounded: never 0, but the largest words round to 1.
    """
    return _unit_interval(jax.random.bits(key, shape, jnp.uint32), dtype)


def _unit_interval(words: Array, dtype) -> Array:
    """``(b + 1/2) 2^-32`` of 32-bit words ``b``: :func:`uniform32`'s map to ``(0, 1)``."""
    return (words.astype(dtype) + 0.5) * _TWO_M32


# Taylor coefficients of sin (x, x^3, ..., x^11) and cos (1, x^2, ..., x^12): on [0, pi/2]
# the first omitted terms are below 6e-8, the single-precision rounding of the result
_SIN_TAYLOR = tuple((-1.0) ** k / math.factorial(2 * k + 1) for k in range(6))
_COS_TAYLOR = tuple((-1.0) ** k / math.factorial(2 * k) for k in range(7))


def _even_poly(coefs, x2):
    acc = np.float32(coefs[-1])
    for c in coefs[-2::-1]:
        acc = acc * x2 + np.float32(c)
    return acc


def unit_circle(words: Array) -> tuple[Array, Array]:
    r"""``(cos phi, sin phi)`` in single precision for the uniform angle each 32-bit word encodes.

    The top two bits pick the quadrant ``q``, the other 30 the angle
    :math:`\psi \in [0, \pi/2)` within it: :math:`\phi = q\pi/2 + \psi`.
    Sine and cosine of :math:`\psi` are Taylor polynomials (within 2.5e-7
    of the exact values; tested); the quadrant only swaps and negates them.
    XLA's CPU sine and cosine reduce any argument, which costs about 5 ns a
    value here against well under 1 ns for the polynomials.
    """
    q = words >> np.uint32(30)
    psi = (words & np.uint32(0x3FFFFFFF)).astype(jnp.float32) * np.float32(0.5 * math.pi * 2.0**-30)
    psi2 = psi * psi
    s, c = psi * _even_poly(_SIN_TAYLOR, psi2), _even_poly(_COS_TAYLOR, psi2)
    odd = (q & np.uint32(1)) == 1
    x, y = jnp.where(odd, s, c), jnp.where(odd, c, s)
    return jnp.where((q == 1) | (q == 2), -x, x), jnp.where(q >= 2, -y, y)


def box_muller(key: Array, shape: tuple, dtype=float) -> Float[Array, "..."]:
    """Standard normals by the Box-Muller transform, one 32-bit word per normal.

    The transform runs in single precision and the result is cast to
    ``dtype``: on CPU the double-precision logarithm and sine/cosine cost
    several times their single-precision versions, and the random bits
    themselves (about 10 ns a word here) are half those of double-precision
    uniforms. The angle's cosine and sine come from :func:`unit_circle`.
    Each value is within a few 1e-6 (single-precision rounding) of the exact
    transform of its words, and the tail beyond 6.76 sd (probability
    1.4e-11, where the radius's uniform reaches its smallest value ``2^-33``)
    is cut: far below any Monte-Carlo error of the sampler.
    At T = 1024, N = 50 the sweep's random numbers cost about 4.4 ms in
    double precision (a third of a sweep).
    """
    n = math.prod(shape)
    half = -(-n // 2)
    words = jax.random.bits(key, (2, half), jnp.uint32)
    u = _unit_interval(words[0], jnp.float32)  # may round to 1: a zero radius
    r = jnp.sqrt(-2.0 * jnp.log(u))
    cos, sin = unit_circle(words[1])
    z = jnp.concatenate([r * cos, r * sin])[:n]
    return z.astype(dtype).reshape(shape)


def effective_sample_size(log_weights: Float[Array, " N"]) -> Float[Array, ""]:
    """ESS :math:`1 / \\sum_i \\bar w_i^2` of (unnormalised) log weights."""
    lw = log_weights - jax.scipy.special.logsumexp(log_weights)
    return jnp.exp(-jax.scipy.special.logsumexp(2.0 * lw))
