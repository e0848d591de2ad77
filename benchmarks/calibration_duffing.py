r"""The Duffing family of ``benchmarks/calibration.py``: ``pgas`` by simulation-based calibration.

SBC needs records drawn from exactly the model the sampler conditions on.
For ``pgas`` that is its own discrete model (:class:`~latentforce.inference.particle_model.ParticleModel`):
the force's GP states and the within-step noise of the mechanical states are
the latent path, the mechanical states follow the RK4 step, and the sensors
see the path through the model's observation map. A replicate draws the
free parameters (hyperparameters, and system parameters where the case frees
them) from their priors (in :mod:`calibration`), then the latent path from its
prior at those values (the initial state from the sampler's prior: the default
of a nonlinear system at the free parameters' initial values), then the record;
the sampler infers the parameters and the path. Ranks are taken for the parameters and for
the force at four times (1/8, 3/8, 5/8 and 7/8 of the record): every one is
uniform if ``pgas`` samples the joint posterior.

Kept apart from ``calibration.py`` (its simulate/run pair, registered there as a
:class:`Family`) so that neither file grows past the house limit.
"""

from __future__ import annotations

import numpy as np

#: the monitored force values, as fractions of the record
LATENT_FRACTIONS = (1 / 8, 3 / 8, 5 / 8, 7 / 8)


def latent_names(T: int) -> list[str]:
    """``force@t``: the force value at sample ``t`` (each fraction of :data:`LATENT_FRACTIONS`)."""
    return [f"force@{int(round(f * (T - 1)))}" for f in LATENT_FRACTIONS]


def time_points(T: int) -> int:
    """How many equally spaced ``time_points`` ``run_pgas`` must record so that every monitored
    time is among them (``T - 1`` a multiple of 8: ``linspace(0, T - 1, 9)`` holds each)."""
    if (T - 1) % 8:
        raise ValueError(f"the Duffing SBC case needs T - 1 divisible by 8, got T = {T}")
    return 9


def mech_initial(problem):
    """The ``[initial]`` section's mechanical block ``(mean, cov)`` as ``estimate`` passes it to
    ``pgas`` (the force states start from their stationary distribution), or None. Without the
    section the family keeps its own default (``simulate``), not ``estimate``'s."""
    from latentforce.estimate_particles import _mechanical_initial

    return None if problem.initial is None else _mechanical_initial(problem, {})


def simulate(rng: np.random.Generator, problem, params: dict, T: int, dt: float):
    """``(y, mask, paths)``: one record from the sampler's own model at ``params``; ``paths["force"]``
    is the true force value at every sample."""
    import jax

    from latentforce.inference import latent
    from latentforce.inference.particle_model import ParticleModel

    model = problem.model
    # The initial state's prior is the sampler's: the user's, else the default at the free
    # parameters' initial values (run_pgas builds its model there and keeps that prior while it
    # samples m, c, k, k3 ...; a nonlinear default depends on c and k)
    initial = mech_initial(problem)
    if initial is None:
        init = dict(params, **{n: spec.init for n, spec in problem.free.items()})
        initial = ParticleModel(model, init, dt, R=model.noise_covariance(init)).initial_mech()
    pm = ParticleModel(model, params, dt, initial=initial, R=model.noise_covariance(params))
    kp = model.kernel_params(params)  # scalars, or one per term of a kernel sum
    tr = pm.transition(kp.variance, kp.lengthscale)
    key = jax.random.key(int(rng.integers(2**31)))
    x = pm.path(latent.gp_prior_path(key, tr, T))
    clean = np.asarray(latent.predicted_observations(pm, x))
    noise_sd = np.sqrt(np.diagonal(np.asarray(model.noise_covariance(params))))
    y = clean + rng.standard_normal(clean.shape) * noise_sd
    return y, np.ones(y.shape, dtype=bool), {"force": np.asarray(x[:, pm.nm])}


