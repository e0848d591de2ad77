"""How many RK4 substeps per sample the samplers' mechanical step needs (``[system].substeps``).

``pgas``, ``ekf`` and ``ukf`` advance the mechanical states (z, z', and a Bouc-Wen element's
hysteretic force r) by ``system.substeps`` explicit RK4 steps per sample
(:meth:`latentforce.inference.particle_model.ParticleModel.phi`). An explicit step of size h is
stable only while h times the rate's Jacobian eigenvalues stays inside RK4's region (about 2.8 on
the real and imaginary axes), and accurate well inside it. The hysteretic force's own rate is the
stiff part: :math:`\\partial \\dot r / \\partial r = -\\nu |r|^{\\nu-1} |\\dot z| (\\beta + \\gamma\\,
\\mathrm{sign}(\\dot z r))`, which grows with the velocity and, for nu > 1, with r. The Bouc-Wen
benchmark (nu = 1, 750 Hz) is far from the bound at 4 substeps; a smoother loop (nu = 2, beta +
gamma = 1 800, 500 Hz, velocities of 0.4 m/s) reaches h |lambda| = 3.6 there, and measured: the
smoother move accepted 0-5 % of its proposals and the run ended at R-hat 1.5-2.6 (hysteretic force
NMSE 0.4 %), against 46-51 % and R-hat 1.13 at 16 substeps (NMSE 0.01 %), same record and cap.

So where the config does not fix ``substeps``, :func:`choose` takes the default's count or, if more
are needed, the fewest that keep h |lambda| <= 1 for every real Jacobian eigenvalue lambda over probe
states and <= 0.5 for every oscillatory one (whose RK4 error is numerical damping: :func:`demand`);
a fixed count gets a warning where it puts a real eigenvalue's h |lambda| past :data:`RERUN_BOUND`
(or an oscillatory one's past its bound).

The count is chosen at the parameters' fixed or init values; a sampled stiffness, Bouc-Wen key or
force variance may move the posterior where more are needed. :func:`needed_over_posterior` reads
that need over the run's draws, and where the count used puts some draw past :data:`RERUN_BOUND`
``estimate`` reruns once at the need (the config's own count is only warned about): a rerun doubles
the user's time, and short of that bound it measured no change in the posterior.
"""

from __future__ import annotations

import copy
import functools
import math
from typing import TYPE_CHECKING

import jax
import jax.numpy as jnp
import numpy as np

from latentforce.compile import jit, numbers
from latentforce.models import LatentForceModel
from latentforce.systems import linearised_stability

if TYPE_CHECKING:
    from latentforce.io.config import Problem
    from latentforce.results import RunResult

#: the largest h |lambda| the chosen count allows for a real (decaying) eigenvalue: RK4's factor at
#: h lambda = -1 is 0.375 against exp(-1) = 0.368 (the stability bounds are ~2.8)
STEP_BOUND = 1.0
#: ... and for an oscillatory one (|Im| > |Re|), where RK4's error is numerical damping: |R(iy)| is
#: about 1 - y^6/144, 0.9969 at y = 0.89, Silverbox's h omega at one substep, which took 2 % off its
#: damping c (2.216e-4 against 2.260e-4 at two substeps and from the exact discretisation of
#: kalman-mcmc's linear model; ``demo silverbox --quick``, 2026-12-03); 1.1e-4 per step at 0.5
OSCILLATION_BOUND = 0.5
#: after a run, the largest h |lambda| for a real eigenvalue that the count used may reach at the
#: posterior's draws before ``estimate`` reruns (or warns about a fixed count): RK4's factor at
#: h lambda = -2 is 1/3 (the fast mode still decays, without oscillating; exp(-2) = 0.135), its
#: stability bound about 2.8. Measured (2026-12-04): a 3-storey frame with a Bouc-Wen element (alpha and
#: beta inferred, acc + disp, 100 Hz) chose 6 substeps at the init values and needed 10 at the posterior
#: (h |lambda| = 1.67 at 6); the run at 6 (493 s, converged) and the rerun at 10 (1 220 s in all) gave
#: the same posterior (alpha 5 104 +- 112 against 5 107 +- 111, beta 323.6 +- 13.9 against 323.4 +- 13.7,
#: every state's NMSE equal to 3 digits); the nu = 2 loop below (pgas, velocity + displacement, virgin
#: [initial], 150 s cap) at 9 substeps (h |lambda| = 2) against 18: both converged (120 s, 181 s), the
#: posterior means of force, hysteretic force and displacement 0.03 sd apart (median; 0.15 at most),
#: their sds equal within 0.4 %, smoother move acceptance 0.96 against 0.97; at h |lambda| = 3.6 pgas
#: failed (docs/nonlinear.md, "Substeps chosen per record"). An oscillation keeps its bound: its RK4
#: error is damping, a bias in c
RERUN_BOUND = 2.0
#: the most substeps a sample's step takes (the config's limit)
MAX_SUBSTEPS = 64
#: probe states reach this many stationary sds of the linearised system
PROBE_SDS = 3.0
#: probe states drawn (each coordinate -1, 0 or +1 times its scale; a fixed seed: no randomness
#: reaches the result)
N_PROBES = 256


