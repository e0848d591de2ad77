"""A scalar parameter of the config: a number (known and fixed) or a prior table (inferred).

:class:`ParamSpec` is an inferred one; :func:`_split` sorts a key's value into the ``fixed`` or the
``free`` dict, checking a number's sign or the prior table (its kind, its keys, ``init``, or a
``"posterior"`` prior carried from an earlier result folder). Split from ``io/config.py``; every
error names the key.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import NamedTuple

from latentforce.io.carry import carried_prior
from latentforce.io.schema import _did_you_mean, _Fail, _PriorTable
from latentforce.priors import PRIOR_PARAMS, AtLeast, Prior, prior_from_spec


class ParamSpec(NamedTuple):
    """An inferred parameter: its prior on the physical value and a starting value."""

    prior: Prior
    init: float


def _check_init(fail: _Fail, key: str, init: float, signed: bool, note: str = "") -> None:
    if signed and not math.isfinite(init):
        raise fail(f"{key}.init", f"the initial value must be a finite number, got {init!r}{note}.")
    if not signed and not (math.isfinite(init) and init > 0):
        raise fail(f"{key}.init", f"the initial value must be positive and finite, got {init!r}{note}.")


def _carried_spec(fail: _Fail, key: str, table: _PriorTable, param: str, signed: bool) -> ParamSpec:
    """``prior = "posterior"``: the marginal posterior of ``param`` in an earlier result folder
    (:mod:`latentforce.io.carry`), ``from`` resolved against the config's folder."""
    extras = dict(table.model_extra or {})
    for extra in extras:
        if extra not in ("from", "param"):
            valid = ("prior", "from", "param", "init")
            raise fail(
                f"{key}.{extra}",
                f'unknown key for a "posterior" prior{_did_you_mean(extra, valid)} Valid keys: {", ".join(valid)}.',
            )
    source, param = extras.get("from"), extras.get("param", param)
    if not isinstance(source, str) or not source:
        raise fail(
            f"{key}.from",
            'a "posterior" prior needs from = "FOLDER", the result folder of an '
            "earlier run whose posterior becomes this prior.",
        )
    if not isinstance(param, str) or not param:
        raise fail(f"{key}.param", f"must be a parameter name (a string), got {param!r}.")
    folder = fail.base_dir / Path(source).expanduser()
    carried = carried_prior(folder, param, f"{fail.source}: {key}", signed=signed)
    init = table.init if table.init is not None else carried.prior.default_init()
    _check_init(fail, key, init, carried.prior.signed)
    fail.carried[key] = carried
    return ParamSpec(prior=carried.prior, init=float(init))


def _prior_spec(fail: _Fail, key: str, table: _PriorTable, param: str = "", signed: bool = False) -> ParamSpec:
    """The prior table of ``key``; ``signed``: the parameter may take either sign (a ``normal``
    prior is then on the whole real line, :class:`latentforce.priors.SignedNormal`)."""
    name = table.prior
    if name == "posterior":
        return _carried_spec(fail, key, table, param, signed)
    if name not in PRIOR_PARAMS:
        raise fail(
            f"{key}.prior",
            f"unknown prior {name!r}{_did_you_mean(name, tuple(PRIOR_PARAMS), '{!r}')} "
            f"Valid priors: {', '.join(PRIOR_PARAMS)}, posterior "
            "(carried from an earlier result folder).",
        )
    wanted = PRIOR_PARAMS[name]
    extras = dict(table.model_extra or {})
    for extra in extras:
        if extra not in wanted:
            valid = ("prior", "init") + wanted
            raise fail(
                f"{key}.{extra}",
                f"unknown key for a {name!r} prior{_did_you_mean(extra, valid)} Valid keys: {', '.join(valid)}.",
            )
    missing = [p for p in wanted if p not in extras]
    if missing:
        raise fail(key, f"a {name!r} prior needs {' and '.join(wanted)}; missing: {', '.join(missing)}.")
    for p, v in extras.items():
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise fail(f"{key}.{p}", f"must be a finite number, got {v!r}.")
    try:
        prior = prior_from_spec(name, signed=signed, **extras)
    except ValueError as exc:
        raise fail(key, f"{exc}.") from None
    init = table.init if table.init is not None else prior.default_init()
    if init is None:
        raise fail(f"{key}.init", f"a {name!r} prior has no natural starting value: give init (a positive number).")
    _check_init(fail, key, init, prior.signed, "" if table.init is not None else " (from the prior; give init)")
    return ParamSpec(prior=prior, init=float(init))


def _scalar(fail: _Fail, key: str, value: float, rule: str) -> float:
    """Check a fixed scalar: ``rule`` is "positive", "nonnegative" or "any"."""
    words = {
        "m": "mass",
        "c": "damping",
        "k": "stiffness",
        "alpha": "Bouc-Wen stiffness alpha",
        "variance": "force variance",
        "lengthscale": "force lengthscale",
    }
    what = words.get(key.rsplit(".", 1)[-1], "value")
    if rule == "positive" and not value > 0:
        raise fail(key, f"the {what} must be positive, got {value!r}.")
    if rule == "nonnegative" and not value >= 0:
        raise fail(key, f"the {what} must be non-negative, got {value!r}.")
    if rule == "exponent" and not value >= 1:
        raise fail(
            key,
            f"the Bouc-Wen exponent nu must be at least 1, got {value!r}: below 1 the hysteretic "
            "force's rate |r|^(nu-1) r is not Lipschitz at r = 0 (its solution need not be unique).",
        )
    return float(value)


def exponent_prior(spec: ParamSpec) -> ParamSpec:
    """An inferred Bouc-Wen exponent's prior truncated to ``nu >= 1`` (:class:`~latentforce.priors.AtLeast`):
    a log-normal prior reaches below 1, where the rate is not Lipschitz at r = 0, and a user sweep's ukf run
    drew 64 % of its nu there (a fixed nu or an init below 1 is refused outright)."""
    return spec._replace(prior=AtLeast(spec.prior, 1.0))


def _split(fail: _Fail, key: str, name: str, value, rule: str, fixed: dict, free: dict) -> None:
    if isinstance(value, _PriorTable):
        spec = _prior_spec(fail, key, value, name, signed=rule == "any")
        if rule == "exponent":  # Bouc-Wen's nu >= 1, its prior truncated there (:func:`exponent_prior`)
            if not spec.init >= 1:
                raise fail(key, f"init must be at least 1 (the Bouc-Wen exponent), got {spec.init!r}.")
            spec = exponent_prior(spec)
        free[name] = spec
    else:
        fixed[name] = _scalar(fail, key, value, rule)
