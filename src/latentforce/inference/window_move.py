r"""The window move: the smoother move on one window of a long record at a time.

The smoother move (:mod:`latentforce.inference.smoother_move`) proposes a whole new path from
the model linearised about a centre and accepts it on the exact/linearised weight of the whole
path. The log weight's variance grows with the record (each sample adds its share of the
expansion's error), so its acceptance falls with T: on a Duffing record with a displacement
channel (Matérn-3/2) 0.96 at T = 256, 0.66 at 1 024 and 0.24 at 4 096, and the worst bulk ESS
of 1 000 iterations fell from 624 to 11 (``docs/nonlinear.md``). This move renews the path a
window at a time, with an acceptance set by the window's length, not the record's.

Write the latent path by its whitened innovations :math:`\varepsilon` (``latent.whiten``; prior
:math:`N(0, I)`). A window :math:`W = [s, s + w)` lies in a *segment* :math:`[a, a + L)`,
:math:`L` = ``width`` + ``tail`` samples (clipped to the record). The proposal for
:math:`\varepsilon_W` given everything else is the posterior of a local linear-Gaussian model:

* the state just before the segment is the current path's, :math:`x_{a-1}` (a function of
  :math:`\varepsilon_{<a}`, which the move holds; the record's own initial distribution where
  :math:`a = 0`);
* inside the segment the transition is expanded, :math:`x_t = F_t x_{t-1} + e_t + B_t
  \varepsilon_t`, with the innovations outside the window held at their current values (known
  inputs) and those inside free; the expansion point is the fixed centre re-centred by
  ``iterations`` Gauss-Newton steps on the window's innovations given the held ones (the
  conditional mode of the expanded model, rolled out through the exact transition): a function of
  the held innovations alone, so the proposal below is one fixed density given them;
* the sensors over the segment are expanded about the centre, their noise the channels' own;
  data after the segment are not seen.

With :math:`\tilde\ell(\varepsilon)` that model's likelihood of the segment's data, the proposal
is :math:`\tilde q(\varepsilon_W \mid \varepsilon_{-W}) \propto N(\varepsilon_W; 0, I)\,
\tilde\ell(\varepsilon)`, and for the target :math:`\pi(\varepsilon) \propto N(\varepsilon; 0,
I)\, p(y \mid \mathrm{path}(\varepsilon))` the Metropolis-Hastings ratio is

.. math:: \frac{w(\varepsilon')}{w(\varepsilon)}, \qquad
          w(\varepsilon) = \frac{p(y \mid \mathrm{path}(\varepsilon))}{\tilde\ell(\varepsilon)}

(the prior of the window and the proposal's normalising constant, both functions of
:math:`\varepsilon_{-W}` alone, cancel), exact for any system and any segment: the exact path is
rebuilt over the whole record. Its log changes only where the path changes: the window, and
after it the response's decay (the state at the window's end differs, the innovations after it
do not), which the segment's tail lets the proposal follow. A Crank-Nicolson step about the
proposal's mean (``betas`` < 1; :mod:`~latentforce.inference.smoother_move`, "Crank-Nicolson
steps") is reversible with respect to :math:`\tilde q` and has the same ratio.

The draw is the simulation smoother of Durbin & Koopman (2002) on the segment (as
:func:`smoother_move._draw` on the record): innovations :math:`\varepsilon^*` in the window and a
record :math:`y^*` simulated through the local model, then
:math:`\varepsilon^* - \hat\varepsilon(y^*) + \hat\varepsilon(y)`, the smoothed innovations from
the covariance recursion (with the noise loading zeroed outside the window) and the backward
recursion :math:`r_{t-1} = H_t^\top S_t^{-1} v_t + L_t^\top r_t`.

One call makes ``ceil(T / width) + 1`` window steps, windows of ``width`` samples laid end to
end from a random offset (so that every sample is renewed, and window edges fall anywhere),
one after another. A step costs, over the segment, ``iterations + 1`` expansions, covariance
recursions and pairs of mean passes, and the draw's simulated record and its smoothing; over the
record, one rebuild of the path (the weight).

Why the tail is long (``docs/nonlinear.md``, "Long records: the window move"): holding the
innovations after the window holds the future *input*, not the future path, so a new state at the
window's end is carried through the rest of the record by the dynamics; a damped linear structure
forgets it within a few decay times, the stiffening Duffing of the calibration records did not
(a perturbation 500 samples on was as large as at the start), and with a short tail the data after
the segment put up to 430 nats of spread into some windows' log weights.

For a linear system with the tail reaching the record's end the expansion is exact, every step
is accepted, and each is an exact Gibbs draw of the window (tested, every Matérn order).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from latentforce.inference import particle_model
from latentforce.inference.latent import ObservationDensity, colour, observation_log_likelihood, whiten
from latentforce.inference.smoother_move import noise_factors
from latentforce.linalg import cho_solve, cholesky, symmetrise

#: folded into a chain's key for the window move's random numbers (its own stream)
WINDOW_STREAM = 0x5700
#: samples per window (module doc)
WIDTH = 256
#: samples after a window whose data its proposal sees (module doc)
TAIL = 1024
#: Gauss-Newton steps re-centring a segment's expansion (module doc)
RECENTRE = 2


class Segment(NamedTuple):
    """One segment of the expanded model, with its window and the current innovations (module doc).
    The transition is indexed by the sample it leads *into*: ``x_t = F_t x_{t-1} + u_t + B_t eps_t``."""

    F: Float[Array, "L n n"]  # zero at the record's first sample
    u: Float[Array, "L n"]  # the expansion's constant plus the held innovations' share (the initial mean at t = 0)
    B: Float[Array, "L n nl"]  # the free innovations' loading (zero outside the window)
    Hm: Float[Array, "L d n"]  # the sensors' Jacobian, the missing channels' rows zeroed
    d: Float[Array, "L d"]  # y_t = H_t x_t + d_t + noise (zero on missing channels)
    y: Float[Array, "L d"]
    mask: Float[Array, "L d"]
    Rinv: Float[Array, "L d d"]
    const: Float[Array, " L"]
    x_prev: Float[Array, " n"]  # the current path's state before the segment (unused at a = 0)
    win: Float[Array, " L"]  # 1 inside the window
    eps: Float[Array, "L nl"]  # the current innovations over the segment


class _Frame(NamedTuple):
    """What a segment's expansions share: where it is, its data, the held innovations."""

    t: Array  # the segment's sample indices
    first: Array  # 1.0 at the record's first sample
    Bfull: Float[Array, "L n nl"]  # every innovation's loading (L1 at the record's first sample, else Lq)
    held: Float[Array, "L n"]  # the held innovations' share of each state
    m1: Float[Array, " n"]
    x_prev: Float[Array, " n"]
    win: Float[Array, " L"]
    eps: Float[Array, "L nl"]
    y: Float[Array, "L d"]
    mask: Float[Array, "L d"]
    Rinv: Float[Array, "L d d"]
    const: Float[Array, " L"]


