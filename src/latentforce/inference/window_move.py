r"""The window move: a bridge through one window of a long record at a time, the path after it held.

The smoother move (:mod:`latentforce.inference.smoother_move`) proposes a whole new path from
the model linearised about a centre and accepts it on the exact/linearised weight of the whole
path. The log weight's variance grows with the record (each sample adds its share of the
expansion's error), so its acceptance falls with T: on a Duffing record with a displacement
channel (Matérn-3/2) 0.96 at T = 256, 0.66 at 1 024 and 0.24 at 4 096, and the worst bulk ESS
of 1 000 iterations fell from 624 to 11 (``docs/nonlinear.md``). This move renews the path a
window at a time, with an acceptance set by the window's length, not the record's.

The model is :math:`x_t = f(x_{t-1}) + L_Q \varepsilon_t` in the state's order
(``smoother_move.noise_factors``; :math:`x_0 = m_1 + L_1\varepsilon_0`), the whitened
innovations :math:`\varepsilon` with prior :math:`N(0, I)`. A window :math:`W = [a, b]`,
``width`` samples, is renewed given the states before it *and after it*: the conditional target is

.. math:: \pi(\varepsilon_W) \propto N(\varepsilon_W; 0, I)\, N(\varepsilon_{b+1}; 0, I)
          \prod_{t \in W} p(y_t \mid x_t),
          \qquad \varepsilon_{b+1} = L_Q^{-1}(x_{b+1} - f(x_b)),

the path rolled out exactly from the current :math:`x_{a-1}` through the window, :math:`x_{b+1}`
and every state after it held (so the data after the window do not enter; where :math:`b` is the
record's last sample there is no :math:`\varepsilon_{b+1}` term).

**Proposal.** The window's model expanded about the centre (re-centred by ``iterations``
Gauss-Newton steps given the held ends: a function of them alone), its sensors with the channels'
noise, and one more observation at :math:`b`, the *pin* :math:`L_Q^{-1}(x_{b+1} - e) =
L_Q^{-1} F x_b + \varepsilon_{b+1}` (the transition into the held state expanded about the
centre's :math:`x_b`, noise :math:`N(0, I)`). Its posterior :math:`\tilde q(\varepsilon_W)
\propto N(\varepsilon_W; 0, I)\,\tilde\ell(\varepsilon_W)` (:math:`\tilde\ell` the expanded
likelihood of the window's data and the pin) is drawn by the simulation smoother of Durbin &
Koopman (2002), as the smoother move does on the record.

**Why a correction.** The mechanical states' within-step noise is small (the displacement's sd
2e-5 m at the calibration Duffing's 256 Hz), and the exact end state :math:`x_b` of a draw differs
from the expanded model's by the expansion's error accumulated over the window: amplified by
:math:`L_Q^{-1}`, that error put a spread of 8-34 nats into the pin term of some windows' log
weights (T = 4 096, windows of 256; acceptance 0). So the draw :math:`\varepsilon` is mapped to
:math:`\varepsilon' = \Phi(\varepsilon) = \varepsilon + D u`, with :math:`D = J^\top` (:math:`J`
the expanded model's Jacobian of the mechanical part of :math:`x_b` in :math:`\varepsilon_W`,
constant) and :math:`u` solved by Newton so that the exact path's mechanical :math:`x_b` is the
expanded one's: the force then moves a little across the window to steer the structure to where
the Gaussian put it. The inverse is explicit (the expansion is affine):
:math:`\Phi^{-1}(\varepsilon') = \varepsilon' - D (JD)^{-1} (m_\mathrm{lin}(\varepsilon') -
m_\mathrm{ex}(\varepsilon'))`, and its Jacobian determinant :math:`\det(J_\mathrm{ex}(\varepsilon')
D)/\det(JD)` (the matrix determinant lemma; :math:`J_\mathrm{ex}` the exact path's Jacobian, by
forward-mode along the ``nm`` columns of :math:`D`). The proposal in :math:`\varepsilon'` is
:math:`q'(\varepsilon') = \tilde q(\Phi^{-1}(\varepsilon'))\,|\det D\Phi^{-1}(\varepsilon')|`, and
the Metropolis-Hastings ratio :math:`\exp(w(\varepsilon'_\mathrm{new}) - w(\varepsilon'_\mathrm{cur}))`
with

.. math:: w(\varepsilon') = \log\pi(\varepsilon') - \log\tilde q(\Phi^{-1}(\varepsilon'))
          - \log|\det(J_\mathrm{ex}(\varepsilon') D)|,

exact for any system. A proposal whose Newton solve did not close (:math:`\Phi^{-1}(\Phi(\varepsilon))`
off :math:`\varepsilon` by more than :data:`INVERSE_TOL`) is rejected; the current path's
pre-image is always the explicit :math:`\Phi^{-1}`. (Exactness needs :math:`\Phi` to be the
inverse of :math:`\Phi^{-1}` on the proposals made, i.e. Newton's root the one near :math:`u = 0`;
the corrections are small, a few per cent of the window's force variation.) With ``betas`` < 1 the
draw is a Crank-Nicolson step about :math:`\tilde q`'s mean from :math:`\Phi^{-1}` of the current
innovations, reversible with respect to :math:`\tilde q` (same ratio).

Measured (``docs/nonlinear.md``, "Long records: the window move"; ``benchmarks/long_record.py``):
on the T = 4 096 Duffing record (acc + disp, Matérn-3/2) windows of 256 accepted 0.94-0.98 of
draws from near the posterior, where the pin without the correction accepted none at some windows;
in the sampler (1 000 iterations after 500) the worst bulk ESS was 431 and R-hat 1.008 in 97 s,
against 11 / 1.31 in 63 s without the move and 58 / 1.06 in 119 s with the first design (the
innovations after the window held instead of the path, which needed tails of 1 024 samples and a
rebuild of the record per step); "auto" converged in 137 s where both stopped at the 600 s cap.
A step costs the window's work alone. Acceleration alone is not helped (the expansion itself is
poor there).

For a linear system the expansion is exact, :math:`\Phi` the identity, every step accepted and
each an exact Gibbs draw of the window given the rest (tested, every Matérn order).

**Numerical limit.** The pin and the target's last term divide by the within-step noise's factor
:math:`L_Q`, whose condition number grows with the force's smoothness, the sampling rate and the
number of mechanical states driven by one force (Duffing at 256 Hz: 2e5 at Matérn-1/2, 2e8 at 3/2,
3e11 at 5/2; a 3-storey frame at 100 Hz, Matérn-3/2: 5e14). Past about 1e12 the covariance
recursion with the pin loses the precision the weights need: on linear dynamics, where every step
must be accepted, the Bouc-Wen oscillator without hysteresis accepted every step at 3.5e11 but 45 %
at 8.4e14 (its weights then noise of thousands of nats, the pin innovations of proposals 1e7), the
frame likewise at 4.8e14, while the linear SDOF at 2e11 accepted all. So the move is made only where
the condition number is at most :data:`COND_MAX` (1e12; :func:`well_conditioned`, evaluated at each
call's transition: elsewhere every step is rejected), and the default
(``pgas_defaults.default_window``) turns it on only where the starting transition passes. A pin
split along :math:`L_Q`'s singular directions (the stiff ones as exact constraints the correction
meets) would lift the limit; not built.

One call makes ``ceil(T / width) + 1`` window steps, windows laid end to end from a random offset
(clipped into the record: those at its ends overlap their neighbours), one after another.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from latentforce.inference import particle_model
from latentforce.inference.latent import ObservationDensity, observation_log_likelihood, whiten
from latentforce.inference.smoother_move import noise_factors
from latentforce.linalg import cho_solve, cholesky, symmetrise

#: folded into a chain's key for the window move's random numbers (its own stream)
WINDOW_STREAM = 0x5700
#: samples per window (module doc)
WIDTH = 256
#: Gauss-Newton steps re-centring a window's expansion (module doc)
RECENTRE = 2
#: Newton steps of the end-state correction (module doc; from u = 0 the residual fell to 1e-15 in 3)
NEWTON = 4
#: largest ``|Phi^-1(Phi(eps)) - eps|`` (whitened units) of an accepted proposal (module doc)
INVERSE_TOL = 1e-8
#: largest condition number of ``L_Q`` at which the move is made (module doc, "Numerical limit")
COND_MAX = 1e12


class Noise(NamedTuple):
    """The latent's noise factors in the state's order and the inverse of the later steps' factor."""

    L1: Float[Array, "n nl"]
    Lq: Float[Array, "n nl"]
    Lq_inv: Float[Array, "nl n"]


