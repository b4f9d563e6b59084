"""Zenoh key expressions: validation and matching, without Zenoh.

Rules (Zenoh 1.x): chunks are separated by ``/``; ``*`` matches exactly one chunk, ``**``
matches zero or more chunks, ``$*`` inside a chunk matches any (possibly empty) run of
characters, other chunks match literally; a chunk starting with ``@`` (verbatim) is matched only
by the same literal chunk, never by a wildcard. A concrete key is a key expression without
wildcards, so :func:`intersects` also answers "does this pattern match this key".
"""

from __future__ import annotations

from functools import lru_cache


def check_keyexpr(expr: object) -> str:
    """``expr`` if it is a well-formed key expression, else ValueError saying why."""
    if not isinstance(expr, str) or not expr:
        raise ValueError(f"expected a key expression, got {expr!r}")
    for c in expr.split("/"):
        if c == "":
            raise ValueError(f"{expr!r} has an empty chunk (leading, trailing or '//')")
        if c in ("*", "**"):
            continue
        if "**" in c:
            raise ValueError(f"{expr!r}: '**' must be a whole chunk")
        if "*" in c.replace("$*", ""):
            raise ValueError(f"{expr!r}: '*' must be a whole chunk (or '$*' inside one)")
        if any(ch in c for ch in "?#[]"):
            raise ValueError(f"{expr!r}: characters ?, #, [ and ] are not allowed")
    return expr


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
    return _chunks_intersect(a[0], b[0]) and _match(a[1:], b[1:])


def _chunks_intersect(x: str, y: str) -> bool:
    if x == y:
        return True
    if x.startswith("@") or y.startswith("@"):
        return False
    if x == "*" or y == "*":
        return True
    if "$*" not in x and "$*" not in y:
        return False
    return _globs_intersect(_tokens(x), _tokens(y))


def _tokens(chunk: str) -> tuple[str, ...]:
    """A chunk as single characters, with each ``$*`` as one ``""`` token (the wildcard)."""
    out: list[str] = []
    for i, part in enumerate(chunk.split("$*")):
        if i:
            out.append("")
        out.extend(part)
    return tuple(out)


def _globs_intersect(a: tuple[str, ...], b: tuple[str, ...]) -> bool:
    """Do two globs (``""`` = any run of characters) match a common string?  Each wildcard
    either ends here or swallows the other side's next token."""
    if not a or not b:
        return all(t == "" for t in a + b)
    if a[0] == "":
        return _globs_intersect(a[1:], b) or _globs_intersect(a, b[1:])
    if b[0] == "":
        return _globs_intersect(b, a)
    return a[0] == b[0] and _globs_intersect(a[1:], b[1:])
