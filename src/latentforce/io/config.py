"""The TOML configuration file: read, validate, and turn into a :class:`Problem`.

The schema is INTERFACE.md's ``[data]``, ``[system]``, ``[force]``,
``[[sensors]]``, ``[initial]`` and ``[inference]`` sections. Validation has
two stages:

1. *shape*: pydantic v2 models (strict types, unknown keys refused, no NaN
   or inf) check each key on its own;
2. *meaning*: plain Python checks what depends on several keys (a positive
   mass, matrices of one size, a sensor DOF inside the system, an initial
   state of the right length, a method that suits the system); ``[system]``'s
   checks and system objects are :mod:`latentforce.io.system_config`'s.

Every problem becomes a one-paragraph
:class:`~latentforce.errors.LatentForceError` naming the config file and the
key (``[system].m``, ``[[sensors]][1].dof``; sensors count from 0); no
pydantic ``ValidationError`` or ``KeyError`` escapes. A mistyped section or
key gets the closest valid name as a suggestion.

A scalar parameter is either a number (known and fixed) or a table with a
prior and an initial value (inferred); the resulting :class:`Problem` keeps
them apart in ``fixed`` and ``free`` under the names the rest of the package
uses (``m, c, k, k3`` or ``M, C, K``, ``force_variance``,
``force_lengthscale``).
"""

from __future__ import annotations

import re
import tomllib
from pathlib import Path
from typing import NamedTuple

import numpy as np
from pydantic import ValidationError

from latentforce.errors import LatentForceError
from latentforce.io.matrices import _initial_state
from latentforce.io.params import ParamSpec, _prior_spec, _split
from latentforce.io.schema import (
    _ConfigFile,
    _did_you_mean,
    _Fail,
    _from_validation_error,
    _PriorTable,
    _SensorSection,
)
from latentforce.io.sensor_checks import check_sensor, validate_outputs
from latentforce.io.system_config import BOUC_WEN_KEYS, PLANNED_SYSTEM_TYPES, SCALAR_RULES, _system  # noqa: F401
from latentforce.kernels import KERNELS, kernel_from_name
from latentforce.models import LatentForceModel, Sensor, hyper_names, is_hyper_name

__all__ = [
    "DataSettings",
    "InferenceSettings",
    "ParamSpec",
    "Problem",
    "config_from_dict",
    "data_path",
    "data_sources",
    "samples",
    "initial_params",
    "load_config",
]

METHODS = ("kalman", "kalman-mcmc", "kalman-nuts", "pgas", "ekf", "ukf")
#: warm-up iterations per chain when [inference].burn_in is not given: the Kalman
#: samplers start at the posterior's modes (Laplace), so a short warm-up adapts them
DEFAULT_BURN_IN = {"kalman": 0, "kalman-mcmc": 500, "kalman-nuts": 300, "pgas": 1000, "ekf": 500, "ukf": 500}


# ----- the result ------------------------------------------------------------
class InferenceSettings(NamedTuple):
    """``[inference]`` with defaults filled in and ``method`` resolved."""

    method: str
    particles: int | None  # None: "auto" (pgas_defaults.default_particles)
    iterations: int | None  # None: "auto" (run until converged or max_time)
    burn_in: int
    state_every: int
    chains: int
    seed: int
    mh_steps: int
    discretisation: str
    proposal: str
    thin_draws: int
    target_ess: float = 400.0
    max_time: float = 600.0
    checkpoint_every: float = 60.0  # seconds between checkpoints (latentforce.checkpoint); 0: every chunk
    kalman: str = "auto"  # "auto" | "sequential" | "parallel" (latentforce.inference.kalman_choice)


class DataSettings(NamedTuple):
    """``[data]``: ``path`` is absolute (None when the config gives none);
    exactly one of ``time_column`` and ``sample_rate`` is set. ``dt``: the
    common time grid's step (None: the fastest channel's). ``units`` and
    ``sensor_paths``: each sensor's ``unit`` and ``path`` keys (None where
    not given; paths absolute), in sensor order."""

    path: Path | None
    time_column: str | None
    sample_rate: float | None
    missing: str
    dt: float | None = None
    units: tuple[str | None, ...] = ()
    sensor_paths: tuple[Path | None, ...] = ()