def noise(pm, tr) -> Noise:
    """The :class:`Noise` of transition ``tr`` (once per call of :func:`window_move`)."""
    L1, Lq = noise_factors(pm, tr)
    return Noise(L1, Lq, jnp.linalg.inv(Lq))


def well_conditioned(pm, tr) -> Array:
    """Whether the move is made at transition ``tr``: ``L_Q``'s condition number at most
    :data:`COND_MAX` (module doc, "Numerical limit")."""
    s = jnp.linalg.svd(noise_factors(pm, tr)[1], compute_uv=False)
    return jnp.max(s) <= COND_MAX * jnp.min(s)


class Frame(NamedTuple):
    """A window's place in the record, its data and the held states at its ends."""

    first: Array  # 1.0 at the record's first sample
    B: Float[Array, "W n nl"]  # each innovation's loading (L1 at the record's first sample, else Lq)
    m1: Float[Array, " n"]
    x_prev: Float[Array, " n"]  # the current path's state before the window (unused at a = 0)
    x_next: Float[Array, " n"]  # the held state after it
    pin: Array  # 1.0 where the window ends before the record does
    eps: Float[Array, "W nl"]  # the current innovations over the window
    od: ObservationDensity  # the window's data


class Segment(NamedTuple):
    """The window's expanded model (:func:`expand`): ``x_t = F_t x_{t-1} + u_t + B_t eps_t``, the
    observations ``y_t = H_t x_t + d_t + noise``, the sensors' rows then the pin's (module doc)."""

    F: Float[Array, "W n n"]  # zero at the record's first sample
    u: Float[Array, "W n"]  # the expansion's constant (the initial mean at t = 0)
    B: Float[Array, "W n nl"]
    Hm: Float[Array, "W e n"]  # the missing channels' rows and the pin's (but at its sample) zeroed
    d: Float[Array, "W e"]
    y: Float[Array, "W e"]
    mask: Float[Array, "W e"]
    Rinv: Float[Array, "W e e"]
    x_prev: Float[Array, " n"]
    R: Float[Array, "e e"]  # the sensors' noise covariance and the pin's identity


