"""The configuration file's shape (stage 1 of :mod:`latentforce.io.config`): the pydantic
schema of every section, and the one-paragraph messages its validation errors become
(``FILE: KEY: message``, with a "did you mean" for misspelt keys)."""

from __future__ import annotations

import difflib
from pathlib import Path
from typing import Annotated, Any, Literal, Union

from pydantic import BaseModel, ConfigDict, Discriminator, Field, Tag, ValidationError

from latentforce.errors import LatentForceError


# ----- stage 1: shape, by pydantic -------------------------------------------
class _Strict(BaseModel):
    # strict: "1.0" is not a number and 2.0 is not an integer (ints are still
    # accepted as floats); allow_inf_nan=False because TOML can spell nan/inf.
    model_config = ConfigDict(strict=True, extra="forbid", allow_inf_nan=False)


class _PriorTable(BaseModel):
    # The prior's own parameters (mean, sd, ...) depend on its name, so they
    # arrive as extras and are checked in stage 2 with a proper suggestion.
    model_config = ConfigDict(strict=True, extra="allow", allow_inf_nan=False)

    prior: str
    init: float | None = None


def _param_kind(value: Any) -> str:
    return "table" if isinstance(value, (dict, _PriorTable)) else "number"


# A number (fixed) or a prior table (inferred); the discriminator keeps
# pydantic from reporting both failed branches of the union.
_Param = Annotated[
    Union[Annotated[float, Tag("number")], Annotated[_PriorTable, Tag("table")]],
    Discriminator(_param_kind),
]
_UNION_TAGS = ("number", "table", "list")


def _param_or_list_kind(value: Any) -> str:
    return "list" if isinstance(value, list) else _param_kind(value)


# [force].variance / lengthscale: one parameter, or a list of them (one per term of a kernel sum)
_ParamOrList = Annotated[
    Union[
        Annotated[float, Tag("number")],
        Annotated[_PriorTable, Tag("table")],
        Annotated[list[_Param], Tag("list")],
    ],
    Discriminator(_param_or_list_kind),
]


class _DataSection(_Strict):
    path: str | None = None
    time_column: str | None = None
    sample_rate: float | None = Field(default=None, gt=0)
    missing: Literal["error", "skip"] = "error"
    dt: float | None = Field(default=None, gt=0)


class _ElementSection(_Strict):
    """``[[system.elements]]``: a nonlinear element of an MDOF structure."""

    type: Literal["cubic", "bouc-wen"]
    dofs: list[Annotated[int, Field(ge=0)]] = Field(min_length=1, max_length=2)
    k3: _Param | None = None
    alpha: _Param | None = None
    beta: _Param | None = None
    gamma: _Param | None = None
    nu: _Param | None = None


class _SystemSection(_Strict):
    type: str
    m: _Param | None = None
    c: _Param | None = None
    k: _Param | None = None
    k3: _Param | None = None
    alpha: _Param | None = None
    beta: _Param | None = None
    gamma: _Param | None = None
    nu: _Param | None = None
    substeps: int | None = Field(default=None, ge=1, le=64)
    # model steps per sample of the nonlinear methods (latentforce.latent_grid; le: its MAX_STEPS)
    steps_per_sample: Literal["auto"] | Annotated[int, Field(ge=1, le=8)] = "auto"
    M: list[list[float]] | None = None
    C: list[list[float]] | None = None
    K: list[list[float]] | None = None
    masses: list[_Param] | None = None
    dampings: list[_Param] | None = None
    stiffnesses: list[_Param] | None = None
    force_dofs: list[int] | None = None
    elements: list[_ElementSection] | None = None


class _ForceSection(_Strict):
    kernel: str
    variance: _ParamOrList
    lengthscale: _ParamOrList


class _SensorSection(_Strict):
    column: str
    quantity: Literal["displacement", "velocity", "acceleration", "strain", "force"]
    dof: int = Field(default=0, ge=0)
    noise_std: _Param  # a number (known) or a prior table (inferred)
    unit: str | None = None
    path: str | None = None
    coefficients: list[float] | None = None  # strain: one per DOF


class _OutputSection(_Strict):
    name: str
    unit: str = ""
    displacement: list[float] | None = None
    velocity: list[float] | None = None
    acceleration: list[float] | None = None
    force: list[float] | None = None


class _InitialSection(_Strict):
    mean: list[float]
    sd: list[Annotated[float, Field(ge=0)]] | None = None
    cov: list[list[float]] | None = None


class _InferenceSection(_Strict):
    method: Literal["kalman", "kalman-mcmc", "kalman-nuts", "pgas", "ekf", "ukf"] | None = None
    particles: Annotated[int, Field(ge=2)] | Literal["auto"] = "auto"
    iterations: Annotated[int, Field(ge=1)] | Literal["auto"] = "auto"
    burn_in: int | None = Field(default=None, ge=0)
    target_ess: float = Field(default=400.0, gt=0)
    max_time: float = Field(default=600.0, gt=0)
    checkpoint_every: float = Field(default=60.0, ge=0)
    state_every: int = Field(default=5, ge=1)
    chains: int = Field(default=4, ge=1)
    seed: int = 0
    mh_steps: int = Field(default=1, ge=1)
    discretisation: Literal["rk4", "euler"] = "rk4"
    proposal: Literal["optimal", "bootstrap"] = "optimal"
    thin_draws: int = Field(default=200, ge=1)
    kalman: Literal["auto", "sequential", "parallel"] = "auto"