@functools.partial(jit, static_argnames=("model",))
def _probe_jacobians(params, signs, *, model):
    # one compiled program: op by op the Lyapunov solve alone compiled dozens of small ones
    system, L = model.system, model.layout
    _, P = model.stationary_initial(params, linear_part=True)
    scale = PROBE_SDS * jnp.sqrt(jnp.clip(jnp.diagonal(P)[L.mech], 0.0))
    if L.n_internal:
        inner = np.arange(L.n_mech)[L.internal]
        scale = scale.at[inner].set(jnp.minimum(scale[inner], system.internal_bound(params)))
    probes = jnp.concatenate([jnp.zeros((1, L.n_mech)), scale[None], signs * scale])
    u = jnp.zeros(model.nforce)

    def rate(mech):
        z, v, r = L.split_mech(mech)
        return jnp.concatenate([v, system.acceleration(params, z, v, u, r), system.internal_rate(params, z, v, r)])

    return jax.vmap(jax.jacfwd(rate))(probes)


def _linearisation_stable(model, params: dict) -> bool:
    """Whether the structure linearised about rest is asymptotically stable, so that its stationary
    sds exist to scale the probes (a double-well Duffing, k < 0, or an undamped one has none)."""
    return linearised_stability(model.system, numbers(params))[1]


def _eigenvalues(model, params: dict) -> np.ndarray | None:
    """The mechanical rate's Jacobian eigenvalues at every probe state (None: no scale to probe at)."""
    if not _linearisation_stable(model, params):
        return None
    signs = np.random.default_rng(0).integers(-1, 2, size=(N_PROBES, model.layout.n_mech)).astype(float)
    J = np.asarray(_probe_jacobians(numbers(params), signs, model=model))
    return np.linalg.eigvals(J).ravel() if np.all(np.isfinite(J)) else np.array([np.inf])


def _demand_of(lam: np.ndarray | None, real_bound: float = STEP_BOUND) -> float:
    if lam is None:
        return float("nan")
    bound = np.where(np.abs(lam.imag) > np.abs(lam.real), OSCILLATION_BOUND, real_bound)
    return float(np.max(np.abs(lam) / bound))


def demand(model, params: dict) -> float:
    """The substeps a unit of time needs: the largest |lambda| / bound over the probe states'
    eigenvalues, the bound :data:`OSCILLATION_BOUND` for an oscillatory one, :data:`STEP_BOUND`
    otherwise (NaN as :func:`stiffness`)."""
    return _demand_of(_eigenvalues(model, params))


def stiffness(model, params: dict) -> float:
    """rho: the largest modulus of an eigenvalue of the mechanical rate's Jacobian (1/s) over probe
    states: each displacement and velocity at 0 or +-3 of its stationary sd under the system
    linearised about rest (at ``params``, the force's hyperparameters included), each hysteretic
    force at 0 or +-3 sds of its linear-part value, but no further than the bound its rate allows
    (``system.internal_bound``: the loading branch's saturation). NaN where that linearisation is
    not stable (no stationary sds to scale the probes by): :func:`choose` then keeps the count."""
    lam = _eigenvalues(model, params)
    return float("nan") if lam is None else float(np.max(np.abs(lam)))


def _count(rate: float, dt: float) -> int:
    """The fewest substeps ``n`` with ``dt / n * rate <= 1``, ``rate`` from :func:`demand` (uncapped; one
    past the cap for an infinite rate)."""
    return max(1, math.ceil(dt * rate)) if math.isfinite(rate) else MAX_SUBSTEPS + 1