def frame(pm, tr, od: ObservationDensity, nz: Noise, path, eps, start, width: int) -> tuple[Frame, Array]:
    """``(frame, a)``: the window of ``width`` samples from ``a = clip(start, 0, T - width)``."""
    T = eps.shape[0]
    a = jnp.clip(start, 0, T - width)
    t = a + jnp.arange(width)

    def sl(x):
        return jax.lax.dynamic_slice_in_dim(x, a, width, axis=0)

    first = (t == 0).astype(eps.dtype)
    B = jnp.where((t == 0)[:, None, None], nz.L1, nz.Lq)
    m1 = jnp.concatenate([pm.mech0_mean, jnp.zeros(pm.nfx)])
    od_w = ObservationDensity(sl(od.y), sl(od.maskf), sl(od.Rinv), sl(od.const), od.R)
    x_prev, x_next = path[jnp.maximum(a - 1, 0)], path[jnp.minimum(a + width, T - 1)]
    pin = (a + width < T).astype(eps.dtype)
    return Frame(first, B, m1, x_prev, x_next, pin, sl(eps), od_w), a


def rollout(pm, tr, fr: Frame, eps_w) -> Float[Array, "W n"]:
    """The exact states over the window with innovations ``eps_w``."""
    noise_w = jnp.einsum("tij,tj->ti", fr.B, eps_w)

    def _step(x, inp):
        q, first = inp
        nxt = jnp.where(first > 0, fr.m1, pm.state_step(tr, x)) + q
        return nxt, nxt

    _, xs = jax.lax.scan(_step, fr.x_prev, (noise_w, fr.first))
    return xs


