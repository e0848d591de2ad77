"""A campaign's second record compiles nothing under ``pgas``: the model's numbers (system, noise
levels, force variance, the data) are arguments of the compiled programs, its structure (system type,
kernel order, sensors' kinds, settings) is static, so ``jax.jit``'s own cache serves a second run of one
structure and shape whatever its numbers. The second run must also give what it gives in a fresh
process (caches cleared): a program shared across numbers never carries the first run's numbers."""

import contextlib
import copy

import jax
import numpy as np
import pytest

import latentforce  # noqa: F401
from latentforce import estimate
from latentforce.io.config import config_from_dict
from latentforce.io.data import Dataset
from latentforce.simulate import measure, simulate

COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"
T, DT = 64, 0.02


@contextlib.contextmanager
def counting_compiles():
    """A list that gets one entry (its duration) per backend compile while the block runs; JAX's
    persistent cache off, so that every compile in the process is one."""
    seen = []

    def listen(event, duration, **_):
        if event == COMPILE_EVENT:
            seen.append(duration)

    old = jax.config.jax_enable_compilation_cache
    jax.config.update("jax_enable_compilation_cache", False)
    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        yield seen
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
        jax.config.update("jax_enable_compilation_cache", old)


def _config(nonlinear: bool, r: int) -> dict:
    """Record ``r``'s configuration: the same structure, its own numbers."""
    system = {
        "type": "duffing" if nonlinear else "linear",
        "m": 1.0 + 0.2 * r,
        "c": 0.4 + 0.1 * r,
        "k": 40.0 + 10.0 * r,
    }
    sensors = [{"column": "acc", "quantity": "acceleration", "noise_std": 0.05 * (1 + r)}]
    if nonlinear:
        system["k3"] = 1e3 * (1 + r)
    else:  # a displacement channel with its own noise, and the acceleration's noise level inferred
        sensors = [
            {"column": "disp", "quantity": "displacement", "noise_std": 0.002 * (1 + r)},
            {
                "column": "acc",
                "quantity": "acceleration",
                "noise_std": {"prior": "lognormal", "mu": float(np.log(0.05 * (1 + r))), "sigma": 1.0},
            },
        ]
    return {
        "system": system,
        "force": {
            "kernel": "matern32",
            "variance": 1.0 + r,
            "lengthscale": {"prior": "lognormal", "mu": float(np.log(0.3 + 0.1 * r)), "sigma": 0.5},
        },
        "sensors": sensors,
        "inference": {"method": "pgas", "particles": 8, "iterations": 4, "burn_in": 4, "chains": 2, "seed": 3},
    }


def _record(nonlinear: bool, r: int):
    cfg = _config(nonlinear, r)
    problem = config_from_dict(copy.deepcopy(cfg), source=f"record{r}.toml")
    params = {k: float(v) for k, v in cfg["system"].items() if k != "type"}
    params.update(force_variance=1.0 + r, force_lengthscale=0.3)
    sim = simulate(jax.random.key(10 + r), problem.model, params, T, DT)
    y = np.asarray(measure(jax.random.key(20 + r), sim, problem.model.sensors))
    names = [s["column"] for s in cfg["sensors"]]
    return problem, Dataset(sim.time, DT, y, np.isfinite(y), names, {})


def _numbers(result) -> dict:
    out = {f"mean/{k}": np.asarray(v) for k, v in result.state_mean.items()}
    out.update({f"sd/{k}": np.asarray(v) for k, v in result.state_sd.items()})
    out.update({f"draws/{k}": np.asarray(v) for k, v in result.param_draws.items()})
    out.update({f"paths/{k}": np.asarray(v) for k, v in result.path_draws.items()})
    return out


# slow-marked to keep CI's time: each case compiles every program twice (140-220 s under load). In CI,
# tests/test_pgas.py::test_runs_through_the_same_channels_compile_once_and_agree_with_their_own_sensors
# shows a second pgas run with other numbers compiling nothing
@pytest.mark.slow
@pytest.mark.parametrize("nonlinear", [True, False], ids=["duffing", "linear-noise-inferred"])
def test_a_second_record_compiles_nothing_and_carries_none_of_the_first_ones_numbers(nonlinear):
    first, second = _record(nonlinear, 0), _record(nonlinear, 1)
    assert first[0].model == second[0].model  # one structure
    with counting_compiles() as compiles:
        estimate.run(*first, seed=0)
        assert compiles  # (else the count below says nothing)
        compiles.clear()
        shared = _numbers(estimate.run(*second, seed=0)[0])
        assert len(compiles) == 0, f"{len(compiles)} programs compiled for the second record"
    jax.clear_caches()
    fresh = _numbers(estimate.run(*second, seed=0)[0])
    assert shared.keys() == fresh.keys()
    for k in fresh:
        np.testing.assert_array_equal(shared[k], fresh[k], err_msg=k)