class Problem(NamedTuple):
    """Everything a run needs from a config file, validated."""

    model: LatentForceModel
    fixed: dict[str, float | np.ndarray]
    free: dict[str, ParamSpec]
    columns: list[str]
    initial: tuple[np.ndarray, np.ndarray] | None
    inference: InferenceSettings
    data: DataSettings
    config_path: Path
    #: priors carried over from earlier result folders, by config key (``prior = "posterior"``)
    carried: dict = {}
    outputs: tuple = ()  # latentforce.outputs.OutputSpec per [[outputs]] table
    #: ``[system].substeps`` as given (None: chosen per record, :func:`latentforce.substeps.choose`)
    substeps: int | None = None
    #: ``[system].steps_per_sample`` as given (None: "auto", :func:`latentforce.latent_grid.choose`)
    steps_per_sample: int | None = None
    #: warnings about the file that do not stop the run (keys the method ignores), for the run's own
    notes: tuple[str, ...] = ()


# ----- stage 2: meaning ------------------------------------------------------
def _sensor(fail: _Fail, i: int, sen: _SensorSection, free: dict, noise_names: dict) -> Sensor:
    """A :class:`Sensor` from ``[[sensors]][i]``; an inferred ``noise_std`` joins ``free``
    as ``noise_std_<column>`` (:attr:`Sensor.noise_param`)."""
    key = f"[[sensors]][{i}].noise_std"
    sensor = Sensor(
        sen.quantity,
        sen.dof,
        1.0,
        name=sen.column,
        coefficients=None if sen.coefficients is None else tuple(sen.coefficients),
    )
    if not isinstance(sen.noise_std, _PriorTable):
        if not sen.noise_std > 0:
            raise fail(
                key, f"the noise standard deviation of column {sen.column!r} must be positive, got {sen.noise_std!r}."
            )
        return sensor._replace(noise_std=float(sen.noise_std))
    name = sensor.noise_param
    if name in noise_names:
        raise fail(
            key,
            f"columns {noise_names[name]!r} and {sen.column!r} both give the parameter name "
            f"{name!r} to their inferred noise; rename one of the columns.",
        )
    noise_names[name] = sen.column
    spec = _prior_spec(fail, key, sen.noise_std, name)
    free[name] = spec
    return sensor._replace(noise_std=spec.init)


def _default_method(is_linear: bool, free: dict) -> str:
    if not is_linear:
        return "pgas"
    return "kalman-mcmc" if free else "kalman"


_FRAME_KEYS = {"m": "masses", "c": "dampings", "k": "stiffnesses"}


def config_key(name: str) -> str:
    """The config key of a parameter name: ``force_variance`` -> ``[force].variance``,
    a shear frame's ``k_1`` -> ``[system].stiffnesses[1]``."""
    if name.startswith("noise_std_"):
        return f"[[sensors]].noise_std (column {name.removeprefix('noise_std_')!r})"
    if name.startswith("force_"):
        key, _, term = name.removeprefix("force_").partition("_")
        return f"[force].{key}[{term}]" if term else f"[force].{key}"
    kind, _, index = name.partition("_")
    if kind.startswith("element") and kind.removeprefix("element").isdigit():
        return f"[[system.elements]][{kind.removeprefix('element')}].{index}"
    if index.isdigit() and kind in _FRAME_KEYS:
        return f"[system].{_FRAME_KEYS[kind]}[{index}]"
    return f"[system].{name}"


def _kernel_suggestion(name: str) -> str:
    """ "; did you mean 'matern32'?" for a kernel name with another case, its digits swapped
    (matern23) or a close spelling; "." when nothing is close."""
    low = name.lower().replace("-", "").replace("_", "").replace(" ", "")
    for valid in KERNELS:
        digits = valid[len("matern") :]
        if low == valid or (low.startswith("matern") and sorted(low[len("matern") :]) == sorted(digits)):
            return f"; did you mean {valid!r}?"
    return _did_you_mean(name, tuple(KERNELS), "{!r}")