def expand(pm, tr, fr: Frame, nz: Noise, c: Float[Array, "W n"]) -> Segment:
    """The window's model expanded about ``c``: each transition about the state it leaves (the
    current path's ``x_prev`` for the first), each sensor about ``c_t``, the pin about ``c_b``."""

    def f(x):
        return pm.state_step(tr, x)

    W, n = c.shape
    prev = jnp.concatenate([fr.x_prev[None], c[:-1]])
    F = jax.vmap(jax.jacfwd(f))(prev)
    e = jax.vmap(f)(prev) - jnp.einsum("tij,tj->ti", F, prev)
    first = fr.first[:, None]
    F = F * (1.0 - first)[:, :, None]
    e = e * (1.0 - first) + fr.m1 * first
    mask = fr.od.maskf
    H = jax.vmap(jax.jacfwd(pm.readout))(c) * mask[:, :, None]
    d = (jax.vmap(pm.readout)(c) - jnp.einsum("tij,tj->ti", H, c)) * mask
    # the pin: L_Q^-1 (x_{b+1} - e_b) = L_Q^-1 F_b x_b + eps_{b+1}, observed at the window's last sample
    F_b = jax.jacfwd(f)(c[-1])
    last = (jnp.arange(W) == W - 1).astype(c.dtype)[:, None] * fr.pin
    H_pin = (nz.Lq_inv @ F_b)[None] * last[:, :, None]
    z_pin = (nz.Lq_inv @ (fr.x_next - f(c[-1]) + F_b @ c[-1]))[None] * last
    ones = jnp.ones((W, n)) * last
    return Segment(
        F, e, fr.B,
        jnp.concatenate([H, H_pin], axis=1),
        jnp.concatenate([d, jnp.zeros((W, n))], axis=1),
        jnp.concatenate([fr.od.y, z_pin], axis=1),
        jnp.concatenate([mask, ones], axis=1),
        jax.vmap(jax.scipy.linalg.block_diag)(fr.od.Rinv, jax.vmap(jnp.diag)(ones)),
        fr.x_prev,
        jax.scipy.linalg.block_diag(fr.od.R, jnp.eye(n)),
    )  # fmt: skip


def segment(pm, tr, fr: Frame, nz: Noise, centre_w, iterations: int = 0) -> Segment:
    """The window's expanded model about ``centre_w`` re-centred by ``iterations`` Gauss-Newton steps
    (the expanded model's conditional mode, rolled out exactly): a function of the held ends alone."""

    def _gn(c, _):
        seg = expand(pm, tr, fr, nz, c)
        return rollout(pm, tr, fr, _smoothed_eps(seg, _gains(seg), seg.y)), None

    c, _ = jax.lax.scan(_gn, centre_w, None, length=int(iterations))
    return expand(pm, tr, fr, nz, c)


class _Gains(NamedTuple):
    Sinv: Float[Array, "W e e"]
    M: Float[Array, "W n e"]


def _gains(seg: Segment) -> _Gains:
    """The window's covariance recursion, the state before it known."""

    def _step(P_f, inp):
        F, B, H, m = inp
        P = symmetrise(F @ P_f @ F.T + B @ B.T)
        S = symmetrise(H @ P @ H.T + seg.R) * jnp.outer(m, m) + jnp.diag(1.0 - m)
        Sinv = cho_solve(cholesky(S), jnp.eye(S.shape[0])) * jnp.outer(m, m)
        M = P @ H.T @ Sinv
        return symmetrise(P - M @ H @ P), (Sinv, M)

    n = seg.x_prev.shape[0]
    _, (Sinv, M) = jax.lax.scan(_step, jnp.zeros((n, n)), (seg.F, seg.B, seg.Hm, seg.mask))
    return _Gains(Sinv, M)


def _smoothed_eps(seg: Segment, gains: _Gains, y) -> Float[Array, "W nl"]:
    r""":math:`\hat\varepsilon` of the window given observations ``y`` (the sensors' and the pin's)."""

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


def linear_path(seg: Segment, eps_w) -> Float[Array, "W n"]:
    """The expanded model's states over the window with innovations ``eps_w``."""

    def _step(x, inp):
        F, u, B, e = inp
        nxt = F @ x + u + B @ e
        return nxt, nxt

    _, xs = jax.lax.scan(_step, seg.x_prev, (seg.F, seg.u, seg.B, eps_w))
    return xs


def _log_q(seg: Segment, eps_w) -> Float[Array, ""]:
    r""":math:`\log\tilde q` up to its constant: the prior and the expanded likelihood (sensors and pin)."""
    x = linear_path(seg, eps_w)
    r = (seg.y - jnp.einsum("tij,tj->ti", seg.Hm, x) - seg.d) * seg.mask
    return -0.5 * jnp.sum(eps_w**2) - 0.5 * jnp.einsum("ti,tij,tj->", r, seg.Rinv, r)