def needed(model, params: dict, dt: float) -> int:
    """The fewest substeps keeping every probe eigenvalue within its bound (:func:`demand`; uncapped),
    or the system's own count where there is no answer."""
    rate = demand(model, params)
    return int(model.system.substeps) if math.isnan(rate) else _count(rate, dt)


#: posterior draws (evenly spread over the chains) at which :func:`needed_over_posterior` probes
N_POSTERIOR_PROBES = 64


def _posterior_eigenvalues(model, fixed: dict, draws: dict) -> list[tuple[dict, np.ndarray | None]]:
    """``(values, eigenvalues)`` at :data:`N_POSTERIOR_PROBES` draws evenly spread over ``draws``
    (:func:`needed_over_posterior`): each draw's sampled values and :func:`_eigenvalues` there."""
    names = [k for k, v in draws.items() if np.size(v)]
    if not names:
        return []
    flat = {k: np.asarray(draws[k], dtype=float).reshape(-1) for k in names}
    size = min(v.size for v in flat.values())
    probes = []
    for i in np.unique(np.linspace(0, size - 1, min(N_POSTERIOR_PROBES, size)).astype(int)):
        values = {k: float(flat[k][i]) for k in names}
        probes.append((values, _eigenvalues(model, {**fixed, **values})))
    return probes


def _worst(probes, dt: float, real_bound: float, default: int) -> tuple[int, dict | None]:
    """``(need, at)`` over :func:`_posterior_eigenvalues`' probes at a real eigenvalue's bound
    ``real_bound`` (``default`` where no probe has an answer; ``at`` None with no probes)."""
    best, at = -math.inf, None
    for values, lam in probes:
        rate = _demand_of(lam, real_bound)
        at = values if at is None else at
        if rate > best:  # NaN (no scale to probe at) never wins
            best, at = rate, values
    return (default if best == -math.inf else _count(best, dt)), at


def needed_over_posterior(model, fixed: dict, draws: dict, dt: float) -> tuple[int, dict | None]:
    """``(need, at)``: the largest :func:`needed` over :data:`N_POSTERIOR_PROBES` draws evenly spread
    over ``draws`` (name -> array of draws of the sampled parameters, any shape with the draws
    flattened), the other parameters at ``fixed``; ``at`` holds the sampled values of the draw that
    needs it (None with no draws). One compiled program serves every draw."""
    probes = _posterior_eigenvalues(model, fixed, draws)
    return _worst(probes, dt, STEP_BOUND, int(model.system.substeps))


def with_substeps(system, n: int):
    """A copy of ``system`` stepping ``n`` substeps per sample (systems are structure only)."""
    out = copy.copy(system)
    out.substeps = int(n)
    return out


def choose(model, params: dict, dt: float, given: int | None) -> tuple[int, str | None]:
    """``(substeps, warning)`` for a nonlinear model at sample step ``dt``: ``given`` (the config's
    ``[system].substeps``) with a warning if it falls short of :func:`needed` with a real eigenvalue's
    bound :data:`RERUN_BOUND` (the step is then at risk, not only less accurate); else the system's
    default count or the need, whichever is larger, capped at :data:`MAX_SUBSTEPS` (with a warning
    when the cap falls short)."""
    lam = _eigenvalues(model, params)  # once: the rule and the message both read them
    rate = _demand_of(lam)
    if math.isnan(rate):  # no scale to probe at (an unstable linearisation, started from [initial])
        return (int(given) if given is not None else int(model.system.substeps)), None
    need = _count(rate, dt)
    tolerated = _count(_demand_of(lam, RERUN_BOUND), dt)  # a fixed count is warned about only below it
    why = (
        f"the mechanical rate's fastest eigenvalue reaches {np.max(np.abs(lam)):.4g} 1/s at the probe "
        f"states (the structure linearised about rest at the parameters' fixed or init values, {PROBE_SDS:g} "
        f"stationary sds), so an RK4 step of {dt:.4g} s needs {need} substeps to keep h |lambda| <= "
        f"{STEP_BOUND:g} ({OSCILLATION_BOUND:g} for an oscillation)"
    )
    if given is not None:
        if given >= tolerated:
            return int(given), None
        return int(given), (
            f"[system].substeps = {given} may be too few: {why}. With too few the sampler's mechanical "
            "step is inaccurate or unstable, and pgas's linearised moves then accept almost nothing. "
            "Leave substeps out to have the count chosen, or raise it."
        )
    n = max(int(model.system.substeps), need)
    if n <= MAX_SUBSTEPS:
        return n, None
    return MAX_SUBSTEPS, (
        f"{why}, more than the {MAX_SUBSTEPS} allowed; the run used {MAX_SUBSTEPS}, and its mechanical step "
        "may be inaccurate or unstable. A higher sample rate (a smaller step) or a check of the system's "
        "parameters (a stiffness or a Bouc-Wen beta, gamma far larger than meant) is the remedy."
    )