def _force(fail: _Fail, f, fixed: dict, free: dict):
    """``[force]``: the kernel (a Matérn, or a sum of them written with ``+``) and its
    hyperparameters, one number or prior table each, or a list of them (one per term) for a sum."""
    terms = [t.strip() for t in f.kernel.split("+")]
    for t in terms:
        if t not in KERNELS:
            raise fail(
                "[force].kernel",
                f"unknown kernel {t!r}{_kernel_suggestion(t)} "
                f'Valid kernels: {", ".join(KERNELS)}, or a sum of them such as "matern12 + matern52".',
            )
    kernel = kernel_from_name(f.kernel)
    names = dict(zip(("variance", "lengthscale"), hyper_names(kernel, split=True)))
    for key, value in (("variance", f.variance), ("lengthscale", f.lengthscale)):
        if len(terms) == 1:
            if isinstance(value, list):
                raise fail(
                    f"[force].{key}",
                    f"is a list of {len(value)} but the kernel {f.kernel!r} has one term: give one number "
                    "or prior table (a list is for a sum of kernels, one entry per term).",
                )
            _split(fail, f"[force].{key}", names[key][0], value, "positive", fixed, free)
            continue
        if not isinstance(value, list) or len(value) != len(terms):
            got = f"a list of {len(value)}" if isinstance(value, list) else "one value"
            raise fail(
                f"[force].{key}",
                f"the kernel {f.kernel!r} is a sum of {len(terms)} terms, each with its own {key}: give a list "
                f"of {len(terms)} (numbers or prior tables, in the kernel's order), got {got}.",
            )
        for i, v in enumerate(value):
            _split(fail, f"[force].{key}[{i}]", names[key][i], v, "positive", fixed, free)
    return kernel


