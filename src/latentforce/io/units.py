"""Units of measured channels: parsed by pint, checked against the sensor's quantity, scaled to SI.

A channel's unit comes from the sensor's ``unit`` key, else from the data
file (a UFF record's ordinate units label, a TDMS channel's ``unit_string``,
a SEP005 record's ``unit_str``, a netCDF or HDF5 variable's ``units``
attribute), else SI is assumed. The data are multiplied
by the unit's factor to SI before inference, and so is the sensor's
``noise_std``, which is given in the channel's unit.

Words the units library reads differently from a vibration engineer:
``g`` is standard gravity (9.80665 m/s², so ``mg`` is a thousandth of it),
never the gram, since no sensor here measures a mass; ``strain`` is a
dimensionless unit (``ustrain``, ``µε`` = 1e-6). Labels in the UDUNITS
syntax of netCDF files (CF conventions), which pint does not read, are read
after rewriting: a power written after its unit (``"m s-2"``, ``"m/s2"``,
``"m.s^-2"``) and ``.`` as the product. The registry holding these
definitions is private to this module (STYLE.md 7a: importing changes
nothing global) and is built on first use only, since building it takes a
second or two.
"""

from __future__ import annotations

import functools
import math
import re
from typing import NamedTuple

from latentforce.errors import LatentForceError

__all__ = ["NO_UNIT", "SI_UNITS", "ChannelUnit", "override_warning", "resolve_unit", "unit_scale"]

#: The unit every quantity is converted to before inference.
SI_UNITS: dict[str, str] = {
    "displacement": "m",
    "velocity": "m/s",
    "acceleration": "m/s^2",
    "force": "N",
    "strain": "m/m",
}


class _WrongDimension(ValueError):
    """A unit that parses but measures something else."""


#: Vendor spellings pint reads as something else ("g's" as g times seconds).
_ALIASES = {"g's": "g", "G's": "g", "g’s": "g", "G’s": "g"}
#: Labels that say a channel is in some unit without naming it (pint: "EU" is the enzyme unit).
_UNNAMED = {"eu", "engineering units", "engineering unit", "eng. units", "eng units"}

#: Labels vendor files use for "no unit given" (pyuff writes "NONE" by default).
NO_UNIT = {"", "none", "null", "n/a", "na", "-"}


class ChannelUnit(NamedTuple):
    """How a channel's numbers were turned into SI.

    ``unit``: the unit the numbers were given in (the sensor's ``unit``, the
    file's label, or the SI unit when neither gives one); ``si``: the SI unit
    the data now carry; ``scale``: SI per ``unit`` (data and ``noise_std``
    are multiplied by it); ``source``: ``"sensor"``, ``"file"`` or
    ``"assumed"``; ``file_label``: where the sensor's ``unit`` overrode a
    label of the file's that reads as another unit of the same dimension,
    that label (None otherwise: :func:`override_warning`).
    """

    unit: str
    si: str
    scale: float
    source: str
    file_label: str | None = None


@functools.cache
def _registry():
    import pint

    ureg = pint.UnitRegistry()
    # Vibration usage, see the module docstring: g is the acceleration of gravity.
    ureg.define("g = standard_gravity")
    # but "kg" stays the kilogram (else kilo-gravities: "kg m s-2", a newton in UDUNITS, would not be one)
    ureg.define("kg = kilogram")
    ureg.define("strain = 1 = ε")
    return ureg


#: UDUNITS writes a power straight after its unit ("s-2", "m2", "s^-2"); pint needs "**".
_UDUNITS_POWER = re.compile(r"(?<=[A-Za-zµμ])\^?([-+]?\d+)(?![\d.])")
#: and "." between units as their product ("m.s-2")
_UDUNITS_PRODUCT = re.compile(r"(?<=[A-Za-zµμ\d])\.(?=[A-Za-zµμ])")


def _pint_syntax(text: str) -> str:
    """A UDUNITS label (netCDF, CF conventions) in pint's syntax: "m s-2" -> "m s**-2"."""
    return _UDUNITS_POWER.sub(r"**\1", _UDUNITS_PRODUCT.sub("*", text))


def _parse(text: str):
    """The pint unit of ``text`` (as written, else read as UDUNITS), or a ValueError saying why not."""
    import pint

    ureg = _registry()
    caught = (pint.errors.PintError, AttributeError, TypeError, ValueError, SyntaxError)
    text = _ALIASES.get(text.strip(), text.strip())
    try:
        quantity = ureg.Quantity(1.0, text)
    except caught as exc:
        rewritten = _pint_syntax(text)
        if rewritten == text:
            raise ValueError(str(exc) or type(exc).__name__) from None
        try:
            quantity = ureg.Quantity(1.0, rewritten)
        except caught:
            raise ValueError(str(exc) or type(exc).__name__) from None
    if quantity.magnitude != 1.0:
        # "1e-3 m" or "2 N": a number inside the unit string
        raise ValueError("a unit must not hold a number")
    return quantity


