"""Parse people's quantities into SI values: ``'180cm'``, ``'1.8m'``, ``'80kg'``, ``'+5cm'``, ``'male'``,
ranges ``'155:185cm'``.

Every semantic variable has a *kind* (length, mass, ...) that fixes the accepted units; lengths
and masses must say their unit (``'180'`` is refused: centimetres or millimetres?), unitless
variables (muscle, sex as a number) take bare numbers. Errors name the field, what was found and
the accepted units.

>>> parse_target("stature", "180cm")
Target(name='stature', kind='value', value=1.8, lo=None, hi=None)
>>> parse_target("stature", "+5cm").kind
'delta'
>>> parse_target("stature", "155:185cm").hi
1.85
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from bodyspace.errors import UnitError

__all__ = ["UnitError", "Target", "UNITS", "KINDS", "ALIASES", "kind_of", "parse_quantity", "parse_target",
           "parse_assignment", "format_value", "example"]



# kind -> {unit: factor to SI}; the first unit is the one used for display.
UNITS: dict[str, dict[str, float]] = {
    "length": {"cm": 0.01, "m": 1.0, "mm": 0.001, "in": 0.0254, "ft": 0.3048},
    "mass": {"kg": 1.0, "g": 0.001, "lb": 0.45359237},
    "age": {"years": 1.0, "y": 1.0, "yr": 1.0, "": 1.0},
    "percent": {"%": 1.0, "": 1.0},
    "bmi": {"kg/m2": 1.0, "kg/m^2": 1.0, "": 1.0},
    "volume": {"l": 0.001, "m3": 1.0, "m^3": 1.0},
    "area": {"m2": 1.0, "m^2": 1.0, "cm2": 1e-4},
    "ratio": {"": 1.0},
}
# kind of every known semantic variable; measurement names not listed are inferred from their unit
KINDS: dict[str, str] = {
    "stature": "length", "height": "length", "mass": "mass", "bmi": "bmi", "age": "age", "body_fat": "percent",
    "muscle": "ratio", "sex": "sex", "volume": "volume", "surface_area": "area",
}
ALIASES = {"weight": "mass", "fat": "body_fat", "body_fat_percent": "body_fat", "age_years": "age",
           "gender": "sex", "muscularity": "muscle"}
SEX = {"male": 1.0, "m": 1.0, "man": 1.0, "female": 0.0, "f": 0.0, "woman": 0.0}
_NUM = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_QTY = re.compile(rf"^\s*({_NUM})\s*([a-zA-Z%/^0-9]*)\s*$")


def kind_of(name: str) -> str:
    """The kind of variable ``name`` ('length', 'mass', ...): KINDS, else from its suffix: every
    length of the measurement set ends in _girth, _length, _width, _height or _size (then
    optionally _l / _r), e.g. waist_size, thigh_girth_l, shoulder_width, arm_length_r."""
    name = ALIASES.get(name, name)
    if name in KINDS:
        return KINDS[name]
    base = name[:-2] if name.endswith(("_l", "_r")) else name  # left/right measurements: thigh_girth_l
    if base.endswith(("_girth", "_length", "_width", "_height", "_size")):
        return "length"
    return "ratio"


def parse_quantity(name: str, text: str, default_unit: str | None = None) -> float:
    """One value of variable ``name`` in SI units (metres, kilograms, years, % ...)."""
    kind = kind_of(name)
    raw = str(text).strip()
    if kind == "sex":
        low = raw.lower()
        if low in SEX:
            return SEX[low]
        try:
            v = float(low)
        except ValueError:
            v = None
        # a number is a degree between the two (the regressors' label): 0 female .. 1 male
        if v is None or not 0.0 <= v <= 1.0:
            raise UnitError(f"{name}: {text!r} is not a sex; expected male or female (or a number from 0 = female "
                            "to 1 = male)")
        return v
    m = _QTY.match(raw)
    units = UNITS[kind]
    accepted = ", ".join(u for u in units if u) or "a bare number"
    if not m:
        raise UnitError(f"{name}: {text!r} is not a number with a unit; expected e.g. "
                        f"{_example(kind)} (units: {accepted})")
    value, unit = float(m.group(1)), m.group(2).lower()
    if unit == "" and default_unit is not None:
        unit = default_unit
    if unit not in units:
        if unit == "":
            raise UnitError(f"{name}: {text!r} has no unit; expected one of {accepted} (e.g. {_example(kind)})")
        raise UnitError(f"{name}: unit {m.group(2)!r} in {text!r} is not a {kind} unit; expected one of {accepted}")
    return value * units[unit]


def example(name: str) -> str:
    """A valid value of variable ``name`` for messages: ``example('mass')`` is ``'80kg'``."""
    name, kind = ALIASES.get(name, name), kind_of(name)
    if kind == "length":
        return "180cm" if name in ("stature", "height") else "90cm"
    return "female" if kind == "sex" else _example(kind)


def _example(kind: str) -> str:
    return {"length": "180cm or 1.8m", "mass": "80kg", "age": "35", "percent": "25%", "bmi": "24",
            "volume": "70l", "area": "1.9m2"}.get(kind, "0.5")


@dataclass(frozen=True)
class Target:
    """A request on one variable, SI units: ``kind`` 'value' (``value``), 'delta' (``value`` is the
    change, from '+5cm'/'-2kg') or 'range' (``lo``..``hi``)."""

    name: str
    kind: str
    value: float | None = None
    lo: float | None = None
    hi: float | None = None


def parse_target(name: str, text: str) -> Target:
    """``'180cm'`` → value, ``'+5cm'`` / ``'-2kg'`` → delta, ``'155:185cm'`` or ``'1.55m:1.85m'`` → range."""
    name = ALIASES.get(name.strip(), name.strip())
    raw = str(text).strip()
    if not raw:
        raise UnitError(f"{name}: empty value; expected e.g. {_example(kind_of(name))}")
    if ":" in raw:
        a, _, b = raw.partition(":")
        mb = _QTY.match(b)
        unit_b = mb.group(2) if mb else None
        lo = parse_quantity(name, a, default_unit=unit_b.lower() if unit_b else None)
        hi = parse_quantity(name, b)
        if not lo < hi:
            raise UnitError(f"{name}: range {text!r} has low >= high; expected low:high, e.g. 155:185cm")
        return Target(name, "range", lo=lo, hi=hi)
    if raw[0] in "+-" and kind_of(name) != "sex":
        return Target(name, "delta", value=parse_quantity(name, raw))
    return Target(name, "value", value=parse_quantity(name, raw))


def parse_assignment(text: str) -> Target:
    """``'stature=180cm'`` → Target (for ``--set`` / ``--range`` options)."""
    name, sep, value = str(text).partition("=")
    if not sep or not name.strip():
        raise UnitError(f"{text!r}: expected NAME=VALUE, e.g. stature=180cm, mass=80kg, sex=female")
    return parse_target(name, value)


def format_value(name: str, value: float) -> str:
    """SI value for people: lengths in cm, masses in kg, sex as male/female when exact."""
    kind = kind_of(name)
    if kind == "sex":
        return "male" if value == 1 else "female" if value == 0 else f"{value:.2f} (1 = male)"
    if kind == "length":
        return f"{value * 100:.1f} cm"
    if kind == "mass":
        return f"{value:.2f} kg"
    unit = next(iter(UNITS[kind]))
    return f"{value:.3g}{(' ' + unit) if unit else ''}"
