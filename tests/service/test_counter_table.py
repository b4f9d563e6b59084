"""docs/protocol.md's counter table (section 8) names exactly the counters the daemon can emit.

The set is derived from the code, not listed here: every string the daemon's modules
(``pd_service/service/**``, ``pd_service/intake``, the replay estimator whose counters
join the session's) use as a key of a counters mapping
(``x.counters["name"]``, ``c["name"]`` for ``c`` bound to counters, the status' ``c``), every
refusal reason (``Refusal("name", ...)``, whose reason is its counter), every name in a
``counted=(...)`` or ``counted = (...)`` tuple, the intake's outcome tuples, and the keys
built at run time (f-strings, ``prefix + name``), which become patterns such as
``recovered_<reason>``. A key the scan cannot read (a plain variable) must be one of
:data:`RESOLVED`, with the names it can hold; a new one fails the test until it is listed.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

from pd_service.intake import COMMAND_OUTCOMES, MEASUREMENT_OUTCOMES

ROOT = Path(__file__).resolve().parents[2]
SOURCES = sorted((ROOT / "pd_service" / "service").rglob("*.py")) + \
    [ROOT / "pd_service" / "intake" / "__init__.py",
     ROOT / "pd_service" / "estimation" / "replay.py"]  # its counters join the session's

#: Counter keys held in a variable: (file, the key's source text) -> the names it can hold.
RESOLVED = {
    ("dispatch.py", "name"): {"accepted", "commands_accepted"},
    ("dispatch.py", "also + name"): {"recovered_accepted", "recovered_commands_accepted"},
    ("outbox.py", "name"): set(),  # iterates `counted`, whose tuples are scanned
    ("lifecycle.py", "counter"): {"legacy_keys", "wrong_partition"},  # _refuse_key's callers
    # the intake's decode and check reasons: its outcome tuples (added whole)
    ("__init__.py", "prefix + exc.kind"): set(),
    ("__init__.py", "_CHECK_REASONS.get(head, default)"): set(),
}

_COUNTERISH = re.compile(r"(^|\.)(c|counters|_counters)$")


def _key_names(node: ast.expr, where: str, found: set[str], unresolved: set[tuple[str, str]]
               ) -> None:
    """The counter name(s) of one key expression, into ``found`` (patterns for f-strings)."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        found.add(node.value)
    elif isinstance(node, ast.IfExp):
        _key_names(node.body, where, found, unresolved)
        _key_names(node.orelse, where, found, unresolved)
    elif isinstance(node, ast.JoinedStr):
        found.add("".join(v.value if isinstance(v, ast.Constant) else "<>" for v in node.values))
    else:
        unresolved.add((where, ast.unparse(node)))


def code_counters() -> set[str]:
    """Every counter name (or ``prefix_<>`` pattern) the daemon's code can emit."""
    found: set[str] = set(MEASUREMENT_OUTCOMES) | set(COMMAND_OUTCOMES)
    unresolved: set[tuple[str, str]] = set()
    for path in SOURCES:
        tree = ast.parse(path.read_text(encoding="utf-8"))
        where = path.name
        for node in ast.walk(tree):
            if isinstance(node, ast.Subscript) and _COUNTERISH.search(ast.unparse(node.value)):
                _key_names(node.slice, where, found, unresolved)
            elif isinstance(node, ast.Call):
                fn = ast.unparse(node.func)
                if fn == "Refusal" and node.args:
                    _key_names(node.args[0], where, found, unresolved)
                for kw in node.keywords:
                    if kw.arg == "counted" and isinstance(kw.value, ast.Tuple):
                        for e in kw.value.elts:
                            _key_names(e, where, found, unresolved)
                if fn.endswith("_refuse_key") and len(node.args) >= 3:
                    _key_names(node.args[2], where, found, unresolved)
            elif isinstance(node, ast.Assign) and isinstance(node.value, ast.Tuple) and any(
                    isinstance(t, ast.Name) and t.id == "counted" for t in node.targets):
                for e in node.value.elts:
                    if isinstance(e, ast.Constant):
                        found.add(e.value)
    for site in unresolved:
        assert site in RESOLVED, f"counter key {site[1]!r} in {site[0]}: list its names in RESOLVED"
        found |= RESOLVED[site]
    # "recovered" is a notice's reason, counted=() (never a counter), while the counters of
    # the same name (recoveries, pd_service.service.outbox) are scanned from their subscripts
    return found


def table_counters() -> set[str]:
    """The names in the first column of protocol.md's counter table (``a`` / ``b``, ``a, b``
    and ``prefix_<what>`` patterns, written ``prefix_<>`` here)."""
    text = (ROOT / "docs" / "protocol.md").read_text(encoding="utf-8")
    section = text.split("## 8. Counters", 1)[1].split("\n## ", 1)[0]
    names: set[str] = set()
    for line in section.splitlines():
        if not line.startswith("| `"):
            continue
        first = re.sub(r"\([^)]*\)", "", line.split("|")[1])  # "(e.g. ...)": examples
        for name in re.findall(r"`([^`]+)`", first):
            names.add(re.sub(r"<[a-z_ ]+>", "<>", name))
    return names


def test_the_counter_table_equals_the_counters_the_code_emits():
    code, table = code_counters(), table_counters()
    assert not code - table, f"counters missing from docs/protocol.md §8: {sorted(code - table)}"
    assert not table - code, f"table rows no code emits: {sorted(table - code)}"


def test_the_scan_finds_counters_of_each_kind():
    """The scan is not vacuous: a subscript, a refusal reason, a counted tuple, an f-string
    pattern and a resolved variable each contribute."""
    code = code_counters()
    assert {"tick_overruns", "config_rate_limited", "restore_refused", "recovered_<>",
            "resumed_from_<>", "recovered_commands_accepted", "out_of_range"} <= code
