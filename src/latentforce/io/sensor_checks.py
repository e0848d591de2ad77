"""Config checks of the channels beyond the three motion sensors: strain gauges and load
cells in ``[[sensors]]``, and the virtual sensors of ``[[outputs]]``.

Called by :func:`latentforce.io.config.config_from_dict` with its error
factory ``fail(key, message)``, so that every problem is a one-paragraph
:class:`~latentforce.errors.LatentForceError` naming the config file and key.
"""

from __future__ import annotations

import re
from collections.abc import Callable

from latentforce.outputs import OutputSpec

#: an output's name becomes a column, a netCDF variable and a file name
_NAME = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")
_STATES = ("displacement", "velocity", "force")


def check_sensor(fail: Callable, i: int, sen, system) -> None:
    """A strain gauge has coefficients, one per DOF (and only a strain gauge has them);
    a load cell sits at a DOF where a latent force acts."""
    what = f"sensor {i} (column {sen.column!r})"
    key = f"[[sensors]][{i}].coefficients"
    if sen.quantity == "strain":
        if sen.coefficients is None:
            raise fail(
                key,
                f"{what} measures strain, a linear map of the displacements: give "
                f"coefficients, one per DOF ({system.ndof}).",
            )
        if len(sen.coefficients) != system.ndof:
            raise fail(
                key,
                f"{what} gives {len(sen.coefficients)} coefficient(s) but the system has "
                f"{system.ndof} DOF(s): give one per DOF.",
            )
    elif sen.coefficients is not None:
        raise fail(
            key, f'{what}: coefficients belong to a strain sensor (quantity = "strain"), not to {sen.quantity!r}.'
        )
    if sen.quantity == "force" and sen.dof not in system.force_dofs:
        raise fail(
            f"[[sensors]][{i}].dof",
            f"{what} is a load cell at DOF {sen.dof}, but no latent force acts there "
            f"([system].force_dofs = {list(system.force_dofs)}); a force sensor measures the "
            f"latent force at a DOF it acts on.",
        )


def _reserved(model) -> set[str]:
    """Names an output may not take: ``time``, the states and their per-component labels."""
    names = {"time", *_STATES, "hysteretic_force"}
    widths = (("displacement", model.ndof), ("velocity", model.ndof), ("force", model.nforce))
    for state, width in (*widths, ("hysteretic_force", model.layout.n_internal)):
        names.update(f"{state}_{j}" for j in range(width))
    return names


def validate_outputs(fail: Callable, tables: list[dict], model, parameters=()) -> tuple[OutputSpec, ...]:
    """``[[outputs]]`` tables (already shape-checked) as :class:`~latentforce.outputs.OutputSpec`;
    ``parameters``: the model's parameter names (``k``, ``k_0``, ``force_variance`` ...), which an
    output may not take either (posterior.nc holds both under their names: a user sweep, 2026-12-05,
    found an output ``k_0`` stored over the sampled stiffness's draws)."""
    widths = {"displacement": model.ndof, "velocity": model.ndof, "acceleration": model.ndof, "force": model.nforce}
    reserved = _reserved(model)
    seen: dict[str, int] = {}
    specs = []
    for i, t in enumerate(tables):
        name = t["name"]
        what = f"output {i} ({name!r})"
        if not _NAME.match(name):
            raise fail(
                f"[[outputs]][{i}].name",
                f"{what}: a name must start with a letter and hold only "
                "letters, digits and underscores (it becomes a column "
                "and a file name).",
            )
        if name in reserved or name.endswith(("_mean", "_sd")):
            raise fail(
                f"[[outputs]][{i}].name",
                f"{what}: the name is taken by a state or a summary "
                f"column ({', '.join(sorted(reserved))}, *_mean, *_sd); "
                "choose another.",
            )
        if name in parameters:
            raise fail(
                f"[[outputs]][{i}].name",
                f"{what}: the name is taken by a parameter of the model (posterior.nc and summary.json "
                "hold parameters and outputs under their names); choose another.",
            )
        if name in seen:
            raise fail(f"[[outputs]][{i}].name", f"{what}: the name is already used by output {seen[name]}.")
        seen[name] = i
        given = [k for k in widths if t.get(k) is not None]
        if not given:
            raise fail(
                f"[[outputs]][{i}]",
                f"{what} gives no coefficients: give at least one of "
                "displacement, velocity, acceleration (one per DOF) or force "
                "(one per latent force).",
            )
        for k in given:
            if len(t[k]) != widths[k]:
                per = "latent force" if k == "force" else "DOF"
                raise fail(
                    f"[[outputs]][{i}].{k}",
                    f"{what} gives {len(t[k])} coefficient(s) but the model "
                    f"has {widths[k]} {per}(s): give one per {per}.",
                )
        specs.append(
            OutputSpec(name=name, unit=t.get("unit") or "", **{k: tuple(float(c) for c in t[k]) for k in given})
        )
    return tuple(specs)