class _ConfigFile(_Strict):
    data: _DataSection = Field(default_factory=_DataSection)
    system: _SystemSection
    force: _ForceSection
    sensors: list[_SensorSection] = Field(min_length=1)
    initial: _InitialSection | None = None
    inference: _InferenceSection = Field(default_factory=_InferenceSection)
    outputs: list[_OutputSection] = Field(default_factory=list)


_SECTIONS: dict[str, type[BaseModel]] = {
    "data": _DataSection,
    "system": _SystemSection,
    "force": _ForceSection,
    "sensors": _SensorSection,
    "initial": _InitialSection,
    "inference": _InferenceSection,
    "outputs": _OutputSection,
}


# ----- error messages ------------------------------------------------------------
def _key(loc: tuple) -> str:
    """``('sensors', 1, 'dof')`` -> ``[[sensors]][1].dof``; union tags dropped."""
    if not loc:
        return "(top level)"
    head, rest = loc[0], list(loc[1:])
    # The discriminated union puts its tag after the parameter name.
    if head in ("system", "force"):
        rest = [part for part in rest if part not in _UNION_TAGS]
    out = f"[[{head}]]" if head in ("sensors", "outputs") else f"[{head}]"
    if head == "system" and rest[:1] == ["elements"] and len(rest) > 1:  # [[system.elements]][0].k3
        out, rest = "[[system.elements]]", rest[1:]
    for part in rest:
        out += f"[{part}]" if isinstance(part, int) else f".{part}"
    return out


def _did_you_mean(name: str, valid: list[str] | tuple[str, ...], fmt: str = "`{}`") -> str:
    close = difflib.get_close_matches(str(name), list(valid), n=1, cutoff=0.5)
    return f"; did you mean {fmt.format(close[0])}?" if close else "."


def _unknown_key_message(source: str, loc: tuple) -> str:
    name = loc[-1]
    prefix = loc[:-1]
    if not prefix:
        valid = list(_SECTIONS)
        return (
            f"unknown section [{name}] in {source}{_did_you_mean(name, valid, '[{}]')} "
            f"Valid sections: {', '.join(valid)}."
        )
    model = _ElementSection if prefix[:2] == ("system", "elements") else _SECTIONS.get(prefix[0])
    valid = list(model.model_fields) if model is not None else []
    return (
        f"unknown key `{name}` in {_key(prefix)} of {source}{_did_you_mean(name, valid)} "
        f"Valid keys: {', '.join(valid)}."
    )


def _from_validation_error(source: str, exc: ValidationError) -> LatentForceError:
    """The first (most telling) pydantic error as one paragraph naming the key."""
    errors = exc.errors()
    # A typo explains the "missing" errors it causes, so report it first.
    errors.sort(key=lambda e: e["type"] != "extra_forbidden")
    err = errors[0]
    loc, kind, msg = tuple(err["loc"]), err["type"], err["msg"]
    if kind == "extra_forbidden":
        return LatentForceError(_unknown_key_message(source, loc))
    key = _key(loc)
    if kind == "missing":
        what = f"section {key}" if len(loc) == 1 else key
        return LatentForceError(f"{source}: {what} is required but missing.")
    if kind in ("model_type", "dict_type"):
        return LatentForceError(f"{source}: {key} must be a table.")
    if kind == "list_type" and loc in (("sensors",), ("outputs",)):
        return LatentForceError(
            f"{source}: {key} must be an array of tables: write each one under its own {key} header."
        )
    if kind in ("too_short", "too_long") and loc[:2] == ("system", "elements") and loc[-1] == "dofs":
        return LatentForceError(
            f"{source}: {key}: give [i, j] for an element between DOFs i and j, or [i] for one between DOF i "
            "and the ground."
        )
    if kind == "too_short" and loc == ("sensors",):
        return LatentForceError(f"{source}: at least one [[sensors]] table is required.")
    shown = "" if isinstance(err.get("input"), (dict, list)) else f" = {err.get('input')!r}"
    if loc[:2] == ("inference", "iterations"):  # int | "auto": pydantic names the union's branch
        return LatentForceError(
            f'{source}: [inference].iterations{shown}: give a whole number of draws per chain (1 or more) or "auto" '
            "(lower case: sample until converged, the default)."
        )
    if loc[:2] == ("system", "steps_per_sample"):
        return LatentForceError(
            f"{source}: [system].steps_per_sample{shown}: give a whole number of model steps per sample, 1 to 8, "
            'or "auto" (lower case, the default: checked on hysteretic records).'
        )
    if loc[:2] == ("inference", "particles"):
        return LatentForceError(
            f'{source}: [inference].particles{shown}: give a whole number of particles (2 or more) or "auto" '
            "(lower case, the default: 50, or 16 where pgas runs its window move on a long record)."
        )
    if kind == "float_type" and len(loc) >= 3 and loc[0] in ("system", "force") and loc[-1] == "number":
        msg = (
            "must be a number (known and fixed) or a prior table such as "
            '{ prior = "normal", mean = 1.0, sd = 0.1, init = 1.0 } (inferred)'
        )
    return LatentForceError(f"{source}: {key}{shown}: {msg}.")


class _Fail:
    """Raises stage-2 errors in the common format ``FILE: KEY: message``."""

    def __init__(self, source: str, base_dir: Path | None = None):
        self.source = source
        self.base_dir = Path.cwd() if base_dir is None else Path(base_dir)
        #: priors carried over from earlier runs, by config key (recorded in the result)
        self.carried: dict[str, Any] = {}

    def __call__(self, key: str, message: str) -> LatentForceError:
        return LatentForceError(f"{self.source}: {key}: {message}")
