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
likelihood of the window's data and the pin) is drawn forward in time from the messages of a
backward information filter ("Numerics" below); the weight uses the normalised density of those
draws, the forward pass's Gaussians, so it is the proposal's own density, round-off and all.

**Why a correction.** The within-step noise of the mechanical states and of a smooth force's
lower derivatives is small (the displacement's sd 2e-5 m at the calibration Duffing's 256 Hz), and
the exact transition into the held state differs from the expanded one by the expansion's error
accumulated over the window: amplified by :math:`L_Q^{-1}`, that error put a spread of 8-34 nats
into the pin term of some windows' log weights (T = 4 096, windows of 256; acceptance 0). So the
draw :math:`\varepsilon` is mapped to :math:`\varepsilon' = \Phi(\varepsilon) = \varepsilon + D u`,
:math:`u` solved by Newton so that the exact path meets a constraint where the expanded path of
:math:`\varepsilon` does: the force then moves a little across the window to steer the structure.
The constraint (:func:`_end_linear`) is the mechanical rows of the transition into the held state,
:math:`f(x_b)` against its expansion :math:`f(c_b) + F_b(x_b - c_b)`, and :math:`D`'s columns are the
rows of its Jacobian :math:`J` in :math:`\varepsilon_W` (constant) less their projection on the
Jacobian of :math:`f`'s force rows (linear, and the same in the exact model), so :math:`D u` leaves
the force at :math:`b` as drawn: the pin's whole innovation :math:`\varepsilon_{b+1}` is then the
expanded model's, and the pin term drops out of the weight's spread. (The first constraint, the
mechanical :math:`x_b` itself, left two errors in the pin: :math:`f`'s second-order term and the
correction's own change of the force at :math:`b`, which the near-deterministic derivatives of a
smooth force amplify; on the Matérn-7/2 record windows with a pin accepted 0.73-0.81 against 0.94
without one, and 0.93-0.95 everywhere with this constraint, the log weight's sd 0.3-1.6 -> 0.08-0.1.)
Where the window ends the record the constraint is the mechanical :math:`x_b` (no pin; the force rows
are not projected out). The inverse is explicit (the expansion is affine):
:math:`\Phi^{-1}(\varepsilon') = \varepsilon' - D (JD)^{-1} (g_\mathrm{lin}(\varepsilon') -
g_\mathrm{ex}(\varepsilon'))`, and its Jacobian determinant :math:`\det(J_\mathrm{ex}(\varepsilon')
D)/\det(JD)` (the matrix determinant lemma, for any constant :math:`D`; :math:`J_\mathrm{ex}` the
exact constraint's Jacobian, by forward-mode along the ``nm`` columns of :math:`D`). The proposal in
:math:`\varepsilon'` is :math:`q'(\varepsilon') = \tilde q(\Phi^{-1}(\varepsilon'))\,|\det
D\Phi^{-1}(\varepsilon')|`, and the Metropolis-Hastings ratio :math:`\exp(w(\varepsilon'_\mathrm{new}) -
w(\varepsilon'_\mathrm{cur}))` with

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
At Matérn-5/2 and 7/2 on the same record (possible since the proposal was rebuilt, "Numerics"), 1 000
iterations: R-hat 1.011 / 1.021, ESS 447 / 333, windows accepted 0.89 / 0.78, where without the move
the chains sat apart (R-hat 3.5 / 4.1, bands holding the truth on 78 / 63 % at ±2 sd).
A step costs the window's work alone. Acceleration alone is not helped (the expansion itself is
poor there).

For a linear system the expansion is exact, :math:`\Phi` the identity, every step accepted and
each an exact Gibbs draw of the window given the rest (tested, every Matérn order).

**Numerics.** The within-step noise's factor :math:`L_Q` spans the scales from the force's
driving noise to the displacement's within-step noise: condition numbers 2e5-4e14 (Duffing at 256 Hz,
Matérn-1/2 to 7/2), 2.5e18 (Bouc-Wen at 750 Hz, 5/2), 4.8e14 (a 3-storey frame, 3/2); scaled by its
rows, 16-3e5 (the particle model's relative jitter bounds it). The first proposal ran the Kalman
filter's covariance form over the window with the pin as its last observation: conditioning a
window's accumulated covariance on a near-exact observation cancelled the digits the pin needs, and
on *linear* dynamics, where every step must be accepted, the Bouc-Wen oscillator accepted 45 % at
Matérn-3/2 and the frame 56 %, the smoothed mean itself missing the pin by 1e4-1e7 whitened units;
the move was kept off such models ("a numerical limit", 2026-12-02). Now every quantity is a whitened
deviation from the centre: :math:`x_t = c_t + B_t\xi_t`, :math:`\xi_t = \tilde F_t\xi_{t-1} +
\varepsilon_t - \varepsilon^c_t` with :math:`\tilde F_t = B_t^{-1}F_tB_{t-1}`, the sensors' rows
:math:`H_tB_t`, the pin :math:`\rho - \tilde F_\mathrm{pin}\xi_b` with the centre's own pin residual
:math:`\rho = L_Q^{-1}(x_{b+1} - f(c_b))` formed directly, and the conditional is computed by a
backward *information* filter started by the pin (information :math:`U_t`, passed through each
step's unit noise as :math:`U(I + U)^{-1}`, never a difference), then drawn forward. The Bouc-Wen
oscillator without hysteresis then accepts every step at 3/2 and 5/2 (windows of 16 and 256), the
linear SDOF at every order; the frame accepts 0.84-0.96 of its windows of 16 and 0.5-0.64 at 256:
its whitened deviations grow to 1e4 along the stiff directions and the round-off of the window's
path parts the exact from the expanded pin by a few tenths of a nat (measured), a cost in
acceptance, not in exactness. The correction's constraint rows are scaled to unit norm and a row
within :data:`DEPENDENT` (relative) of the span of the rows before it is dropped (the frame's and the
twin's hysteretic state, carried as alpha times a displacement, is an exact function of the others;
solving for it amplified round-off into the Newton step). No LAPACK call is made (linalg's own
loops, as everywhere in the samplers).

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
from latentforce.linalg import cho_solve, cholesky, inv, log_abs_det, psd_sqrt, solve, solve_lower, symmetrise

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
#: a constraint row of the correction within this (relative) distance of the span of the rows before
#: it is dropped (module doc, "Dependent end states")
DEPENDENT = 1e-6


class Noise(NamedTuple):
    """The latent's noise factors in the state's order and their inverses."""

    L1: Float[Array, "n nl"]
    Lq: Float[Array, "n nl"]
    L1_inv: Float[Array, "nl n"]
    Lq_inv: Float[Array, "nl n"]


def _inverse(L):
    # rows from the force's scale to the within-step displacement's (1e-9 against 1e3): scaled first
    rows = jnp.sqrt(jnp.sum(L**2, axis=1))
    return inv(L / rows[:, None]) / rows[None, :]


def noise(pm, tr) -> Noise:
    """The :class:`Noise` of transition ``tr`` (once per call of :func:`window_move`)."""
    L1, Lq = noise_factors(pm, tr)
    return Noise(L1, Lq, _inverse(L1), _inverse(Lq))


class Frame(NamedTuple):
    """A window's place in the record, its data and the held states at its ends."""

    first: Array  # 1.0 at the record's first sample
    B: Float[Array, "W n nl"]  # each innovation's loading (L1 at the record's first sample, else Lq)
    B_inv: Float[Array, "W nl n"]
    m1: Float[Array, " n"]
    x_prev: Float[Array, " n"]  # the current path's state before the window (unused at a = 0)
    x_next: Float[Array, " n"]  # the held state after it
    pin: Array  # 1.0 where the window ends before the record does
    eps: Float[Array, "W nl"]  # the current innovations over the window
    od: ObservationDensity  # the window's data


class Segment(NamedTuple):
    r"""The window's expanded model (:func:`expand`) in whitened deviations from its centre ``c``:
    :math:`x_t = c_t + B_t\xi_t`, :math:`\xi_t = \tilde F_t \xi_{t-1} + \varepsilon_t - \varepsilon^c_t`
    (:math:`\xi` zero before the window), the sensors :math:`y_t - h(x_t) \approx r_t - \tilde H_t\xi_t`
    and the pin :math:`\varepsilon_{b+1} \approx \rho - \tilde F_\mathrm{pin}\xi_b` (module doc)."""

    c: Float[Array, "W n"]
    B: Float[Array, "W n nl"]
    F: Float[Array, "W nl nl"]  # B_t^-1 F_t B_{t-1}
    eps_c: Float[Array, "W nl"]  # the centre's innovations under the expanded model
    H: Float[Array, "W e nl"]  # H_t B_t, the missing channels' rows zeroed
    r: Float[Array, "W e"]  # y_t - h(c_t), zero where missing
    Rinv: Float[Array, "W e e"]
    F_pin: Float[Array, "nl nl"]  # zero where the window ends the record
    rho: Float[Array, " nl"]
    pin: Array  # 1.0 where the window ends before the record does
    g_c: Float[Array, " nm"]  # the correction's constraint at the centre: f(c_b) or c_b, mechanical rows
    G_x: Float[Array, "nm n"]  # its Jacobian in x_b there: f's at c_b, or the selection
    G_f: Float[Array, "nf n"]  # f's force rows (linear): the correction leaves them as drawn (zero: no pin)


def frame(pm, tr, od: ObservationDensity, nz: Noise, path, eps, start, width: int) -> tuple[Frame, Array]:
    """``(frame, a)``: the window of ``width`` samples from ``a = clip(start, 0, T - width)``."""
    T = eps.shape[0]
    a = jnp.clip(start, 0, T - width)
    t = a + jnp.arange(width)

    def sl(x):
        return jax.lax.dynamic_slice_in_dim(x, a, width, axis=0)

    first = (t == 0).astype(eps.dtype)
    B = jnp.where((t == 0)[:, None, None], nz.L1, nz.Lq)
    B_inv = jnp.where((t == 0)[:, None, None], nz.L1_inv, nz.Lq_inv)
    m1 = jnp.concatenate([pm.mech0_mean, jnp.zeros(pm.nfx)])
    od_w = ObservationDensity(sl(od.y), sl(od.maskf), sl(od.Rinv), sl(od.const), od.R)
    x_prev, x_next = path[jnp.maximum(a - 1, 0)], path[jnp.minimum(a + width, T - 1)]
    pin = (a + width < T).astype(eps.dtype)
    return Frame(first, B, B_inv, m1, x_prev, x_next, pin, sl(eps), od_w), a


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
    current path's ``x_prev`` for the first), each sensor about ``c_t``, the pin about ``c_b``. Every
    term is formed as a deviation from the centre and whitened by the step's own noise factor, so no
    quantity carries the within-step noise's range of scales (module doc, "Numerics")."""

    def f(x):
        return pm.state_step(tr, x)

    first = fr.first[:, None]
    prev = jnp.concatenate([fr.x_prev[None], c[:-1]])
    F = jax.vmap(jax.jacfwd(f))(prev) * (1.0 - first)[:, :, None]
    mean = jnp.where(first > 0, fr.m1, jax.vmap(f)(prev))
    eps_c = jnp.einsum("tij,tj->ti", fr.B_inv, c - mean)
    B_prev = jnp.concatenate([fr.B[:1], fr.B[:-1]])  # the first one multiplies xi = 0
    Ft = jnp.einsum("tij,tjk,tkl->til", fr.B_inv, F, B_prev)
    mask = fr.od.maskf
    H = jax.vmap(jax.jacfwd(pm.readout))(c) * mask[:, :, None]
    r = (fr.od.y - jax.vmap(pm.readout)(c)) * mask
    F_b = jax.jacfwd(f)(c[-1])
    F_pin = fr.pin * (nz.Lq_inv @ F_b @ fr.B[-1])
    rho = fr.pin * (nz.Lq_inv @ (fr.x_next - f(c[-1])))
    nm = c.shape[1] - pm.nfx
    g_c = jnp.where(fr.pin > 0, f(c[-1])[:nm], c[-1, :nm])
    G_x = jnp.where(fr.pin > 0, F_b[:nm], jnp.eye(c.shape[1])[:nm])
    G_f = fr.pin * F_b[nm:]
    H_w = jnp.einsum("tij,tjk->tik", H, fr.B)
    return Segment(c, fr.B, Ft, eps_c, H_w, r, fr.od.Rinv, F_pin, rho, fr.pin, g_c, G_x, G_f)


def segment(pm, tr, fr: Frame, nz: Noise, centre_w, iterations: int = 0) -> Segment:
    """The window's expanded model about ``centre_w`` re-centred by ``iterations`` Gauss-Newton steps
    (the expanded model's conditional mode, rolled out exactly): a function of the held ends alone."""

    def _gn(c, _):
        seg = expand(pm, tr, fr, nz, c)
        return rollout(pm, tr, fr, _forward(seg, _messages(seg), None)), None

    c, _ = jax.lax.scan(_gn, centre_w, None, length=int(iterations))
    return expand(pm, tr, fr, nz, c)


class _Messages(NamedTuple):
    r"""The backward information filter's factors: ``L_t`` the Cholesky factor of ``I + U_t`` and
    ``u_t``, the information on :math:`\xi_t` from the window's data at and after ``t`` and the pin."""

    L: Float[Array, "W nl nl"]
    u: Float[Array, "W nl"]


def _messages(seg: Segment) -> _Messages:
    r"""The backward information filter in whitened deviations (module doc, "Numerics"): the pin
    starts it as information, so no covariance is ever conditioned on a near-exact observation."""
    nl = seg.F.shape[-1]
    eye = jnp.eye(nl)
    Lam = jnp.einsum("tei,tef,tfj->tij", seg.H, seg.Rinv, seg.H)
    lam = jnp.einsum("tei,tef,tf->ti", seg.H, seg.Rinv, seg.r)
    Lam = Lam.at[-1].add(seg.F_pin.T @ seg.F_pin)
    lam = lam.at[-1].add(seg.F_pin.T @ seg.rho)

    def _step(carry, inp):
        U_next, u_next = carry
        Lam_t, lam_t, F_t, e_t = inp
        U, u = symmetrise(U_next + Lam_t), u_next + lam_t
        L = cholesky(eye + U)
        U_pred = symmetrise(cho_solve(L, U))  # U (I + U)^-1: through the step's unit noise
        u_pred = cho_solve(L, u) + U_pred @ e_t
        return (symmetrise(F_t.T @ U_pred @ F_t), F_t.T @ u_pred), (L, u)

    zero = (jnp.zeros((nl, nl)), jnp.zeros(nl))
    _, (L, u) = jax.lax.scan(_step, zero, (Lam, lam, seg.F, seg.eps_c), reverse=True)
    return _Messages(L, u)


def _forward(seg: Segment, msg: _Messages, z) -> Float[Array, "W nl"]:
    r"""Innovations drawn forward given the messages: with standard normals ``z`` a draw of
    :math:`\tilde q`, with ``None`` its mean."""
    z = jnp.zeros_like(seg.eps_c) if z is None else z

    def _step(xi_prev, inp):
        F_t, e_t, L, u, z_t = inp
        prior = F_t @ xi_prev - e_t
        xi = cho_solve(L, prior + u) + solve_lower(L, z_t, transpose=True)
        return xi, xi - prior

    _, eps = jax.lax.scan(_step, jnp.zeros(seg.F.shape[-1]), (seg.F, seg.eps_c, msg.L, msg.u, z))
    return eps


def _xi(seg: Segment, eps_w) -> Float[Array, "W nl"]:
    def _step(xi_prev, inp):
        F_t, e_t, eps_t = inp
        xi = F_t @ xi_prev + eps_t - e_t
        return xi, xi

    _, xi = jax.lax.scan(_step, jnp.zeros(seg.F.shape[-1]), (seg.F, seg.eps_c, eps_w))
    return xi


def linear_path(seg: Segment, eps_w) -> Float[Array, "W n"]:
    """The expanded model's states over the window with innovations ``eps_w``."""
    return seg.c + jnp.einsum("tij,tj->ti", seg.B, _xi(seg, eps_w))


def _log_q(seg: Segment, msg: _Messages, eps_w) -> Float[Array, ""]:
    r""":math:`\log\tilde q(\varepsilon)` as :func:`draw` makes it, normalised: the forward pass's
    Gaussians, one a step (:math:`\varepsilon \mapsto \xi` has unit Jacobian). The density of the draws
    themselves, rounding and all; the expanded model's form (prior, sensors, pin) differs from it by a
    constant to round-off (tested)."""

    def _step(xi_prev, inp):
        F_t, e_t, L, u, eps_t = inp
        prior = F_t @ xi_prev - e_t
        xi = prior + eps_t
        z = L.T @ (xi - cho_solve(L, prior + u))
        return xi, jnp.sum(jnp.log(jnp.diagonal(L))) - 0.5 * jnp.sum(z**2)

    _, terms = jax.lax.scan(_step, jnp.zeros(seg.F.shape[-1]), (seg.F, seg.eps_c, msg.L, msg.u, eps_w))
    return jnp.sum(terms) - 0.5 * eps_w.size * math.log(2.0 * math.pi)


def draw(key, seg: Segment, msg: _Messages) -> Float[Array, "W nl"]:
    r"""One draw of :math:`\tilde q` (module doc)."""
    return _forward(seg, msg, jax.random.normal(key, seg.eps_c.shape))


class Correction(NamedTuple):
    r"""The end-state correction :math:`\Phi` (module doc): the constraints' row weights ``G`` (nm,; zero
    for a dropped, dependent row), ``D`` (W, nl, nm; zero columns for dropped rows) and ``JD`` (nm, nm;
    the identity in the dropped rows and columns)."""

    G: Float[Array, " nm"]
    D: Float[Array, "W nl nm"]
    JD: Float[Array, "nm nm"]


def _end_linear(seg: Segment, eps_w) -> Float[Array, " nm"]:
    r"""The correction's constraint under the expanded model: the pin's prediction of the mechanical
    states after the window, :math:`f(c_b) + F_b(x_b - c_b)` (their mechanical rows), or the
    mechanical :math:`x_b` itself where the window ends the record (module doc, "Why a correction")."""
    return seg.g_c + seg.G_x @ (linear_path(seg, eps_w)[-1] - seg.c[-1])


def _end_exact(pm, tr, seg: Segment, x_b) -> Float[Array, " nm"]:
    """The same constraint on the exact path's last state ``x_b``."""
    nm = seg.g_c.shape[0]
    return jnp.where(seg.pin > 0, pm.state_step(tr, x_b)[:nm], x_b[:nm])


def correction(pm, seg: Segment) -> Correction:
    r""":math:`D`: the rows of :math:`J`, the expanded model's Jacobian of the constraint
    (:func:`_end_linear`), less their projection on the rows of :math:`J_f`, the Jacobian of the force
    rows of the transition into the held state (linear, the same in the exact model), so that
    :math:`D u` leaves the force at :math:`b` as drawn and the whole pin's innovation is the expanded
    model's; scaled to unit norm, and a row dependent on those before it (:data:`DEPENDENT`) dropped."""
    nm = seg.g_c.shape[0]

    # d(rows of x_b)/d eps_t = rows B_b F_b ... F_{t+1}: one backward recursion
    top = jnp.concatenate([seg.G_x, seg.G_f]) @ seg.B[-1]

    def _back(M, F_t):
        return M @ F_t, M

    _, J_all = jax.lax.scan(_back, top, seg.F, reverse=True)
    J_all = jnp.moveaxis(J_all, 1, 0)
    J, J_f = J_all[:nm], J_all[nm:]
    # an orthonormal basis of J_f's rows (Gram-Schmidt: a handful of rows; none where no pin)
    basis = []
    for i in range(J_f.shape[0]):
        v = J_f[i]
        for q in basis:
            v = v - jnp.sum(q * v) * q
        v_norm = jnp.sqrt(jnp.sum(v**2))
        keep_f = v_norm > DEPENDENT * jnp.sqrt(jnp.sum(J_f[i] ** 2))
        basis.append(jnp.where(keep_f, v / jnp.where(keep_f, v_norm, 1.0), 0.0))
    P = J
    for q in basis:
        P = P - jnp.einsum("iwl,wl->i", P, q)[:, None, None] * q[None]
    norms = jnp.sqrt(jnp.einsum("iwl,iwl->i", P, P))
    Ps = P / jnp.where(norms > 0, norms, 1.0)[:, None, None]
    # a row's pivot in the unit-diagonal Gram matrix is its squared distance from the span of the rows
    # before it: a zero column of the semi-definite factor marks a dependent row
    keep = (jnp.diagonal(psd_sqrt(jnp.einsum("iwl,jwl->ij", Ps, Ps), rtol=DEPENDENT**2)) > 0) & (norms > 0)
    G = jnp.where(keep, 1.0 / jnp.where(norms > 0, norms, 1.0), 0.0)
    D = jnp.moveaxis(P * G[:, None, None], 0, -1)
    return Correction(G, D, G[:, None] * jnp.einsum("iwl,wlj->ij", J, D) + jnp.diag(jnp.where(keep, 0.0, 1.0)))


def _exact(pm, tr, fr: Frame, seg: Segment, cor: Correction, eps_w) -> tuple[Float[Array, "W n"], Array, Array]:
    r"""``(states, constraint, G J_ex D)`` at ``eps_w``: the exact rollout, :func:`_end_exact` on it and
    that constraint's Jacobian along the columns of ``D`` (one linearised rollout), the identity in the
    dropped rows and columns."""

    def run(e):
        xs = rollout(pm, tr, fr, e)
        return xs, _end_exact(pm, tr, seg, xs[-1])

    (xs, g), lin = jax.linearize(run, eps_w)
    JD = jax.vmap(lambda col: lin(col)[1], -1, -1)(cor.D)
    return xs, g, cor.G[:, None] * JD + jnp.diag(jnp.where(cor.G > 0, 0.0, 1.0))


def phi(pm, tr, fr: Frame, seg: Segment, cor: Correction, eps_w) -> Float[Array, "W nl"]:
    r""":math:`\Phi(\varepsilon)`: :data:`NEWTON` Newton steps on ``u`` from zero (module doc)."""
    nm = cor.D.shape[-1]
    target = _end_linear(seg, eps_w)

    def _newton(u, _):
        _, g, JD = _exact(pm, tr, fr, seg, cor, eps_w + cor.D @ u)
        return u - solve(JD, cor.G * (g - target)), None

    u, _ = jax.lax.scan(_newton, jnp.zeros(nm), None, length=NEWTON)
    return eps_w + cor.D @ u


def _pre_image(seg: Segment, cor: Correction, eps_w, g) -> Float[Array, "W nl"]:
    return eps_w - cor.D @ solve(cor.JD, cor.G * (_end_linear(seg, eps_w) - g))


def phi_inverse(pm, tr, fr: Frame, seg: Segment, cor: Correction, eps_w) -> Float[Array, "W nl"]:
    r""":math:`\Phi^{-1}(\varepsilon')`, explicit (module doc)."""
    return _pre_image(seg, cor, eps_w, _end_exact(pm, tr, seg, rollout(pm, tr, fr, eps_w)[-1]))


def _log_target(pm, tr, fr: Frame, nz: Noise, eps_w, xs) -> tuple[Float[Array, ""], Array]:
    eps_next = nz.Lq_inv @ (fr.x_next - pm.state_step(tr, xs[-1]))
    ll = observation_log_likelihood(pm, fr.od, xs)
    return ll - 0.5 * jnp.sum(eps_w**2) - 0.5 * fr.pin * jnp.sum(eps_next**2), eps_next


def exact_log_target(pm, tr, fr: Frame, nz: Noise, eps_w) -> tuple[Float[Array, ""], Array, Array]:
    r"""``(log pi, states, eps_next)``: :math:`\log\pi(\varepsilon_W)` up to its constant, the window's
    exact states and :math:`\varepsilon_{b+1}` (module doc)."""
    xs = rollout(pm, tr, fr, eps_w)
    log_pi, eps_next = _log_target(pm, tr, fr, nz, eps_w, xs)
    return log_pi, xs, eps_next


def log_weight(pm, tr, fr: Frame, nz: Noise, seg: Segment, msg: _Messages, cor: Correction, eps_w):
    r"""``(w, pre-image, states, eps_next)``: :math:`w(\varepsilon')` of the module doc (one linearised
    rollout serves the target, the pre-image and the determinant)."""
    xs, g, JD = _exact(pm, tr, fr, seg, cor, eps_w)
    pre = _pre_image(seg, cor, eps_w, g)
    log_pi, eps_next = _log_target(pm, tr, fr, nz, eps_w, xs)
    return log_pi - _log_q(seg, msg, pre) - log_abs_det(JD), pre, xs, eps_next


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

    def _step(carry, inp):
        x, eps = carry
        s, b, k = inp
        k_prop, k_acc = jax.random.split(k)
        fr, a = frame(pm, tr, od, nz, x, eps, s, width)
        seg = segment(pm, tr, fr, nz, jax.lax.dynamic_slice_in_dim(centre, a, width, axis=0), iterations)
        cor = correction(pm, seg)
        msg = _messages(seg)
        eps_hat = _forward(seg, msg, None)
        w_cur, pre_cur, _, _ = log_weight(pm, tr, fr, nz, seg, msg, cor, fr.eps)
        new = draw(k_prop, seg, msg)
        new = eps_hat + jnp.sqrt(1.0 - b**2) * (pre_cur - eps_hat) + b * (new - eps_hat)
        eps_w = phi(pm, tr, fr, seg, cor, new)
        w_new, pre_new, xs, eps_next = log_weight(pm, tr, fr, nz, seg, msg, cor, eps_w)
        closed = jnp.max(jnp.abs(pre_new - new)) <= INVERSE_TOL
        log_ratio = w_new - w_cur
        ok = closed & jnp.isfinite(log_ratio) & (jnp.log(jax.random.uniform(k_acc)) < log_ratio)
        x_p = jax.lax.dynamic_update_slice_in_dim(x, xs, a, axis=0)
        eps_p = jax.lax.dynamic_update_slice_in_dim(eps, eps_w, a, axis=0)
        # the innovation into the held state after the window (the record's last row where there is none)
        nxt = jnp.minimum(a + width, T - 1)
        eps_p = eps_p.at[nxt].set(jnp.where(fr.pin > 0, eps_next, eps_p[nxt]))
        return (jnp.where(ok, x_p, x), jnp.where(ok, eps_p, eps)), ok

    eps0 = whiten(tr, pm.latent(path))
    (out, _), acc = jax.lax.scan(_step, (path, eps0), (starts, beta, jax.random.split(k_steps, K)))
    return out, acc