def run(key, sampler: str, problem, y, mask, dt: float, settings: dict):
    """``pgas`` as ``estimate`` runs it ("auto" iterations), returning ``(draws, convergence, info)``:
    draws ``{name: (chains, n)}`` of the free hyperparameters and the monitored force values."""
    import jax.numpy as jnp

    from latentforce.inference.pgas import run_pgas

    if sampler in ("ekf", "ukf"):
        return run_gaussian(key, sampler, problem, y, mask, dt, settings)
    if sampler != "pgas":
        raise ValueError(f"the Duffing family runs pgas, ekf or ukf, not {sampler!r}")
    T = y.shape[0]
    free = {name: (spec.prior, spec.init) for name, spec in problem.free.items()}
    params = dict(problem.fixed, **{name: spec.init for name, spec in problem.free.items()})
    out = run_pgas(
        key,
        problem.model,
        params,
        free,
        jnp.asarray(y),
        jnp.asarray(mask),
        dt,
        iterations=None,
        initial=mech_initial(problem),
        time_points=time_points(T),
        **settings,
    )
    theta = {n: np.asarray(v) for n, v in out.theta.items()}
    points = np.asarray(out.force_points)[..., 0]  # (chains, sweeps, P)
    n = min([points.shape[1]] + [v.shape[1] for v in theta.values()])
    draws = {k: v[:, -n:] for k, v in theta.items()}
    index = {int(t): i for i, t in enumerate(np.asarray(out.time_points))}
    for name in latent_names(T):
        draws[name] = points[:, -n:, index[int(name.split("@")[1])]]
    diag = out.diagnostics
    info = {
        "acceptance": float(np.mean(out.acceptance)),
        "draws_per_chain": int(n),
        "switch_rate": float(np.mean(out.switch_rate)),
    }
    for key, name in (
        ("acceptance_smoother", "smoother_acceptance"),
        ("acceptance_joint", "joint_acceptance"),
        ("acceptance_system", "system_acceptance"),
    ):
        if diag.get(key):  # [] where the move did not run
            info[name] = float(np.mean(diag[key]))
    return draws, dict(diag.get("convergence") or {}), info


#: at most this many parameter draws per chain get a smoother pass for the force values (evenly
#: spaced; the ranks use 99 ESS-thinned draws of them)
GAUSSIAN_FORCE_DRAWS = 500


def run_gaussian(key, sampler: str, problem, y, mask, dt: float, settings: dict):
    """``ekf`` / ``ukf`` as ``estimate`` runs them with free parameters: random-walk Metropolis on the
    filter's approximate likelihood ("auto" iterations), the force at each monitored time drawn from
    the smoother's Gaussian at each (evenly thinned) parameter draw: a draw of the approximate
    posterior the method reports, so its ranks show where that posterior is too sure."""
    import jax
    import jax.numpy as jnp

    from latentforce.estimate_particles import gaussian_for
    from latentforce.inference.kalman_mcmc import run_kalman_mcmc
    from latentforce.inference.particle_model import ParticleModel

    T = y.shape[0]
    free = {name: (spec.prior, spec.init) for name, spec in problem.free.items()}
    params0 = dict(problem.fixed, **{name: spec.init for name, spec in problem.free.items()})
    loglik, smoother = gaussian_for(problem, params0, dt, kind=sampler)
    key_mcmc, key_force = jax.random.split(key)
    y0, mask = jnp.asarray(np.where(mask, y, 0.0)), jnp.asarray(mask)
    out = run_kalman_mcmc(
        key_mcmc, problem.model, dict(problem.fixed), free, y0, mask, dt, iterations=None, loglik=loglik, **settings
    )
    names = list(out.draws)
    chains, n = out.draws[names[0]].shape
    keep = np.unique(np.linspace(0, n - 1, min(n, GAUSSIAN_FORCE_DRAWS)).round().astype(int))
    thetas = {k: jnp.asarray(v[:, keep]).reshape(-1) for k, v in out.draws.items()}
    fixed = {k: jnp.asarray(v, dtype=float) for k, v in problem.fixed.items()}
    nm = ParticleModel(problem.model, params0, dt).nm  # the force is the first state after the mechanical ones
    times = jnp.asarray([int(name.split("@")[1]) for name in latent_names(T)])

    @jax.jit
    def force_draws(k, theta):
        def one(k1, th):
            sm = smoother({**fixed, **th}, y0, mask)
            mean, var = sm.means[times, nm], sm.covs[times, nm, nm]
            return mean + jnp.sqrt(jnp.maximum(var, 0.0)) * jax.random.normal(k1, mean.shape)

        return jax.lax.map(lambda a: one(*a), (jax.random.split(k, len(next(iter(theta.values())))), theta))

    force = np.asarray(force_draws(key_force, thetas)).reshape(chains, len(keep), -1)
    draws = {k: np.asarray(v)[:, keep] for k, v in out.draws.items()}
    for i, name in enumerate(latent_names(T)):
        draws[name] = force[:, :, i]
    info = {"acceptance": float(np.mean(out.acceptance)), "draws_per_chain": int(len(keep))}
    return draws, dict(out.convergence), info
