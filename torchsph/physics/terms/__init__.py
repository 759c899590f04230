"""Composable physics terms (:mod:`torchsph.physics.terms.base` holds the protocol).

Every module of this package is imported by :func:`available`, and each term it registers
becomes a case section: adding a term is adding a module here, with its test."""
from __future__ import annotations

import importlib
import pkgutil

from torchsph.physics.terms.base import TERMS, Term, TermContext, owned_sum, register

__all__ = ["TERMS", "Term", "TermContext", "available", "owned_sum", "register"]


def available() -> dict[str, type[Term]]:
    """Every registered term by section (the package's modules imported once)."""
    for m in pkgutil.iter_modules(__path__):
        if m.name != "base":
            importlib.import_module(f"{__name__}.{m.name}")
    return TERMS