def _frame(pm, tr, od: ObservationDensity, path, eps, start, width: int, length: int) -> tuple[_Frame, Array]:
    """The frame of the segment holding the window ``[start, start + width)`` (clipped to the record;
    ``start`` may be negative), ``length`` samples from ``a = clip(start, 0, T - length)``."""
    T = eps.shape[0]
    a = jnp.clip(start, 0, T - length)
    t = a + jnp.arange(length)
    win = ((t >= start) & (t < start + width)).astype(eps.dtype)

    def sl(x):
        return jax.lax.dynamic_slice_in_dim(x, a, length, axis=0)

    L1, Lq = noise_factors(pm, tr)
    eps_s = sl(eps)
    Bfull = jnp.where((t == 0)[:, None, None], L1, Lq)
    held = jnp.einsum("tij,tj->ti", Bfull, eps_s * (1.0 - win)[:, None])
    m1 = jnp.concatenate([pm.mech0_mean, jnp.zeros(pm.nfx)])
    x_prev = path[jnp.maximum(a - 1, 0)]
    first = (t == 0).astype(eps.dtype)
    frame = _Frame(t, first, Bfull, held, m1, x_prev, win, eps_s, sl(od.y), sl(od.maskf), sl(od.Rinv), sl(od.const))
    return frame, a


def _expand(pm, tr, fr: _Frame, c: Float[Array, "L n"]) -> Segment:
    """The segment's model expanded about ``c``: each transition about the state it leaves (the
    current path's ``x_prev`` for the first, which is known), each sensor about ``c_t``."""

    def f(x):
        return pm.state_step(tr, x)

    prev = jnp.concatenate([fr.x_prev[None], c[:-1]])
    F = jax.vmap(jax.jacfwd(f))(prev)
    e = jax.vmap(f)(prev) - jnp.einsum("tij,tj->ti", F, prev)
    first = fr.first[:, None]
    F = F * (1.0 - first)[:, :, None]
    e = e * (1.0 - first) + fr.m1 * first
    H = jax.vmap(jax.jacfwd(pm.readout))(c) * fr.mask[:, :, None]
    d = (jax.vmap(pm.readout)(c) - jnp.einsum("tij,tj->ti", H, c)) * fr.mask
    return Segment(
        F, e + fr.held, fr.Bfull * fr.win[:, None, None], H, d, fr.y, fr.mask, fr.Rinv, fr.const,
        fr.x_prev, fr.win, fr.eps,
    )  # fmt: skip