# ---- a run's count: chosen at the init values, rechecked at the posterior (estimate.run)


def for_problem(problem: Problem, params0: dict, dt: float) -> tuple[Problem, str | None]:
    """The problem with its nonlinear system's RK4 substeps per sample chosen for this record's step
    (:func:`choose`: the default count, or more where the hysteretic force's rate
    or the structure's frequencies need them), and a warning where a fixed count falls short."""
    model = problem.model
    if model.system.is_linear or problem.inference.method not in ("pgas", "ekf", "ukf"):
        return problem, None
    n, warning = choose(model, params0, dt, problem.substeps)
    if n != model.system.substeps:
        system = with_substeps(model.system, n)
        problem = problem._replace(model=LatentForceModel(system, model.kernel, model.sensors))
    return problem, warning


def recheck(
    problem: Problem, result: RunResult, dt: float, rerun: bool = True, reason: str | None = None
) -> tuple[Problem | None, str | None]:
    """``(problem to rerun, warning)`` once a nonlinear run with sampled parameters is done: the count
    was chosen at the init values, and the posterior may sit where the structure's rate needs more
    (:func:`needed_over_posterior`). A chosen count that falls short (a real eigenvalue's h |lambda|
    past :data:`RERUN_BOUND` at some draw, or an oscillatory one's past :data:`OSCILLATION_BOUND`) gives
    the problem with the posterior's need at the accuracy bound :data:`STEP_BOUND` (the cap's at most)
    to rerun; a count the config fixed, or one at
    the cap, or any count after the rerun (``rerun=False``), a warning (``reason`` in place of the
    count's origin: a rerun that failed, whose first pass then stands). Measured (ekf, the nu = 2
    loop of ``tests/test_substeps.py`` with beta and gamma inferred from init 100 and 80): 6 substeps
    chosen at the init values, 28 needed over the posterior's draws (18 at the truth); 45 s, then
    102 s for the rerun."""
    model = problem.model
    if model.system.is_linear or problem.inference.method not in ("pgas", "ekf", "ukf") or not problem.free:
        return None, None
    chains = result.param_chains or result.param_draws
    draws = {k: chains[k] for k in problem.free if k in chains}
    used = int(model.system.substeps)
    probes = _posterior_eigenvalues(model, dict(problem.fixed), draws)  # once: both bounds read them
    need, at = _worst(probes, dt, STEP_BOUND, used)
    # within RERUN_BOUND (never a larger need than the accuracy bound's): kept without a word
    if at is None or _worst(probes, dt, RERUN_BOUND, used)[0] <= used:
        return None, None
    where = ", ".join(f"{k} = {v:.4g}" for k, v in at.items())
    if rerun and problem.substeps is None and used < MAX_SUBSTEPS:
        system = with_substeps(model.system, min(need, MAX_SUBSTEPS))
        return problem._replace(model=LatentForceModel(system, model.kernel, model.sensors)), None
    if reason is not None:
        what = reason
    elif problem.substeps is not None:
        what = "[system].substeps"
    elif used >= MAX_SUBSTEPS:
        what = f"the cap of {MAX_SUBSTEPS} substeps"
    else:
        what = "chosen at the first pass's posterior, and the run was done twice already"
    return None, (
        f"the posterior reaches parameters ({where}) where the structure's rate needs {need} RK4 substeps a "
        f"sample, more than the {used} this run used ({what}): its mechanical step there may be inaccurate "
        "or unstable. "
        + (
            "Leave substeps out to have the count chosen, or raise it."
            if problem.substeps is not None
            else "A higher sample rate or tighter priors on the system's parameters are the remedy."
        )
    )
