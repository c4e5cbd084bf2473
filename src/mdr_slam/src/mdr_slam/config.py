"""Typed configuration: one dataclass per component, with its defaults in one place.

A component's parameter file (``config/<node>.yaml``), the ROS private parameters and
``mdr run --set`` only override fields of these classes; a key that no field names is refused
with :class:`ConfigError` (a typo would otherwise be ignored in silence), and a value of the
wrong type is refused too (``n_features: "1500"``) or converted where nothing is lost
(``tau: 1`` to 1.0, ``stride: 2.0`` to 2).

    @dataclass
    class FooConfig(Config):
        radius: float = 0.5        # m, what the radius does (0: off)

    cfg = FooConfig.from_dict({"radius": 1})      # FooConfig(radius=1.0)
    cfg.to_dict()                                   # {"radius": 1.0}
"""
from __future__ import annotations

import dataclasses
import typing
from typing import Any, Dict, Iterable, Mapping, Optional

__all__ = ["Config", "ConfigError", "split_known"]


class ConfigError(ValueError):
    """A parameter no component knows, or a value of the wrong type."""


def _coerce(owner: str, name: str, value, typ):
    if typ is Any:
        return value
    if isinstance(typ, type) and issubclass(typ, Config):
        if isinstance(value, typ):
            return value
        if isinstance(value, Mapping):
            return typ.from_dict(value)
        raise ConfigError("%s.%s wants a mapping of %s parameters, got %r"
                          % (owner, name, typ.__name__, value))
    if typ is bool:
        if isinstance(value, bool):
            return value
    elif typ is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
    elif typ is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
    elif typ is str:
        if isinstance(value, str):
            return value
    elif typ is dict or typing.get_origin(typ) is dict:
        if isinstance(value, Mapping):
            return dict(value)
    else:
        raise ConfigError("%s.%s: a field's type is bool, int, float, str, dict, Any or a Config "
                          "(got %r)" % (owner, name, typ))
    raise ConfigError("%s.%s wants %s, got %r" % (owner, name, getattr(typ, "__name__", typ), value))


@dataclasses.dataclass
class Config:
    """Base of the components' configurations (a dataclass whose fields are the parameters)."""

    def __post_init__(self):
        hints = self._hints()
        for f in dataclasses.fields(self):
            setattr(self, f.name, _coerce(type(self).__name__, f.name, getattr(self, f.name),
                                          hints[f.name]))

    @classmethod
    def _hints(cls) -> Dict[str, Any]:
        cached = cls.__dict__.get("_hints_cache")
        if cached is None:
            cached = typing.get_type_hints(cls)
            setattr(cls, "_hints_cache", cached)
        return cached

    @classmethod
    def keys(cls) -> tuple:
        """The parameter names, in declaration order."""
        return tuple(f.name for f in dataclasses.fields(cls))

    @classmethod
    def from_dict(cls, values: Optional[Mapping] = None, ignore: Iterable[str] = ()):
        """The defaults overridden by ``values``; keys in ``ignore`` (another component's) are
        skipped, any other unknown key raises :class:`ConfigError`."""
        values = dict(values or {})
        known = set(cls.keys())
        unknown = sorted(set(values) - known - set(ignore))
        if unknown:
            raise ConfigError("%s has no parameter %s (known: %s)" % (
                cls.__name__, ", ".join(repr(k) for k in unknown), ", ".join(sorted(known))))
        return cls(**{k: v for k, v in values.items() if k in known})

    @classmethod
    def pick(cls, values: Optional[Mapping] = None):
        """From the keys of ``values`` that are fields of this class, the others left out: a
        node's parameter file holds several components' keys, each class takes its own."""
        known = set(cls.keys())
        return cls.from_dict({k: v for k, v in (values or {}).items() if k in known})

    @classmethod
    def of(cls, value=None):
        """``value`` itself when it is an instance, else :meth:`from_dict` of it (a Mapping or
        None): what a component's constructor calls on the configuration it is given."""
        if isinstance(value, cls):
            return value
        if value is not None and not isinstance(value, Mapping):
            raise ConfigError("%s wants a %s or a mapping of its parameters, got %r"
                              % (cls.__name__, cls.__name__, value))
        return cls.from_dict(value)

    @classmethod
    def defaults(cls) -> dict:
        return cls().to_dict()

    def to_dict(self) -> dict:
        out = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            out[f.name] = v.to_dict() if isinstance(v, Config) else v
        return out

    def replace(self, **changes):
        """A copy with some parameters changed (checked like :meth:`from_dict`)."""
        merged = self.to_dict()
        for k, v in changes.items():
            if isinstance(merged.get(k), dict) and isinstance(v, Mapping):
                merged[k] = dict(merged[k], **v)
            else:
                merged[k] = v
        return type(self).from_dict(merged)


def split_known(values: Mapping, *configs) -> list:
    """``values`` divided among ``configs`` (Config classes) by their keys, one dict per class;
    a key none of them knows raises :class:`ConfigError`."""
    values = dict(values or {})
    known = set()
    for c in configs:
        known |= set(c.keys())
    unknown = sorted(set(values) - known)
    if unknown:
        raise ConfigError("unknown parameters %s (known: %s)" % (
            ", ".join(repr(k) for k in unknown), ", ".join(sorted(known))))
    return [{k: v for k, v in values.items() if k in c.keys()} for c in configs]
