"""The config of an environment: the same Hydra configs as ``sdexp experiment=...`` (composed from
sdexp.conf, validated, converted to dataclasses once), with keyword overrides."""
from __future__ import annotations

from typing import Mapping, Sequence

from sdexp.errors import UserError


def override_list(drone: str, overrides: Sequence[str] | Mapping[str, object] | None) -> list[str]:
    """Hydra override strings: ``drone=<drone>`` and the caller's, given as strings
    (``["noise.enabled=false"]``) or as a mapping (``{"noise.enabled": False}``)."""
    if overrides is None:
        extra = []
    elif isinstance(overrides, Mapping):
        extra = [f"{k}={_value(v)}" for k, v in overrides.items()]
    elif isinstance(overrides, str):
        raise UserError(f"overrides = {overrides!r}: allowed a list of Hydra overrides or a mapping key -> value")
    else:
        extra = [str(o) for o in overrides]
    return [f"drone={drone}", *extra]


def _value(v) -> str:
    """A Python value as Hydra's override grammar reads it (booleans lower case, lists bracketed)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if v is None:
        return "null"
    if isinstance(v, (list, tuple)):
        return "[" + ",".join(_value(x) for x in v) + "]"
    return str(v)


def compose_config(drone: str, overrides=None):
    """The typed config (sdexp.config.Config) of ``drone`` with ``overrides``; bad input is a
    UserError naming the override or key (Hydra's own messages, on one line)."""
    from sdexp import conf
    from sdexp.config import validate
    from sdexp.eval.run import compose_overrides, simulator_checks, typed

    names = conf.names("drone")
    if drone not in names:
        raise UserError(f"drone = {drone!r} is unknown: choose one of {', '.join(names)}")
    args = override_list(drone, overrides)
    cfg = compose_overrides(args, f"overrides {args[1:]}")
    validate(cfg)
    simulator_checks(cfg)
    return typed(cfg)
