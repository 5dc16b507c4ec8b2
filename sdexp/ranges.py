"""What a value may be, declared once beside it, and the one checker that reads the declarations.

A dataclass field declares its range in its metadata (``field(default=..., metadata=ranged(...))``,
or the shorthands below); :func:`check_fields` walks a dataclass (an instance or the OmegaConf
node of one) and raises a :class:`~sdexp.errors.UserError` naming the first key outside its
range: ``<key> = <value> is out of range: allowed <allowed>``. A list's or mapping's every
number is checked (the message then says "each"); a number that is not finite never passes; None
passes (an optional field left unset). The config schema (sdexp.config), the experiments' params
(sdexp.experiment_params) and the effects' parameters (sdexp.sim.physics.effects) declare their
ranges this way; what depends on two keys at once (a substep within the control step, a list as
long as the drone's dimension) stays a check of its own beside the schema.
"""
from __future__ import annotations

import copy
import dataclasses
import math
import typing
from dataclasses import dataclass, field
from typing import Any, Callable

from sdexp.errors import UserError


@dataclass(frozen=True)
class Range:
    ok: Callable[[Any], bool]   # the test of one number (of one item, for ``choices``)
    allowed: str                # what the message says is allowed
    numbers: bool = True        # False: the values are names (``choices``), not numbers

    def check(self, key: str, value: Any) -> None:
        if value is None:
            return
        items = _leaves(value)
        good = all(self.ok(v) for v in items) if not self.numbers else all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and self.ok(v)
            for v in items)
        if not good:
            each = " each" if _is_container(value) else ""
            raise UserError(f"{key} = {_plain(value)!r} is out of range: allowed {self.allowed}{each}")


def ranged(ok: Callable[[Any], bool], allowed: str, **metadata) -> dict:
    """A field's metadata with its range (``metadata``: the field's other entries, e.g. cache-key
    flags)."""
    return {**metadata, "range": Range(ok, allowed)}


def _with_unit(text: str, unit: str) -> str:
    return f"{text} {unit}" if unit else text


def positive(unit: str = "", **metadata) -> dict:
    return ranged(lambda v: v > 0, _with_unit("> 0", unit), **metadata)


def nonnegative(unit: str = "", **metadata) -> dict:
    return ranged(lambda v: v >= 0, _with_unit(">= 0", unit), **metadata)


def at_least(low: float, unit: str = "", **metadata) -> dict:
    return ranged(lambda v: v >= low, _with_unit(f">= {low:g}", unit), **metadata)


def between(low: float, high: float, closed: str = "[]", unit: str = "", **metadata) -> dict:
    """low..high, each end closed ("[" / "]") or open ("(" / ")")."""
    lo_ok = (lambda v: v >= low) if closed[0] == "[" else (lambda v: v > low)
    hi_ok = (lambda v: v <= high) if closed[1] == "]" else (lambda v: v < high)
    return ranged(lambda v: lo_ok(v) and hi_ok(v), _with_unit(f"in {closed[0]}{low:g}, {high:g}{closed[1]}", unit),
                  **metadata)


def choices(values, **metadata) -> dict:
    """One of ``values`` (each item, for a list of names)."""
    values = tuple(values)
    names = ["null" if v is None else str(v) for v in values]   # as the user writes it on the command line
    text = " or ".join(names) if len(names) <= 2 else ", ".join(names[:-1]) + f" or {names[-1]}"
    return {**metadata, "range": Range(lambda v: v in values, text, numbers=False)}


def param(default, meta: dict | None = None) -> Any:
    """A dataclass field with ``default`` (a list, mapping or dataclass is copied per instance)
    and ``meta`` (ranged(...), positive(...), ...)."""
    meta = meta or {}
    if isinstance(default, (list, dict)) or dataclasses.is_dataclass(default):
        return field(default_factory=lambda: copy.deepcopy(default), metadata=meta)
    return field(default=default, metadata=meta)


def _is_container(value) -> bool:
    return hasattr(value, "items") or (hasattr(value, "__len__") and hasattr(value, "__getitem__")
                                       and not isinstance(value, str))


def _plain(value):
    """A config container (an OmegaConf list or mapping) as the plain list or dict a user wrote."""
    if hasattr(value, "items") and not isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if _is_container(value) and not isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def _leaves(value) -> list:
    """The values of a field: itself, a list's items, or (a mapping of lists: per element type
    or dimension) all of theirs."""
    if hasattr(value, "items") and not isinstance(value, str):
        return [v for sub in value.values() for v in _leaves(sub)]
    if _is_container(value):
        return [v for item in value for v in _leaves(item)]
    return [value]


def check_fields(node, cls, prefix: str = "") -> None:
    """Every field of dataclass ``cls`` that declares a range, in ``node`` (an instance of it or
    the OmegaConf node of one), and the fields of the dataclasses nested in it."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        value = getattr(node, f.name)   # no missing (???) value here: validate's check_complete came first
        rng = f.metadata.get("range")
        if rng is not None:
            rng.check(f"{prefix}{f.name}", value)
        if dataclasses.is_dataclass(hints[f.name]) and value is not None:
            check_fields(value, hints[f.name], f"{prefix}{f.name}.")