def unit_scale(text: str, si: str) -> float:
    """SI per ``text``: the factor that turns numbers in ``text`` into numbers in ``si``.

    Raises ValueError when ``text`` does not parse or has another dimension.
    """
    quantity = _parse(text)
    target = _parse(si)
    if quantity.dimensionality != target.dimensionality:
        raise _WrongDimension(f"dimension {_dimension(quantity)}, not {_dimension(target)}")
    return float(quantity.to(target.units).magnitude)


def _dimension(quantity) -> str:
    dim = str(quantity.dimensionality)
    return "dimensionless" if dim in ("", "dimensionless") else dim


def _quantity_for(text: str) -> str | None:
    """The sensor quantity whose SI unit has the dimension of ``text`` (None if none does)."""
    q = _parse(text)
    for name, si in SI_UNITS.items():
        if q.dimensionality == _parse(si).dimensionality:
            return name
    return None


def resolve_unit(
    quantity: str | None, sensor_unit: str | None, file_unit: str | None, *, who: str, where: str
) -> ChannelUnit:
    """The unit of one channel and its factor to SI.

    ``quantity``: the sensor's (``"displacement"``, ``"velocity"``,
    ``"acceleration"``, ``"force"``, ``"strain"``), or None when it is not
    known (then it is read off the unit's dimension). ``sensor_unit``
    overrides ``file_unit``; with neither, SI is assumed. ``who`` names the
    sensor and ``where`` the file in messages.
    """
    if sensor_unit is not None and not sensor_unit.strip():
        raise LatentForceError(f'{who}: unit is empty; give a unit such as "m/s^2", or leave the key out.')
    given, source = (sensor_unit, "sensor") if sensor_unit is not None else (file_unit, "file")
    if given is None or (source == "file" and given.strip().lower() in NO_UNIT):
        if quantity is None:
            return ChannelUnit(unit="", si="", scale=1.0, source="assumed")
        si = SI_UNITS[quantity]
        return ChannelUnit(unit=si, si=si, scale=1.0, source="assumed")
    given = given.strip()
    origin = "its unit key" if source == "sensor" else f"the unit label {given!r} in {where}"
    if given.lower() in _UNNAMED:
        raise LatentForceError(
            f"{who}: unit {given!r} (from {origin}) means engineering units, which does not say which unit; "
            'give the channel\'s unit in the sensor\'s unit key (e.g. "g", "m/s^2", "mm", "N").'
        )
    try:
        if quantity is None:
            quantity = _quantity_for(given)
            if quantity is None:
                raise _WrongDimension(
                    f"dimension {_dimension(_parse(given))}, which is none of "
                    f"{', '.join(f'{k} ({v})' for k, v in SI_UNITS.items())}"
                )
        si = SI_UNITS[quantity]
        scale = unit_scale(given, si)
    except ValueError as exc:
        hint = (
            ""
            if source == "sensor"
            else " Give the channel's unit in the sensor's unit key to override the file's label."
        )
        if isinstance(exc, _WrongDimension):
            if quantity is None:
                need = f"any sensor quantity: it has {exc}"
            else:
                article = "an" if quantity[0] in "aeiou" else "a"
                need = (
                    f"quantity {quantity!r}: it has {exc}; {article} {quantity} channel needs a unit like "
                    f"{SI_UNITS[quantity]!r}"
                )
                # units are case-sensitive ('G' is the gravitational constant, 'g' standard gravity)
                for other in dict.fromkeys((given.lower(), given.upper())):
                    if other != given:
                        try:
                            unit_scale(other, SI_UNITS[quantity])
                        except ValueError:
                            continue
                        need += f" (units are case-sensitive: did you mean {other!r}?)"
                        break
            raise LatentForceError(f"{who}: unit {given!r} (from {origin}) does not fit {need}.{hint}") from None
        raise LatentForceError(
            f"{who}: unit {given!r} (from {origin}) is not a unit the units library (pint) knows "
            f'({exc}); write it like "m/s^2", "g", "mm", "um", "in/s", "N", "kN" or '
            f'"ustrain".{hint}'
        ) from None
    label = None
    if source == "sensor" and file_unit is not None and file_unit.strip().lower() not in NO_UNIT:
        try:
            other = unit_scale(file_unit.strip(), si)
        except ValueError:  # a label that does not parse or fit: the override is its documented fix
            other = scale
        label = None if math.isclose(other, scale, rel_tol=1e-9) else file_unit.strip()
    return ChannelUnit(unit=given, si=si, scale=scale, source=source, file_label=label)


def override_warning(units: dict[str, ChannelUnit] | None) -> str | None:
    """A warning naming the channels whose sensor ``unit`` key overrode a file label that reads as a
    different unit of the same quantity (``"m/s^2"`` over a file's ``"g"``): one of the two is wrong,
    and the data were taken in the key's unit. None where there is none."""
    clashes = [(c, u) for c, u in (units or {}).items() if u.file_label is not None]
    if not clashes:
        return None
    listing = "; ".join(
        f"column {c!r}: unit {u.unit!r} from its sensor's unit key, {u.file_label!r} in the file's label "
        f"(a factor {unit_scale(u.file_label, u.si) / u.scale:.4g} apart)"
        for c, u in clashes
    )
    return (
        f"the config's unit overrides the data file's own unit label ({listing}). The data were read in "
        "the config's unit; if the file's label is right, remove the sensor's unit key."
    )
