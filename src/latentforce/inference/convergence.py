r"""Convergence diagnostics of a sampling run: R-hat and ESS from arviz-stats.

Every sampling method reports, for each monitored quantity, the
rank-normalised split :math:`\hat R` and the bulk and tail effective sample
sizes (Vehtari, Gelman, Simpson, Carpenter & Bürkner 2021), computed by
``arviz_stats.base.array_stats`` (not our own code), and one verdict:

.. math:: \text{converged} \iff \max \hat R \le 1.01 \;\wedge\;
          \min \mathrm{ESS}_\text{bulk} \ge \text{target} \;\wedge\;
          \min \mathrm{ESS}_\text{tail} \ge \text{target}/4 .

The tail-ESS bound is the weaker one that Vehtari et al. suggest for the
5 %/95 % quantiles of a summary (with 400 as the bulk target, 100 for the
tails); both are reported.

Monitored quantities: every sampled scalar parameter, and, where the method
samples trajectories (``pgas``), the force and each state at
:func:`monitored_times` (at least 20 times spread over the record). For
the Kalman-based methods the states are exact given the parameters (the
smoother, mixed over parameter draws), so their sampling error is that of
the parameters: the parameters and the log-likelihood decide, and the
states' R-hat of the stored paths is reported beside them as information.
"""

from __future__ import annotations

import warnings
from typing import Mapping

import numpy as np

RHAT_MAX = 1.01
TARGET_ESS = 400
MONITORED_TIMES = 24
#: the share of ``max_time`` an "auto" run's warm-up may take: at the first chunk's end past it the
#: adaptation stops and the draws start, so that they get the rest (:func:`warm_up_cut_warning`)
WARM_UP_SHARE = 0.5
#: a worst R-hat from which chains count as stuck apart, not slowly mixing (:func:`warning_message`: a user
#: sweep's run whose proposals were never accepted printed 32151935721977916 and advised running longer)
STUCK_R_HAT = 100.0
#: the least share of ``burn_in`` a warm-up runs however long it takes (the first chunk, the compile with
#: it, can take half of a short ``max_time`` alone: a user sweep's pgas run kept 5 of 100 iterations)
WARM_UP_FLOOR = 0.15


def monitored_times(T: int, n: int = MONITORED_TIMES) -> np.ndarray:
    """``n`` (at most ``T``) time indices spread evenly over a record of ``T`` samples."""
    return np.unique(np.linspace(0, T - 1, min(n, T)).round().astype(int))


