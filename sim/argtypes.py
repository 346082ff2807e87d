"""argparse types for apf-sim's numeric flags: a bad value is argparse's usage error (exit 2) naming the flag and
the allowed range, before anything starts."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable

__all__ = ["int_from", "number_in", "param_assignment"]


def number_in(lo: float, hi: float, *, lo_open: bool = False, what: str = "") -> Callable[[str], float]:
    """An argparse type: a finite number in [lo, hi] (``(lo, hi]`` with ``lo_open``; hi may be inf: no upper
    bound); ``what`` is its unit and meaning."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) and (value > lo if lo_open else value >= lo) and value <= hi):
            unit = f" {what}" if what else ""
            close = ")" if math.isinf(hi) else "]"
            msg = f"must be a number in {'(' if lo_open else '['}{lo:g}, {hi:g}{close}{unit}, got {text!r}"
            raise argparse.ArgumentTypeError(msg)
        return value

    return parse


def int_from(lo: int, hi: int | None = None) -> Callable[[str], int]:
    """An argparse type: an integer >= lo (and <= hi, when given)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = lo - 1
        if value < lo or (hi is not None and value > hi):
            allowed = f">= {lo}" if hi is None else f"in [{lo}, {hi}]"
            msg = f"must be an integer {allowed}, got {text!r}"
            raise argparse.ArgumentTypeError(msg)
        return value

    return parse


def param_assignment(text: str) -> str:
    """An argparse type: an autopilot parameter override ``NAME=VALUE`` with a finite number, as ``NAME=VALUE`` with
    the name upper-cased (``apf-sim vehicle --param``, ``apf-sim fly --vehicle-param``; the name and its range are
    the vehicle's parameter table's to check)."""
    name, sep, value = text.partition("=")
    try:
        number = float(value)
    except ValueError:
        number = math.nan
    if not sep or not name.strip() or not math.isfinite(number):
        msg = f"must be NAME=VALUE with a finite number VALUE, got {text!r}"
        raise argparse.ArgumentTypeError(msg)
    return f"{name.strip().upper()}={value.strip()}"