def draw(key, seg: Segment, gains: _Gains, eps_hat) -> Float[Array, "W nl"]:
    r"""One draw of :math:`\tilde q` (module doc)."""
    k_eps, k_obs = jax.random.split(key)
    eps_star = jax.random.normal(k_eps, (seg.B.shape[0], seg.B.shape[2]))
    x_star = linear_path(seg, eps_star)
    # each observation row its own stream, as smoother_move._draw_eps
    W, e = seg.y.shape
    z = jax.vmap(lambda i: jax.random.normal(jax.random.fold_in(k_obs, i), (W,)), out_axes=1)(jnp.arange(e))
    y_star = (jnp.einsum("tij,tj->ti", seg.Hm, x_star) + seg.d + z @ cholesky(symmetrise(seg.R)).T) * seg.mask
    return eps_star - _smoothed_eps(seg, gains, y_star) + eps_hat


class Correction(NamedTuple):
    """The end-state correction :math:`\\Phi` (module doc): ``D`` (W, nl, nm) and ``JD`` (nm, nm)."""

    D: Float[Array, "W nl nm"]
    JD: Float[Array, "nm nm"]


def correction(pm, seg: Segment) -> Correction:
    """:math:`D = J^\\top`, :math:`J` the expanded model's Jacobian of the mechanical end state."""
    nm = seg.x_prev.shape[0] - pm.nfx
    J = jax.jacrev(lambda e: linear_path(seg, e)[-1, :nm])(jnp.zeros((seg.B.shape[0], seg.B.shape[2])))
    D = jnp.moveaxis(J, 0, -1)
    return Correction(D, jnp.einsum("iwl,wlj->ij", J, D))


def _mech_end(pm, tr, fr: Frame, eps_w):
    return rollout(pm, tr, fr, eps_w)[-1, : fr.x_prev.shape[0] - pm.nfx]


def _jd_exact(pm, tr, fr: Frame, cor: Correction, eps_w) -> Float[Array, "nm nm"]:
    """:math:`J_\\mathrm{ex} D` at ``eps_w``: forward-mode along the columns of ``D``."""
    return jax.vmap(lambda col: jax.jvp(lambda e: _mech_end(pm, tr, fr, e), (eps_w,), (col,))[1], -1, -1)(cor.D)


def phi(pm, tr, fr: Frame, seg: Segment, cor: Correction, eps_w) -> Float[Array, "W nl"]:
    r""":math:`\Phi(\varepsilon)`: :data:`NEWTON` Newton steps on ``u`` from zero (module doc)."""
    target = linear_path(seg, eps_w)[-1, : cor.D.shape[-1]]

    def _newton(u, _):
        e = eps_w + cor.D @ u
        r = _mech_end(pm, tr, fr, e) - target
        return u - jnp.linalg.solve(_jd_exact(pm, tr, fr, cor, e), r), None

    u, _ = jax.lax.scan(_newton, jnp.zeros(cor.D.shape[-1]), None, length=NEWTON)
    return eps_w + cor.D @ u


def phi_inverse(pm, tr, fr: Frame, seg: Segment, cor: Correction, eps_w) -> Float[Array, "W nl"]:
    r""":math:`\Phi^{-1}(\varepsilon')`, explicit (module doc)."""
    nm = cor.D.shape[-1]
    gap = linear_path(seg, eps_w)[-1, :nm] - _mech_end(pm, tr, fr, eps_w)
    return eps_w - cor.D @ jnp.linalg.solve(cor.JD, gap)


def exact_log_target(pm, tr, fr: Frame, nz: Noise, eps_w) -> tuple[Float[Array, ""], Array, Array]:
    r"""``(log pi, states, eps_next)``: :math:`\log\pi(\varepsilon_W)` up to its constant, the window's
    exact states and :math:`\varepsilon_{b+1}` (module doc)."""
    xs = rollout(pm, tr, fr, eps_w)
    eps_next = nz.Lq_inv @ (fr.x_next - pm.state_step(tr, xs[-1]))
    ll = observation_log_likelihood(pm, fr.od, xs)
    return ll - 0.5 * jnp.sum(eps_w**2) - 0.5 * fr.pin * jnp.sum(eps_next**2), xs, eps_next


