"""What a PGAS run returns: its :class:`PGASOutput`, assembled from the chains and blocks, and its convergence verdict.

:func:`_assemble` pools the chains' running sums into the posterior mean and sd of the
states, keeps the post-burn-in hyperparameters, paths and per-sweep diagnostics;
:func:`_verdict` is the convergence record (R-hat, bulk ESS) over the hyperparameters and
the monitored states, and :func:`convergence_diagnostics` the R-hat and ESS of the
hyperparameters and the force at the recorded time points. Inferred noise levels
(``noise_std_<column>``, :mod:`latentforce.inference.noise_gibbs`) are parameters like the
hyperparameters: recorded per MH iteration (:class:`~latentforce.inference.pgas_block.BlockInfo`),
in ``theta`` and in both verdicts.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import numpy as np

from latentforce.inference import convergence, particle_model
from latentforce.inference.hyper_moves import Hyper, proposal_covariance
from latentforce.inference.pgas_block import BlockInfo, ChainState, Schedule


class PGASOutput(NamedTuple):
    """What :func:`~latentforce.inference.pgas.run_pgas` returns (NumPy arrays; ``chains`` leading)."""

    names: tuple  # inferred parameter names: the free hyperparameters, then the noise levels
    theta: dict  # name -> (chains, iterations), post burn-in (noise levels included)
    theta_burn: dict  # name -> (chains, burn_in)
    trajectories: np.ndarray  # (chains, draws, T, n_state), thinned, post burn-in
    state_mean: dict  # "displacement" | "velocity" | "force" -> (T, ndof|nforce), all post-burn-in sweeps
    state_sd: dict
    acceptance: np.ndarray  # (chains,), post burn-in MH acceptance rate
    switch_rate: np.ndarray  # (chains, sweeps) post burn-in AS switch fraction per sweep
    ess: np.ndarray  # (chains, sweeps) mean ESS/N of the filter per sweep
    log_likelihood: np.ndarray  # (chains, sweeps) PF estimate log p(y | theta) per sweep
    force_points: np.ndarray  # (chains, sweeps, P, nforce) force at `time_points`
    time_points: np.ndarray
    diagnostics: dict
    mh_scale: np.ndarray  # (chains, p) frozen random-walk proposal sd per hyperparameter (log space)


def _parameters(hyper: Hyper, noise_names, info: BlockInfo) -> tuple[tuple, np.ndarray]:
    """``(names, values)``: the inferred parameters' names and their values per MH iteration,
    ``(chains, blocks * state_every, p + s + m)`` (hyperparameters, system parameters, then noise
    levels)."""
    chains, blocks = np.shape(info.accept)[:2]
    theta = np.reshape(info.theta, (chains, blocks * np.shape(info.theta)[2], len(hyper.names)))
    system = np.reshape(info.system, (chains, theta.shape[1], len(hyper.sys_names)))
    noise = np.reshape(info.noise, (chains, theta.shape[1], len(noise_names)))
    names = tuple(hyper.names) + tuple(hyper.sys_names) + tuple(noise_names)
    return names, np.concatenate([theta, system, noise], axis=2)


def _verdict(
    pm: particle_model.ParticleModel,
    hyper: Hyper,
    infos: list,
    sched: Schedule,
    mpoints,
    target_ess: float,
    noise_names=(),
) -> dict:
    """The convergence record over the post-burn-in draws so far (hyperparameters and noise
    levels per iteration, the monitored displacement, velocity and force per sweep)."""
    info = jax.tree_util.tree_map(lambda *a: np.concatenate(a, axis=1), *infos)
    names, values = _parameters(hyper, noise_names, info)
    theta = values[:, sched.burn_in : sched.total]
    params = {n: theta[:, :, i] for i, n in enumerate(names)}
    mon = info.monitored[:, sched.burn_blocks :]  # (chains, sweeps, M, q)
    columns = pm.layout.summary_columns()
    states = {}
    for name, cols in columns.items():
        for j, k in enumerate(cols):
            label = name if len(cols) == 1 else f"{name}_{j}"
            for i, t in enumerate(mpoints):
                states[f"{label}[t={int(t)}]"] = mon[:, :, i, k]
    return convergence.diagnose(params, states, target_ess=target_ess)


def _move_rate(accept, burn_blocks: int) -> list:
    """A path move's acceptance per chain over the post-burn-in blocks; none (``[]``) where the block does
    not make the move (:data:`~latentforce.inference.pgas_block.NOT_RUN`), so that a move that never ran
    does not read as one that never accepted."""
    if accept is None:
        return []
    a = np.asarray(accept)[:, burn_blocks:]
    if a.size == 0 or np.all(np.isnan(a)):
        return []
    return a.mean(axis=1).tolist()


def _assemble(
    pm, hyper, states: ChainState, info: BlockInfo, ref_q, burn_in, total, burn_blocks, n_draws, tpoints, noise_names=()
) -> PGASOutput:
    chains = info.accept.shape[0]
    names, theta = _parameters(hyper, noise_names, info)
    theta = theta[:, :total]
    accept = np.reshape(info.accept, (chains, -1))[:, :total]
    th_post = {n: theta[:, burn_in:, i] for i, n in enumerate(names)}
    th_burn = {n: theta[:, :burn_in, i] for i, n in enumerate(names)}
    count = np.asarray(states.count)[:, None, None]
    s1 = np.asarray(states.sum1)
    s2 = np.asarray(states.sum2)
    # pool the chains: mean and sd over every post-burn-in state sample
    n_all = count.sum()
    mean_c = s1.sum(0) / n_all
    var = np.maximum(s2.sum(0) / n_all - mean_c**2, 0.0)
    mean = mean_c + np.asarray(ref_q)
    sd = np.sqrt(var)
    sl = pm.layout.summary_columns()
    state_mean = {k: mean[:, v] for k, v in sl.items()}
    state_sd = {k: sd[:, v] for k, v in sl.items()}
    cov = np.asarray(jax.vmap(proposal_covariance)(states.rwm))
    mh_sd = np.sqrt(np.diagonal(cov, axis1=1, axis2=2))
    mh_corr = cov / np.maximum(mh_sd[:, :, None] * mh_sd[:, None, :], 1e-300)
    post = slice(burn_blocks, None)
    switch = info.switch_rate[:, post]
    ess = info.ess[:, post]
    fp = info.force_points[:, post]
    # the headline acceptance per chain: the hyperparameters' random walk, or where only system
    # parameters are sampled their move's (zeros read as a stuck sampler); none where nothing is
    system_rate = _move_rate(info.accept_system, burn_blocks)
    headline = accept[:, burn_in:].mean(axis=1) if hyper.names else np.asarray(system_rate, dtype=float).reshape(-1)
    diag = {
        "acceptance": headline.tolist(),
        "switch_rate": switch.mean(axis=1).tolist(),
        "ess_per_particle": ess.mean(axis=1).tolist(),
        "nonfinite_log_likelihood": int(np.sum(~np.isfinite(info.log_likelihood))),
        "mh_proposal_sd": mh_sd.tolist(),
        "mh_proposal_corr": mh_corr.tolist(),
        "mh_sampling_space": "log",
        "acceptance_noncentred": np.reshape(info.accept_noncentred, (chains, -1))[:, burn_in:total]
        .mean(axis=1)
        .tolist()
        if hyper.names
        else [],
        "acceptance_lowfreq": _move_rate(info.accept_lowfreq, burn_blocks),
        "acceptance_residual": _move_rate(info.accept_residual, burn_blocks),
        "acceptance_smoother": _move_rate(info.accept_smoother, burn_blocks),
        "acceptance_window": _move_rate(info.accept_window, burn_blocks),
        "acceptance_joint": _move_rate(info.accept_joint, burn_blocks),
        "acceptance_system": system_rate,
        "acceptance_internal": _move_rate(info.accept_internal, burn_blocks),
        "acceptance_profile": _move_rate(info.accept_profile, burn_blocks),
    }
    if noise_names:  # per chain, per inferred channel: the independence sampler's acceptance
        diag["acceptance_noise"] = {
            n: info.accept_noise[:, burn_blocks:, i].mean(axis=1).tolist() for i, n in enumerate(noise_names)
        }
    diag.update(convergence_diagnostics(th_post, fp, tpoints))
    return PGASOutput(
        names,
        th_post,
        th_burn,
        np.asarray(states.draws)[:, :n_draws],
        state_mean,
        state_sd,
        headline,
        switch,
        ess,
        info.log_likelihood[:, post],
        fp,
        tpoints,
        diag,
        mh_sd,
    )


def convergence_diagnostics(theta: dict, force_points: np.ndarray, tpoints) -> dict:
    """R-hat and bulk ESS (arviz) of the hyperparameters and of the force at the recorded time points."""
    import warnings

    import arviz as az

    out = {"rhat": {}, "ess_bulk": {}}
    series = dict(theta)
    for j, t in enumerate(tpoints):
        for f in range(force_points.shape[-1]):
            series[f"force[{int(t)}]" + (f"[{f}]" if force_points.shape[-1] > 1 else "")] = force_points[:, :, j, f]
    for name, arr in series.items():
        if arr.shape[1] < 4:
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            out["rhat"][name] = float(az.rhat(np.asarray(arr)))
            out["ess_bulk"][name] = float(az.ess(np.asarray(arr)))
    return out
