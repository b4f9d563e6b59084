"""JSON Schemas in the form viewers of MCAP files and Foxglove servers parse.

Lichtblick (and Foxglove Studio, which it forked) turn a ``jsonschema`` schema into message
definitions before showing a ``json`` channel: every property must carry a ``type``
(``object`` / ``array`` / ``string`` / ``number`` / ``integer`` / ``boolean``; an array's
``items`` too, never another array); ``$ref``, ``anyOf`` and ``type: null`` are not read and a
``oneOf`` is only taken as an enumeration of numbers. A property the parser cannot read makes
it drop the whole channel (packages/mcap-support/src/parseJsonSchema.ts).

:func:`flat_schema` rewrites pydantic's schemas into that form, keeping what they say: a
``$ref`` is replaced by its definition; an optional value (``anyOf [T, null]``) becomes T (a
``null`` in a message is shown as empty); alternatives of objects (a ``oneOf`` of model kinds)
become one object with every alternative's properties; numbers of either kind become
``number``; an ``enum`` or ``const`` without a type gets the type of its values. What cannot be
said so (an array of arrays, incompatible alternatives) raises :class:`Inexpressible`, and the
channel is written without a schema (schemaless JSON, which the viewers show untyped).
"""

from __future__ import annotations

from typing import Any

Json = dict[str, Any]
_SCALARS = ("string", "number", "integer", "boolean")
_KEEP = ("description", "title", "minimum", "maximum", "exclusiveMinimum", "enum", "const",
         "contentEncoding")


class Inexpressible(ValueError):
    """A schema the viewers' parser cannot be given without losing its meaning."""


def flat_schema(schema: Json) -> Json:
    """``schema`` (an object's, with ``$defs``) in the viewers' form (module docstring)."""
    defs: Json = schema.get("$defs", {})

    def resolve(node: Json) -> Json:
        while "$ref" in node:
            target = defs[node["$ref"].rsplit("/", 1)[-1]]
            node = {**target, **{k: v for k, v in node.items() if k != "$ref"}}
        return node

    def typed(node: Json, where: str) -> str:
        t = node.get("type")
        if isinstance(t, list):
            t = [x for x in t if x != "null"]
            t = t[0] if len(t) == 1 else None
        if t is None:
            values = node.get("enum", [node["const"]] if "const" in node else [])
            kinds = {"string" if isinstance(v, str) else "boolean" if isinstance(v, bool)
                     else "integer" if isinstance(v, int) else "number" for v in values}
            if len(kinds) != 1:
                raise Inexpressible(f"{where}: no type")
            t = kinds.pop()
        return str(t)

    def merge(alts: list[Json], where: str) -> Json:
        if len(alts) == 1:
            return alts[0]
        kinds = {a["type"] for a in alts}
        if kinds == {"object"}:
            props: Json = {}
            for a in alts:
                for name, p in a.get("properties", {}).items():
                    props[name] = merge([props[name], p], f"{where}.{name}") if name in props else p
            return {"type": "object", "properties": props}
        if kinds <= {"integer", "number"}:
            return {"type": "number"}
        if len(kinds) == 1 and kinds != {"array"}:
            return {"type": kinds.pop()}
        if all(a == alts[0] for a in alts):
            return alts[0]
        raise Inexpressible(f"{where}: alternatives of kinds {sorted(kinds)}")

    def conv(node: Json, where: str) -> Json:
        node = resolve(node)
        alts = node.get("anyOf") or node.get("oneOf")
        if alts is not None:
            alts = [conv(a, where) for a in alts if resolve(a).get("type") != "null"]
            one = merge(alts, where)
            return {**one, **{k: node[k] for k in ("description", "title") if k in node}}
        t = typed(node, where)
        out: Json = {"type": t, **{k: node[k] for k in _KEEP if k in node}}
        if t == "object":
            out["properties"] = {name: conv(p, f"{where}.{name}")
                                 for name, p in node.get("properties", {}).items()}
        elif t == "array":
            items = node.get("items")
            if not isinstance(items, dict):
                raise Inexpressible(f"{where}: array items without a schema")
            out["items"] = conv(items, f"{where}[]")
            if out["items"]["type"] == "array":
                raise Inexpressible(f"{where}: an array of arrays")
        elif t not in _SCALARS:
            raise Inexpressible(f"{where}: type {t!r}")
        return out

    out = conv(schema, schema.get("title", "root"))
    if out["type"] != "object":
        raise Inexpressible("the message is not an object")
    return out


def schema_of_value(value: Any, where: str = "root") -> Json:
    """A schema in the viewers' form that types ``value`` (a JSON-able message: dicts, lists
    of one kind, numbers, strings, booleans): for messages built by a tool, not a model."""
    if isinstance(value, bool):
        return {"type": "boolean"}
    if isinstance(value, int):
        return {"type": "integer"}
    if isinstance(value, float):
        return {"type": "number"}
    if isinstance(value, str):
        return {"type": "string"}
    if isinstance(value, dict):
        return {"type": "object", "properties": {k: schema_of_value(v, f"{where}.{k}")
                                                 for k, v in value.items() if v is not None}}
    if isinstance(value, list) and value:
        items = [schema_of_value(v, f"{where}[]") for v in value]
        kinds = {i["type"] for i in items}
        if kinds <= {"integer", "number"}:
            return {"type": "array", "items": {"type": "number" if "number" in kinds else "integer"}}
        if len(kinds) == 1 and kinds != {"array"}:
            return {"type": "array", "items": items[0]}
    if isinstance(value, list):
        return {"type": "array", "items": {"type": "number"}}
    raise Inexpressible(f"{where}: {type(value).__name__}")