def log_weight(pm, tr, fr: Frame, nz: Noise, seg: Segment, cor: Correction, eps_w):
    r"""``(w, pre-image, states, eps_next)``: :math:`w(\varepsilon')` of the module doc."""
    pre = phi_inverse(pm, tr, fr, seg, cor, eps_w)
    log_pi, xs, eps_next = exact_log_target(pm, tr, fr, nz, eps_w)
    log_det = jnp.linalg.slogdet(_jd_exact(pm, tr, fr, cor, eps_w))[1]
    return log_pi - _log_q(seg, pre) - log_det, pre, xs, eps_next


def n_windows(T: int, width: int) -> int:
    """Window steps per call: enough windows of ``width`` laid end to end from any offset to cover ``T``."""
    return math.ceil(T / width) + 1


def window_starts(key, T: int, width: int) -> Array:
    """The first samples of one call's :func:`n_windows` windows: laid end to end from a random
    offset in ``[0, width)``, the first starting ``width`` earlier (clipped into the record by :func:`frame`)."""
    return jax.random.randint(key, (), 0, width) + width * (jnp.arange(n_windows(T, width)) - 1)


def window_move(
    key,
    pm: particle_model.ParticleModel,
    tr,
    od: ObservationDensity,
    centre,
    path: Float[Array, "T n"],
    width: int = WIDTH,
    betas=(1.0,),
    iterations: int = RECENTRE,
) -> tuple[Float[Array, "T n"], Float[Array, " k"]]:
    """One pass of window steps over the record (module doc): windows of ``width`` samples from a
    random offset; step ``k`` a Crank-Nicolson step of size ``betas[k % len(betas)]``. Returns the
    new path and each step's acceptance (bool). The record must be longer than ``width``."""
    T = path.shape[0]
    width = int(width)
    if not 0 < width < T:
        raise ValueError(f"the window move needs 0 < width < T, got width {width} and T {T}")
    K = n_windows(T, width)
    k_off, k_steps = jax.random.split(key)
    starts = window_starts(k_off, T, width)
    beta = jnp.asarray([float(betas[k % len(betas)]) for k in range(K)])
    nz = noise(pm, tr)
    made = well_conditioned(pm, tr)

    def _step(carry, inp):
        x, eps = carry
        s, b, k = inp
        k_prop, k_acc = jax.random.split(k)
        fr, a = frame(pm, tr, od, nz, x, eps, s, width)
        seg = segment(pm, tr, fr, nz, jax.lax.dynamic_slice_in_dim(centre, a, width, axis=0), iterations)
        cor = correction(pm, seg)
        gains = _gains(seg)
        eps_hat = _smoothed_eps(seg, gains, seg.y)
        w_cur, pre_cur, _, _ = log_weight(pm, tr, fr, nz, seg, cor, fr.eps)
        new = draw(k_prop, seg, gains, eps_hat)
        new = eps_hat + jnp.sqrt(1.0 - b**2) * (pre_cur - eps_hat) + b * (new - eps_hat)
        eps_w = phi(pm, tr, fr, seg, cor, new)
        w_new, pre_new, xs, eps_next = log_weight(pm, tr, fr, nz, seg, cor, eps_w)
        closed = jnp.max(jnp.abs(pre_new - new)) <= INVERSE_TOL
        log_ratio = w_new - w_cur
        ok = made & closed & jnp.isfinite(log_ratio) & (jnp.log(jax.random.uniform(k_acc)) < log_ratio)
        x_p = jax.lax.dynamic_update_slice_in_dim(x, xs, a, axis=0)
        eps_p = jax.lax.dynamic_update_slice_in_dim(eps, eps_w, a, axis=0)
        # the innovation into the held state after the window (the record's last row where there is none)
        nxt = jnp.minimum(a + width, T - 1)
        eps_p = eps_p.at[nxt].set(jnp.where(fr.pin > 0, eps_next, eps_p[nxt]))
        return (jnp.where(ok, x_p, x), jnp.where(ok, eps_p, eps)), ok

    eps0 = whiten(tr, pm.latent(path))
    (out, _), acc = jax.lax.scan(_step, (path, eps0), (starts, beta, jax.random.split(k_steps, K)))
    return out, acc