def config_from_dict(
    d: dict, source: str = "<dict>", base_dir: Path | str | None = None, data_override: str | Path | None = None
) -> Problem:
    """Validate a config given as a dict (as parsed from TOML) and build the :class:`Problem`.

    ``source`` names the config in messages; relative data paths are resolved
    against ``base_dir`` (default: the current folder). ``data_override``
    replaces ``[data].path`` and is resolved against the current folder.
    """
    base_dir = Path.cwd() if base_dir is None else Path(base_dir)
    fail = _Fail(source, base_dir)
    if not isinstance(d, dict):
        raise LatentForceError(f"{source}: a config must be a table of sections, got {type(d).__name__}.")
    try:
        cfg = _ConfigFile.model_validate(d)
    except ValidationError as exc:
        raise _from_validation_error(source, exc) from None

    fixed: dict[str, float | np.ndarray] = {}
    free: dict[str, ParamSpec] = {}
    system = _system(fail, cfg.system, fixed, free)

    kernel = _force(fail, cfg.force, fixed, free)

    sensors = []
    seen: dict[str, int] = {}
    noise_names: dict[str, str] = {}
    for i, sen in enumerate(cfg.sensors):
        if sen.dof >= system.ndof:
            valid = "only DOF 0" if system.ndof == 1 else f"DOFs 0..{system.ndof - 1}"
            raise fail(
                f"[[sensors]][{i}].dof",
                f"sensor {i} (column {sen.column!r}) measures DOF {sen.dof} but the system has {valid}.",
            )
        if sen.column in seen:
            raise fail(
                f"[[sensors]][{i}].column", f"column {sen.column!r} is already used by sensor {seen[sen.column]}."
            )
        seen[sen.column] = i
        _check_sensor_unit(fail, i, sen)
        check_sensor(fail, i, sen, system)
        sensors.append(_sensor(fail, i, sen, free, noise_names))
    model = LatentForceModel(system, kernel, sensors)
    outputs = validate_outputs(fail, [o.model_dump() for o in cfg.outputs], model, {*fixed, *free})

    initial = None
    if cfg.initial is not None:
        initial = _initial_state(cfg.initial, model, kernel, fail)

    inf = cfg.inference
    method = inf.method or _default_method(system.is_linear, free)
    if method in ("kalman", "kalman-mcmc", "kalman-nuts") and not system.is_linear:
        why = (
            f"its [[system.elements]] ({', '.join(sorted({e.type for e in cfg.system.elements}))}) make it nonlinear"
            if cfg.system.elements
            else f"[system].type is {cfg.system.type!r}"
        )
        raise fail(
            "[inference].method",
            f'method {method!r} needs a linear system but {why}; use method = "pgas" (or the Gaussian '
            f'approximations "ekf", "ukf").',
        )
    if method == "kalman" and free:
        names = ", ".join(config_key(n) for n in free)
        raise fail(
            "[inference].method",
            f'method "kalman" needs every parameter fixed, but {names} '
            f'has a prior; use method = "kalman-mcmc" to infer it, or give '
            f"a number.",
        )
    if method in ("kalman-mcmc", "kalman-nuts") and not free:
        raise fail(
            "[inference].method",
            f'method "{method}" needs at least one inferred parameter '
            "(a prior table), but every parameter is fixed; use "
            'method = "kalman".',
        )
    if method == "pgas":
        for name in free:
            # PGAS infers (Algorithm 4, Vibration 2020, with Metropolis-within-Gibbs on the force
            # hyperparameters) those, the system's own (m, c, k, k3 ..., moved by the joint move of
            # latentforce.inference.smoother_move and the move of latentforce.inference.system_moves)
            # and the sensors' noise levels (an exact Gibbs step each, latentforce.inference.noise_gibbs)
            if not is_hyper_name(name) and name not in noise_names and name not in system.param_names:
                raise fail(
                    config_key(name),
                    f'method "pgas" can infer the system\'s parameters, the force variance and '
                    f"lengthscale and the sensors' noise_std; {name} is none of them: "
                    f"give it as a number.",
                )
    if samples(method, free) and inf.iterations == "auto" and inf.chains < 2:
        raise fail(
            "[inference].chains",
            f'iterations = "auto" samples until the chains agree (R-hat <= 1.01), which needs at least 2 '
            f"chains, but chains = {inf.chains}; give chains = 2 or more (default 4), or a fixed number of "
            "iterations.",
        )
    notes = _unused_inference_keys(inf, method)
    settings = InferenceSettings(
        method=method,
        particles=None if inf.particles == "auto" else inf.particles,
        iterations=None if inf.iterations == "auto" else inf.iterations,
        burn_in=DEFAULT_BURN_IN[method] if inf.burn_in is None else inf.burn_in,
        state_every=inf.state_every,
        chains=inf.chains,
        seed=inf.seed,
        mh_steps=inf.mh_steps,
        discretisation=inf.discretisation,
        proposal=inf.proposal,
        thin_draws=inf.thin_draws,
        target_ess=inf.target_ess,
        max_time=inf.max_time,
        checkpoint_every=inf.checkpoint_every,
        kalman=inf.kalman,
    )

    dat = cfg.data
    if dat.time_column is not None and dat.sample_rate is not None:
        raise fail("[data].sample_rate", "give either [data].time_column or [data].sample_rate, not both.")
    if data_override is not None:
        path: Path | None = Path(data_override).expanduser().resolve()
    elif dat.path is not None:
        path = (base_dir / Path(dat.path).expanduser()).resolve()
    else:
        path = None
    # With a sample rate the time axis is implicit; otherwise default to "time".
    time_column = None if dat.sample_rate is not None else (dat.time_column or "time")
    data = DataSettings(
        path=path,
        time_column=time_column,
        sample_rate=dat.sample_rate,
        missing=dat.missing,
        dt=dat.dt,
        units=tuple(sen.unit for sen in cfg.sensors),
        sensor_paths=tuple(
            None if sen.path is None else (base_dir / Path(sen.path).expanduser()).resolve() for sen in cfg.sensors
        ),
    )

    carried = {
        key: {
            "from": c.source,
            "param": c.param,
            "draws": c.draws,
            "converged": c.converged,
            **(
                {"normal_mean": c.prior.mean, "normal_sd": c.prior.sd}
                if c.prior.signed
                else {"softplus_loc": c.prior.loc, "softplus_scale": c.prior.scale}
            ),
        }
        for key, c in fail.carried.items()
    }
    return Problem(
        model=model,
        fixed=fixed,
        free=free,
        columns=[s.name for s in sensors],
        initial=initial,
        inference=settings,
        data=data,
        config_path=Path(source),
        carried=carried,
        outputs=outputs,
        substeps=cfg.system.substeps,
        steps_per_sample=None if cfg.system.steps_per_sample == "auto" else cfg.system.steps_per_sample,
        notes=notes,
    )


