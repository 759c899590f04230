"""The case schema's building blocks: a key's type, default and bounds, and the error a
malformed case raises. The lowest layer of the case handling: the scenes declare their keys
with it, :mod:`torchsph.io.config` validates against them."""
from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any


class CaseError(ValueError):
    """A malformed case file or override (message: one line)."""


REQUIRED = object()  # the default of a key that has none


@dataclass(frozen=True)
class Key:
    kind: str  # float | int | bool | str | vec | strs (a list of strings)
    default: Any = REQUIRED
    gt: float | None = None  # value must be > gt
    ge: float | None = None  # value must be >= ge
    le: float | None = None  # value must be <= le
    lt: float | None = None
    choices: tuple | None = None
    doc: str = ""
    field: str | None = None  # the parameter it sets in the physics' parameter class (None: none)

    def allowed(self) -> str:
        if self.choices is not None:
            return "one of " + ", ".join(repr(c) for c in self.choices)
        parts = {"float": "a number", "int": "an integer", "bool": "true or false",
                 "str": "a string", "vec": "a list of numbers", "strs": "a list of strings"}[self.kind]
        bounds = []
        if self.gt is not None:
            bounds.append(f"> {self.gt:g}")
        if self.ge is not None:
            bounds.append(f">= {self.ge:g}")
        if self.lt is not None:
            bounds.append(f"< {self.lt:g}")
        if self.le is not None:
            bounds.append(f"<= {self.le:g}")
        return parts + (" " + " and ".join(bounds) if bounds else "")


def params(cls, section: dict, schema: dict[str, Key], **extra):
    """An instance of the parameter dataclass ``cls`` from a validated case section: each key
    whose ``field`` is one of ``cls``'s fields sets it (lists become tuples; a None value
    leaves the class's default), then ``extra`` (values from other sections)."""
    names = {f.name for f in fields(cls)}
    kw = {}
    for k, key in schema.items():
        if key.field in names and section.get(k) is not None:
            v = section[k]
            kw[key.field] = tuple(v) if isinstance(v, list) else v
    return cls(**kw, **extra)
