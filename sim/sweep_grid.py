"""The parameter grid of ``apf-sim sweep``: which planner parameters exist and how ``NAME=VALUES`` is read.

The sweepable parameters are the fields of the planner's parameter dataclass (today ``PlannerParams``), read
from the dataclass itself, so a field a planner adds (a margin, a gain) can be swept without touching this
module. A name is a field name (``mu_o_per_m2``), the field name without its unit suffix (``mu_o`` ->
``mu_o_per_m2``, ``rho_l`` -> ``rho_l_m``, ``step`` -> ``step_m``, ``margin`` -> ``margin_m``) or the paper's
symbol where it differs (``N_b`` -> ``n_bacteria``).
"""

from __future__ import annotations

import dataclasses
import enum
import itertools
import math
import typing
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from apf_companion.errors import ConfigError

PAPER_SYMBOLS: Mapping[str, str] = {"N_b": "n_bacteria"}
"""The paper's symbols that are not a field name or its prefix (Table I)."""

UNIT_SUFFIXES = ("m", "per_m2", "s", "m_s", "deg", "rad", "hz")
"""Unit suffixes of field names (GUIDE: units in names) that a sweep name may leave out."""

ParamValue = float | int | bool | enum.Enum


@dataclass(frozen=True, slots=True)
class SweepParam:
    """One swept parameter: a field of the params dataclass and its values, in the order given."""

    field: str
    values: tuple[ParamValue, ...]


def sweepable_fields(params: Any) -> dict[str, type]:
    """Field name -> type of every float, int, bool or enum field of a params dataclass instance or class."""
    cls = params if isinstance(params, type) else type(params)
    if not dataclasses.is_dataclass(cls):
        msg = f"sweep: {cls.__name__} is not a dataclass"
        raise TypeError(msg)
    hints = typing.get_type_hints(cls)
    out: dict[str, type] = {}
    for f in dataclasses.fields(cls):
        kind = hints.get(f.name)
        if isinstance(kind, type) and (kind in (float, int, bool) or issubclass(kind, enum.Enum)):
            out[f.name] = kind
    return out


def resolve_name(name: str, fields: Mapping[str, type]) -> str:
    """The field ``name`` means (see the module docstring); ``ConfigError`` if none or several."""
    name = name.strip()
    if name in fields:
        return name
    if name in PAPER_SYMBOLS and PAPER_SYMBOLS[name] in fields:
        return PAPER_SYMBOLS[name]
    matches = [f for f in fields if any(f == f"{name}_{unit}" for unit in UNIT_SUFFIXES)]
    if len(matches) == 1:
        return matches[0]
    known = ", ".join(fields)
    if matches:
        msg = f"sweep: parameter {name!r} is ambiguous ({', '.join(matches)}); use the full name"
    else:
        msg = f"sweep: unknown parameter {name!r}; sweepable: {known} (and N_b)"
    raise ConfigError(msg)


def _number(text: str, kind: type) -> ParamValue:
    if kind is bool:
        low = text.lower()
        if low in ("true", "1", "yes", "on"):
            return True
        if low in ("false", "0", "no", "off"):
            return False
        raise ValueError(text)
    if issubclass(kind, enum.Enum):
        return kind(text)
    if kind is int:
        return int(text)
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(text)
    return value


def _linspace(text: str, kind: type) -> tuple[ParamValue, ...]:
    low_text, high_text, n_text = text.split(":")
    low, high, n = float(low_text), float(high_text), int(n_text)
    if n < 2 or not (math.isfinite(low) and math.isfinite(high)):
        raise ValueError(text)
    values = [low + (high - low) * k / (n - 1) for k in range(n)]
    if kind is int:
        return tuple(dict.fromkeys(round(v) for v in values))
    if kind is not float:
        raise ValueError(text)
    return tuple(values)


def parse_param(spec: str, fields: Mapping[str, type]) -> SweepParam:
    """``NAME=V1,V2,...`` or ``NAME=LOW:HIGH:N`` (N evenly spaced values, ends included)."""
    name, sep, values_text = spec.partition("=")
    if not sep or not values_text.strip():
        msg = f"sweep: --param expects NAME=V1,V2,... or NAME=LOW:HIGH:N, got {spec!r}"
        raise ConfigError(msg)
    field = resolve_name(name, fields)
    kind = fields[field]
    try:
        if ":" in values_text:
            values = _linspace(values_text, kind)
        else:
            values = tuple(_number(v.strip(), kind) for v in values_text.split(",") if v.strip())
    except ValueError as err:
        msg = f"sweep: --param {spec!r}: values of {field} must be {kind.__name__}"
        if issubclass(kind, enum.Enum):
            msg += f" ({', '.join(str(m.value) for m in kind)})"
        raise ConfigError(msg) from err
    if not values or len(set(values)) != len(values):
        msg = f"sweep: --param {spec!r}: need distinct values"
        raise ConfigError(msg)
    return SweepParam(field=field, values=values)


def parse_params(specs: Sequence[str], params: Any) -> tuple[SweepParam, ...]:
    """Every ``--param``; a field may appear once. All errors are reported together."""
    fields = sweepable_fields(params)
    out: list[SweepParam] = []
    errors: list[str] = []
    for spec in specs:
        try:
            p = parse_param(spec, fields)
        except ConfigError as err:
            errors.append(str(err))
            continue
        if any(q.field == p.field for q in out):
            errors.append(f"sweep: {p.field} given twice")
        out.append(p)
    if errors:
        raise ConfigError("; ".join(errors))
    return tuple(out)


def grid_points(swept: Sequence[SweepParam]) -> list[dict[str, ParamValue]]:
    """The Cartesian product, the first parameter varying slowest."""
    names = [p.field for p in swept]
    return [dict(zip(names, combo, strict=True)) for combo in itertools.product(*(p.values for p in swept))]


def point_label(point: Mapping[str, ParamValue]) -> str:
    """``mu_o_per_m2=500 rho_l_m=0.4`` (enums by value)."""
    return " ".join(f"{k}={format_value(v)}" for k, v in point.items())


def format_value(value: ParamValue) -> str:
    if isinstance(value, enum.Enum):
        return str(value.value)
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)
