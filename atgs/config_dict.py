"""Config dataclasses <-> plain nested dicts (checkpoints, config.json, --auto overrides)."""

from __future__ import annotations

import dataclasses
import typing


def to_dict(cfg) -> dict:
    """Plain nested dict of a config dataclass (tuples stay tuples; JSON writes them as lists)."""
    return dataclasses.asdict(cfg)


def from_dict(cls, d: dict):
    """Inverse of :func:`to_dict` for any config dataclass: nested dataclass fields are rebuilt
    from their dicts and tuple fields from lists; unknown keys are an error so that foreign or
    newer configs are caught."""
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    kwargs = {}
    for k, v in d.items():
        if k not in names:
            raise ValueError(f"unknown config field {cls.__name__}.{k}")
        hint = hints[k]
        if dataclasses.is_dataclass(hint) and isinstance(v, dict):
            v = from_dict(hint, v)
        elif typing.get_origin(hint) is tuple and v is not None:
            args = typing.get_args(hint)
            v = tuple(float(x) for x in v) if args and all(a is float for a in args) else tuple(v)
        kwargs[k] = v
    return cls(**kwargs)