def _rollout(pm, tr, fr: _Frame, eps_w) -> Float[Array, "L n"]:
    """The exact states over the segment with the window's innovations ``eps_w`` (zero outside it)."""
    noise = fr.held + jnp.einsum("tij,tj->ti", fr.Bfull * fr.win[:, None, None], eps_w)

    def _step(x, inp):
        q, first = inp
        nxt = jnp.where(first > 0, fr.m1, pm.state_step(tr, x)) + q
        return nxt, nxt

    _, xs = jax.lax.scan(_step, fr.x_prev, (noise, fr.first))
    return xs


def segment(pm, tr, od: ObservationDensity, centre, path, eps, start, width: int, length: int, iterations: int = 0):
    """``(segment, a)``: the segment holding the window ``[start, start + width)`` (:func:`_frame`),
    expanded about ``centre`` re-centred by ``iterations`` Gauss-Newton steps on the window's
    innovations given the held ones (module doc): a function of the innovations outside the window."""
    fr, a = _frame(pm, tr, od, path, eps, start, width, length)
    c = jax.lax.dynamic_slice_in_dim(centre, a, length, axis=0)

    def _gn(c, _):
        seg = _expand(pm, tr, fr, c)
        return _rollout(pm, tr, fr, _smoothed_eps(seg, _gains(seg, od.R), seg.y)), None

    c, _ = jax.lax.scan(_gn, c, None, length=int(iterations))
    return _expand(pm, tr, fr, c), a


class _SegmentGains(NamedTuple):
    Sinv: Float[Array, "L d d"]
    M: Float[Array, "L n d"]


def _gains(seg: Segment, R) -> _SegmentGains:
    """The segment's covariance recursion: the state before it known, the noise only in the window."""

    def _step(P_f, inp):
        F, B, H, m = inp
        P = symmetrise(F @ P_f @ F.T + B @ B.T)
        S = symmetrise(H @ P @ H.T + R) * jnp.outer(m, m) + jnp.diag(1.0 - m)
        Sinv = cho_solve(cholesky(S), jnp.eye(S.shape[0])) * jnp.outer(m, m)
        M = P @ H.T @ Sinv
        return symmetrise(P - M @ H @ P), (Sinv, M)

    n = seg.x_prev.shape[0]
    _, (Sinv, M) = jax.lax.scan(_step, jnp.zeros((n, n)), (seg.F, seg.B, seg.Hm, seg.mask))
    return _SegmentGains(Sinv, M)


def _smoothed_eps(seg: Segment, gains: _SegmentGains, y) -> Float[Array, "L nl"]:
    r""":math:`\hat\varepsilon` of the window given the segment's data ``y`` (zero outside the window)."""

    def _forward(a_f, inp):
        F, u, H, d, M, y_t = inp
        a = F @ a_f + u
        v = y_t - H @ a - d
        return a + M @ v, v

    _, v = jax.lax.scan(_forward, seg.x_prev, (seg.F, seg.u, seg.Hm, seg.d, gains.M, y))
    F_next = jnp.concatenate([seg.F[1:], jnp.zeros_like(seg.F[:1])])

    def _backward(r, inp):
        v_t, F_n, H, M, Sinv = inp
        r_prev = H.T @ (Sinv @ v_t) + (F_n @ (jnp.eye(F_n.shape[0]) - M @ H)).T @ r
        return r_prev, r_prev

    inputs = (v, F_next, seg.Hm, gains.M, gains.Sinv)
    _, r_prev = jax.lax.scan(_backward, jnp.zeros_like(seg.x_prev), inputs, reverse=True)
    return jnp.einsum("tij,ti->tj", seg.B, r_prev)


def _linear_path(seg: Segment, eps_w) -> Float[Array, "L n"]:
    """The local model's states over the segment with the window's innovations ``eps_w`` (zero outside it)."""

    def _step(x, inp):
        F, u, B, e = inp
        nxt = F @ x + u + B @ e
        return nxt, nxt

    _, xs = jax.lax.scan(_step, seg.x_prev, (seg.F, seg.u, seg.B, eps_w))
    return xs


def _linear_log_likelihood(seg: Segment, eps_w) -> Float[Array, ""]:
    r""":math:`\log\tilde\ell`: the local model's log density of the segment's data."""
    x = _linear_path(seg, eps_w)
    r = (seg.y - jnp.einsum("tij,tj->ti", seg.Hm, x) - seg.d) * seg.mask
    return jnp.sum(seg.const) - 0.5 * jnp.einsum("ti,tij,tj->", r, seg.Rinv, r)


