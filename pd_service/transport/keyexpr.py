"""Zenoh key-expression matching for the in-memory transport.

Rules (Zenoh 1.x): ``*`` matches exactly one chunk, ``**`` matches zero or more chunks, other
chunks match literally; a chunk starting with ``@`` (verbatim) is matched only by the same
literal chunk, never by a wildcard.
"""

from __future__ import annotations

from functools import lru_cache


@lru_cache(maxsize=4096)
def intersects(a: str, b: str) -> bool:
    """True if key expressions ``a`` and ``b`` have at least one concrete key in common."""
    return _match(tuple(a.split("/")), tuple(b.split("/")))


def _match(a: tuple[str, ...], b: tuple[str, ...]) -> bool:
    if not a and not b:
        return True
    if a and a[0] == "**":
        if _match(a[1:], b):  # ** as zero chunks
            return True
        return bool(b) and not b[0].startswith("@") and _match(a, b[1:])
    if b and b[0] == "**":
        return _match(b, a)
    if not a or not b:
        return False
    x, y = a[0], b[0]
    if x == y or (x == "*" and not y.startswith("@")) or (y == "*" and not x.startswith("@")):
        return _match(a[1:], b[1:])
    return False