def _stats(draws: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """R-hat, bulk ESS and tail ESS of ``draws`` shaped ``(chains, draws, k)``, per column."""
    from arviz_stats.base import array_stats

    a = np.moveaxis(np.asarray(draws, dtype=float), -1, 0)  # (k, chains, draws)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # constant columns give NaN with a RuntimeWarning
        # R-hat compares chains: with one, NaN (the verdict says why) rather than arviz's shape
        # warning on the user's terminal
        rhat = (
            np.asarray(array_stats.rhat(a, chain_axis=-2, draw_axis=-1, method="rank"), dtype=float)
            if a.shape[-2] >= 2
            else np.full(a.shape[:-2], np.nan)
        )
        bulk = np.asarray(array_stats.ess(a, chain_axis=-2, draw_axis=-1, method="bulk"), dtype=float)
        tail = np.asarray(
            array_stats.ess(a, chain_axis=-2, draw_axis=-1, method="tail", prob=(0.05, 0.95)), dtype=float
        )
    return rhat.reshape(-1), bulk.reshape(-1), tail.reshape(-1)


def quantity_stats(quantities: Mapping[str, np.ndarray]) -> dict[str, dict[str, float]]:
    """``{name: {r_hat, ess_bulk, ess_tail}}`` for draws shaped ``(chains, draws)``.

    A quantity that does not vary at all (e.g. a state pinned by an exact
    measurement) has no defined R-hat; it is reported as ``nan`` and left
    out of the verdict, which is about sampling error.
    """
    if not quantities:
        return {}
    names = list(quantities)
    stacked = np.stack([np.asarray(quantities[n], dtype=float) for n in names], axis=-1)
    rhat, bulk, tail = _stats(stacked)
    return {
        n: {"r_hat": float(rhat[i]), "ess_bulk": float(bulk[i]), "ess_tail": float(tail[i])}
        for i, n in enumerate(names)
    }


def state_quantities(
    paths: Mapping[str, np.ndarray], times: np.ndarray, time_values: np.ndarray | None = None
) -> dict[str, np.ndarray]:
    """Monitored scalars from sampled paths ``(chains, draws, T, width)``.

    Named ``force[t=1.25]`` (``force_1[t=1.25]`` for a second component), the
    time in the record's units when ``time_values`` is given, else the index.
    """
    out = {}
    for state, p in paths.items():
        p = np.asarray(p)
        width = p.shape[-1]
        for j in range(width):
            label = state if width == 1 else f"{state}_{j}"
            for t in times:
                at = f"{time_values[t]:.6g}" if time_values is not None else str(int(t))
                out[f"{label}[t={at}]"] = p[:, :, t, j]
    return out


def diagnose(
    params: Mapping[str, np.ndarray],
    states: Mapping[str, np.ndarray] | None = None,
    *,
    target_ess: float = TARGET_ESS,
    rhat_max: float = RHAT_MAX,
    states_decide: bool = True,
    worst: int = 5,
) -> dict:
    """The convergence record of a run (JSON-able), see the module docstring.

    ``params`` and ``states`` map a name to draws shaped ``(chains, draws)``
    (``states`` from :func:`state_quantities`). With ``states_decide`` false
    the states are reported but do not enter ``converged`` (Kalman methods).
    Returns ``{converged, max_r_hat, min_ess_bulk, min_ess_tail, target_ess,
    r_hat_max, worst: [{name, r_hat, ess_bulk, ess_tail}, ...], chains,
    draws, states: {max_r_hat, min_ess_bulk, min_ess_tail, monitored,
    decide}, diverged_chains (only where a chain has non-finite draws)}``.
    Fewer than 2 chains or 4 draws cannot show convergence: ``converged``
    is false and the reason is given.
    """
    stats = quantity_stats(params)
    state_stats = quantity_stats(states or {})
    deciding = dict(stats)
    if states_decide:
        deciding.update(state_stats)
    shapes = [np.shape(v) for v in params.values()] + [np.shape(v) for v in (states or {}).values()]
    chains = min((s[0] for s in shapes), default=0)
    n_draws = min((s[1] for s in shapes), default=0)

    def extreme(table, key, fn):
        vals = [v[key] for v in table.values() if np.isfinite(v[key])]
        return float(fn(vals)) if vals else float("nan")

    record = {
        "max_r_hat": extreme(deciding, "r_hat", max),
        "min_ess_bulk": extreme(deciding, "ess_bulk", min),
        "min_ess_tail": extreme(deciding, "ess_tail", min),
        "target_ess": float(target_ess),
        "r_hat_max": float(rhat_max),
        "chains": int(chains),
        "draws": int(n_draws),
    }
    reasons = []
    if chains < 2:
        reasons.append("R-hat needs at least 2 chains")
    if n_draws < 4:
        reasons.append("too few draws")
    # A chain that diverged (an overflowing state, a NaN path) gives NaN draws, whose R-hat is NaN like
    # a constant's and would leave the verdict: name them instead.
    decided = {**params, **(states or {})} if states_decide else dict(params)
    bad = {n: ~np.isfinite(np.asarray(v, dtype=float)) for n, v in decided.items()}
    broken = [n for n, b in bad.items() if b.any()]
    if broken:
        hit = sorted({int(c) for n in broken for c in np.flatnonzero(bad[n].any(axis=1))})  # (chains, draws)
        more = ", ..." if len(broken) > 3 else ""
        reasons.append(
            f"non-finite draws in {len(broken)} quantities ({', '.join(broken[:3])}{more}) on chain(s) "
            f"{', '.join(map(str, hit))} (counting from 0): a chain diverged"
        )
        record["diverged_chains"] = hit
    finite = [v for v in deciding.values() if np.isfinite(v["r_hat"])]
    if not finite and not reasons:
        reasons.append("no quantity varies")
    ok = (
        not reasons
        and record["max_r_hat"] <= rhat_max
        and record["min_ess_bulk"] >= target_ess
        and record["min_ess_tail"] >= target_ess / 4
    )
    record["converged"] = bool(ok)

    def badness(item):
        name, v = item
        r = v["r_hat"] if np.isfinite(v["r_hat"]) else 1.0
        # R-hat excess and ESS shortfall on one scale: 1.01 ~ 400, 1.1 ~ 40.
        e = min(v["ess_bulk"], 4 * v["ess_tail"]) if np.isfinite(v["ess_bulk"]) else float("inf")
        return max((r - 1.0) / max(rhat_max - 1.0, 1e-12), target_ess / max(e, 1e-12))

    ranked = sorted(deciding.items(), key=badness, reverse=True)[:worst]
    record["worst"] = [{"name": n, **v} for n, v in ranked]
    if state_stats:
        record["states"] = {
            "max_r_hat": extreme(state_stats, "r_hat", max),
            "min_ess_bulk": extreme(state_stats, "ess_bulk", min),
            "min_ess_tail": extreme(state_stats, "ess_tail", min),
            "monitored": len(state_stats),
            "decide": bool(states_decide),
        }
    if reasons:
        record["reason"] = "; ".join(reasons)
    return record


def warning_message(record: dict, method: str, hint: str = "") -> str | None:
    """A one-paragraph warning for an unconverged run (``None`` if converged). Where a chain diverged
    (``record["diverged_chains"]``) the advice is about the model, not about running longer, and
    ``hint`` (a sentence naming a likely cause in the user's model, or "") follows it."""
    if record.get("converged", False):
        return None
    worst = ", ".join(
        f"{w['name']} (R-hat {w['r_hat']:.3f}, bulk ESS {w['ess_bulk']:.0f})"
        if w["r_hat"] < STUCK_R_HAT
        else f"{w['name']} (R-hat > {STUCK_R_HAT:g}, bulk ESS {w['ess_bulk']:.0f})"
        for w in record.get("worst", [])[:3]
    )
    why = f" ({record['reason']})" if "reason" in record else ""
    advice = {
        "pgas": 'run longer (iterations = "auto" with a larger max_time), use more particles, or check '
        "that the force kernel suits the data",
        "kalman-mcmc": 'run longer (iterations = "auto" with a larger max_time), or try '
        'method = "kalman-nuts"; check diagnostics.start.modes for a posterior with '
        "several modes",
        "kalman-nuts": 'run longer (iterations = "auto" with a larger max_time); check '
        "diagnostics.start.modes for a posterior with several modes",
    }.get(method, "run longer")
    if not record.get("max_r_hat", 0.0) < STUCK_R_HAT:  # (NaN too)
        advice = (
            "the chains sit apart and hardly move (R-hat this large is no slow mixing), so running longer will "
            "not help: the model probably cannot follow the data near where the chains started. Check its "
            'parameters, units and sensor noise against the data (a fit with method = "ekf" or "ukf" '
            "at fixed parameters shows quickly where it fails)"
        )
    if record.get("diverged_chains"):
        advice = (
            "running longer does not help where a chain diverged: the model's step overflowed at the values "
            "that chain reached, so the model cannot follow the data there. Check the parameters' values and "
            "units and that no prior reaches values the structure cannot have (a negative stiffness, an "
            f"unstable structure){hint}"
        )
    r_hat = record["max_r_hat"]
    # four decimals where three would read as passing (1.0104 is not <= 1.01, but "1.010" looks it)
    shown = f"{r_hat:.4f}" if round(r_hat, 3) <= record["r_hat_max"] < r_hat else f"{r_hat:.3f}"
    shown = shown if r_hat < STUCK_R_HAT else f"> {STUCK_R_HAT:g}"
    return (
        f"NOT CONVERGED{why}: worst max R-hat {shown} (need <= {record['r_hat_max']}), "
        f"min bulk ESS {record['min_ess_bulk']:.0f} (need >= {record['target_ess']:.0f}); worst "
        f"quantities: {worst}. The posterior summaries and bands may be wrong: {advice}."
    )


def warm_up_cut_warning(planned: int, run: int, max_time: float) -> str | None:
    """The warning of an "auto" run whose warm-up :data:`WARM_UP_SHARE` of ``max_time`` cut short:
    ``run`` of ``planned`` iterations (``None`` where it was not cut)."""
    if run >= planned:
        return None
    return (
        f"the warm-up stopped after {run} of its {planned} iterations (burn_in), when half of max_time "
        f"({WARM_UP_SHARE * max_time:.0f} of {max_time:.0f} s) had passed, so that the draws get the other "
        "half: the proposals were adapted for that long only and the chains may still carry their start. "
        "Raise max_time, or lower burn_in to what this machine runs in half of it."
    )