#: [inference] keys that only some methods read (the others ignore them): key -> those methods
_METHOD_KEYS = {
    "particles": ("pgas",),
    "state_every": ("pgas",),
    "mh_steps": ("pgas",),
    "proposal": ("pgas",),
    "kalman": ("kalman", "kalman-mcmc", "kalman-nuts"),
}


def _unused_inference_keys(inf, method: str) -> tuple[str, ...]:
    """A warning for each ``[inference]`` key given in the file that ``method`` does not read (a user who
    switched methods and thinks the key still applies gets told)."""
    unused = [k for k, methods in _METHOD_KEYS.items() if k in inf.model_fields_set and method not in methods]
    if not unused:
        return ()
    which = "; ".join(f"{k} ({' / '.join(_METHOD_KEYS[k])} only)" for k in unused)
    return (
        f"[inference] sets {', '.join(unused)}, which method {method!r} does not use: {which}. They were ignored; "
        "remove them, or choose a method that uses them.",
    )


_TOML_POSITION = re.compile(r"\(at line (\d+), column (\d+)\)")


def load_config(path: str | Path, data_override: str | None = None) -> Problem:
    """Read and validate a TOML config file; ``data_override`` replaces ``[data].path``."""
    path = Path(path)
    if not path.exists():
        raise LatentForceError(f"config file {str(path)!r} not found.")
    if not path.is_file():
        raise LatentForceError(f"config file {str(path)!r} is not a file.")
    try:
        with open(path, "rb") as fh:
            raw = tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        text = str(exc)
        pos = _TOML_POSITION.search(text)
        where = f" at line {pos.group(1)}, column {pos.group(2)}" if pos else ""
        reason = _TOML_POSITION.sub("", text).strip()
        raise LatentForceError(f"{path}: invalid TOML{where}: {reason}.") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise LatentForceError(f"config file {str(path)!r} cannot be read ({exc}).") from None
    problem = config_from_dict(raw, source=str(path), base_dir=path.resolve().parent, data_override=data_override)
    return problem._replace(config_path=path.resolve())


def _check_sensor_unit(fail: _Fail, i: int, sen: _SensorSection) -> None:
    """A sensor's ``unit`` must parse and fit its quantity (io/units.py)."""
    if sen.unit is None:
        return
    from latentforce.io.units import resolve_unit

    try:
        resolve_unit(sen.quantity, sen.unit, None, who=f"sensor {i} (column {sen.column!r})", where="")
    except LatentForceError as exc:
        raise fail(f"[[sensors]][{i}].unit", str(exc)) from None


# ----- small helpers for the commands ------------------------------------------
def data_path(problem: Problem) -> Path:
    """The data file to read, or an error when neither the config nor ``--data`` gives one."""
    if problem.data.path is None:
        raise LatentForceError(
            f"{problem.config_path}: [data].path is missing; give it in the config or pass --data FILE."
        )
    return problem.data.path


def samples(method: str, free) -> bool:
    """Whether a run of ``method`` with the inferred parameters ``free`` samples (chains, R-hat,
    a checkpoint): the MCMC methods always, ``ekf``/``ukf`` when some parameter is inferred."""
    return method in ("kalman-mcmc", "kalman-nuts", "pgas") or (method in ("ekf", "ukf") and bool(free))


def data_sources(problem: Problem) -> tuple[Path, ...]:
    """Every data file the problem reads: ``[data].path`` (or ``--data``) first, then the sensors'
    own ``path`` keys (each once); the :func:`data_path` error when a sensor has no file."""
    own = tuple(getattr(problem.data, "sensor_paths", ()) or ()) or (None,) * len(problem.columns)
    if problem.data.path is None and (not own or any(p is None for p in own)):
        data_path(problem)
    out = [Path(problem.data.path)] if problem.data.path is not None else []
    for p in own:
        if p is not None and Path(p) not in out:
            out.append(Path(p))
    return tuple(out)


def initial_params(problem: Problem) -> dict[str, float | np.ndarray]:
    """All parameters at their starting point: fixed values plus each free ``init``."""
    return {**problem.fixed, **{name: spec.init for name, spec in problem.free.items()}}
