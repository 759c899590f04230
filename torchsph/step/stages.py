"""The composable terms as stages of the step, ordered by what they declare.

A term's ``reads`` names fields: the state's (``"x"``, ``"T"``, ...), an array of the
registry (:mod:`torchsph.step.particles`, e.g. ``"sf.kappa"``, ``"dTdt"``), or a field another
term makes (a name in its ``writes`` that is not a rate, held as one of its arrays). The terms
that make fields are evaluated every step, once the step's pairs are selected and before the
rates, in an order where every field is made before a term that reads it; a term that reads a
field nothing in the case writes, two terms that make the same field, or a cycle, is refused
at set-up in one line (:class:`~torchsph.core.schema.CaseError`)."""
from __future__ import annotations

from torchsph.core.schema import CaseError
from torchsph.core.state import FIELDS


def order_terms(terms: list, provided: set[str], registered: dict | None = None) -> list:
    """The terms that make fields, in the order the step evaluates them. ``provided``: the
    fields the case has without the terms (the registry's names of the built physics);
    ``registered``: every term class by section, to name the one that would make a missing field."""
    writers = {}
    for t in terms:
        for f in t.fields:
            if f in writers:
                raise CaseError(f"[{t.section}] and [{writers[f].section}] both write the field {f!r}")
            writers[f] = t
    have = set(FIELDS) | set(provided)
    for t in terms:
        for r in t.reads:
            if r in have or r in writers:
                continue
            makers = sorted(c.section for c in (registered or {}).values() if r in getattr(c, "writes", ()))
            hint = f"; [{makers[0]}] writes it: name that section" if makers else ""
            raise CaseError(f"[{t.section}] reads {r!r}, which nothing in this case writes{hint}")
    order, done, visiting = [], set(), set()

    def visit(t):
        if t.section in done:
            return
        if t.section in visiting:
            raise CaseError(f"[{t.section}] is in a cycle of fields: each term reads what another makes")
        visiting.add(t.section)
        for r in t.reads:
            if r in writers and writers[r] is not t:
                visit(writers[r])
        visiting.discard(t.section)
        done.add(t.section)
        if t.fields:
            order.append(t)
    for t in terms:
        visit(t)
    return order


class Fields:
    """The terms' fields, by name (``sim.fields["grad_T"]``: what a term reads of another's
    without naming it), and the field-making terms in their evaluation order (``order``)."""

    def __init__(self, terms: list, provided: set[str], registered: dict | None = None):
        self.order = order_terms(terms, provided, registered)
        self.writer = {f: t for t in self.order for f in t.fields}

    def __getitem__(self, name: str):
        return getattr(self.writer[name], name)


def evaluate_fields(sim) -> None:
    """Every field-making term's ``evaluate``, in order (the step, once its pairs are selected)."""
    for t in sim.fields.order:
        t.evaluate(sim)
