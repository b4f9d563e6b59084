"""Tally: counts by name, a dict whose missing keys read as 0.

``collections.Counter`` does the same, but it defines ``__delitem__`` in Python, and a class
that defines one of the item-assignment methods gets CPython's generic slot for all item
assignment: every ``counter[k] += 1`` then looks ``__setitem__`` up on the type and calls it
through a wrapper, several times a dict's own assignment; the daemon counts several
outcomes per message (the estimator's, the session's and the service's counters), so this
shows in its worker (docs/performance.md).

A Tally inherits every dict slot unchanged and adds only ``__missing__``: ``t[k]`` of a key
never counted is 0 and inserts nothing, ``t[k] += 1`` starts from 0, as with Counter. It has
none of Counter's arithmetic, and ``update`` replaces values (a dict's), where Counter's adds.
Not compiled (mypyc's native classes cannot subclass dict): its instances are plain dicts to
the C code that uses them.
"""

from __future__ import annotations


class Tally(dict[str, int]):
    """Counts by name (see the module docstring)."""

    __slots__ = ()

    def __missing__(self, key: str) -> int:
        return 0