def window_draw(key, seg: Segment, gains: _SegmentGains, R, eps_hat) -> Float[Array, "L nl"]:
    """One draw of the window's innovations from the proposal (zero outside the window; module doc)."""
    k_eps, k_obs = jax.random.split(key)
    L, nl = seg.eps.shape
    eps_star = jax.random.normal(k_eps, (L, nl)) * seg.win[:, None]
    x_star = _linear_path(seg, eps_star)
    # each channel its own stream, as smoother_move._draw_eps
    z = jax.vmap(lambda i: jax.random.normal(jax.random.fold_in(k_obs, i), (L,)), out_axes=1)(
        jnp.arange(seg.y.shape[1])
    )
    y_star = (jnp.einsum("tij,tj->ti", seg.Hm, x_star) + seg.d + z @ cholesky(symmetrise(R)).T) * seg.mask
    return eps_star - _smoothed_eps(seg, gains, y_star) + eps_hat


def proposal(key, seg: Segment, R, beta=1.0) -> Float[Array, "L nl"]:
    """The proposed innovations over the segment: a Crank-Nicolson step of size ``beta`` about the
    proposal's mean in the window (1: a draw of it), the current ones outside."""
    gains = _gains(seg, R)
    eps_hat = _smoothed_eps(seg, gains, seg.y)
    draw = window_draw(key, seg, gains, R, eps_hat)
    cur = seg.eps * seg.win[:, None]
    step = eps_hat + jnp.sqrt(1.0 - beta**2) * (cur - eps_hat) + beta * (draw - eps_hat)
    return jnp.where(seg.win[:, None] > 0, step, seg.eps)


def n_windows(T: int, width: int) -> int:
    """Window steps per call: enough windows of ``width`` laid end to end from any offset to cover ``T``."""
    return math.ceil(T / width) + 1


def window_starts(key, T: int, width: int) -> Array:
    """The first samples of one call's :func:`n_windows` windows: laid end to end from a random
    offset in ``[0, width)``, the first starting ``width`` earlier (before the record, clipped)."""
    return jax.random.randint(key, (), 0, width) + width * (jnp.arange(n_windows(T, width)) - 1)


def window_move(
    key,
    pm: particle_model.ParticleModel,
    tr,
    od: ObservationDensity,
    centre,
    path: Float[Array, "T n"],
    width: int = WIDTH,
    tail: int = TAIL,
    betas=(1.0,),
    iterations: int = RECENTRE,
) -> tuple[Float[Array, "T n"], Float[Array, " k"]]:
    """One pass of window steps over the record (module doc): windows of ``width`` samples from a
    random offset, each proposal seeing ``tail`` samples after its window; step ``k`` a
    Crank-Nicolson step of size ``betas[k % len(betas)]``. Returns the new path and each step's
    acceptance (bool). The record must be longer than ``width``."""
    T = path.shape[0]
    width = int(width)
    if not 0 < width < T:
        raise ValueError(f"the window move needs 0 < width < T, got width {width} and T {T}")
    length = min(T, width + int(tail))
    K = n_windows(T, width)
    k_off, k_steps = jax.random.split(key)
    starts = window_starts(k_off, T, width)
    beta = jnp.asarray([float(betas[k % len(betas)]) for k in range(K)])
    eps0 = whiten(tr, pm.latent(path))
    ll0 = observation_log_likelihood(pm, od, path)

    def _step(carry, inp):
        x, eps, ll = carry
        s, b, k = inp
        k_prop, k_acc = jax.random.split(k)
        seg, a = segment(pm, tr, od, centre, x, eps, s, width, length, iterations)
        eps_seg = proposal(k_prop, seg, od.R, b)
        eps_p = jax.lax.dynamic_update_slice_in_dim(eps, eps_seg, a, axis=0)
        x_p = pm.path(colour(tr, eps_p))
        ll_p = observation_log_likelihood(pm, od, x_p)
        log_ratio = ll_p - _linear_log_likelihood(seg, eps_seg * seg.win[:, None]) - ll
        log_ratio += _linear_log_likelihood(seg, seg.eps * seg.win[:, None])
        ok = jnp.isfinite(log_ratio) & (jnp.log(jax.random.uniform(k_acc)) < log_ratio)
        return (jnp.where(ok, x_p, x), jnp.where(ok, eps_p, eps), jnp.where(ok, ll_p, ll)), ok

    (out, _, _), acc = jax.lax.scan(_step, (path, eps0, ll0), (starts, beta, jax.random.split(k_steps, K)))
    return out, acc
