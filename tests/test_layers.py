"""The layering of docs/architecture.md, enforced: which package may import which, no import
cycles, and a light ``import pd_client``.

Every ``import`` statement of every module is read with :mod:`ast`, function-level (lazy)
imports included, so a lazy import cannot hide an upward edge or a cycle.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SOURCES = {"pd_service": ROOT / "pd_service", "pd_client": ROOT / "clients" / "python" / "pd_client"}

#: Layers from the bottom up. A module may import its own layer, the layers listed in
#: ``ALLOWED`` for it, and third-party/stdlib modules (restricted further by ``THIRD_PARTY``).
ALLOWED: dict[str, set[str]] = {
    # native (stdlib only) tells whether the C kernel of the linear backend is in use
    "pd_service.estimation": {"pd_service.native"},
    # baselines and research estimators (benchmarks, tests): never on the daemon's path
    "pd_service.research": {"pd_service.estimation", "pd_service.native"},
    "pd_service.errors": set(),
    "pd_service.logs": set(),
    "pd_service.ratelimit": set(),
    # the Prometheus endpoint every long-running executable shares (prometheus-client)
    "pd_service.metrics": set(),
    # which hot modules run compiled (mypyc, setup.py): stdlib only, read by setup.py alone
    "pd_service.native": set(),
    "pd_service.wire": {"pd_service.estimation", "pd_service.errors", "pd_service.native"},
    "pd_service.transport": set(),
    "pd_service.cli": {"pd_service.errors", "pd_service.logs", "pd_service.transport",
                       "pd_service.metrics"},
    "pd_service.scenarios": {"pd_service.estimation", "pd_service.wire", "pd_service.errors"},
    "pd_service.intake": {"pd_service.estimation", "pd_service.native", "pd_service.wire"},
    "pd_service.backends": {"pd_service.estimation", "pd_service.wire", "pd_service.errors"},
    "pd_service.ros2": {"pd_service.estimation", "pd_service.wire", "pd_service.errors"},
    # the pd-ros2 bridge on top of the pure building blocks: they never import it
    "pd_service.ros2.bridge": {"pd_service.ros2", "pd_service.wire", "pd_service.errors",
                               "pd_service.logs", "pd_service.transport", "pd_service.ratelimit",
                               "pd_service.metrics"},
    "pd_service.ros2.__main__": {"pd_service.ros2.bridge", "pd_service.errors", "pd_service.logs",
                                 "pd_service.transport", "pd_service.cli", "pd_service.ros2",
                                 "pd_service.metrics"},
    "pd_service.service": {"pd_service.estimation", "pd_service.wire", "pd_service.errors",
                           "pd_service.logs", "pd_service.transport", "pd_service.backends",
                           "pd_service.service.handover.checkpoint", "pd_service.intake",
                           "pd_service.ratelimit", "pd_service.native", "pd_service.metrics"},
    # the daemon's checkpoint codec (EstimatorState <-> SessionState): estimation and wire only
    "pd_service.service.handover.checkpoint": {"pd_service.estimation", "pd_service.wire"},
    "pd_service.link": {"pd_service.errors", "pd_service.logs", "pd_service.transport",
                        "pd_service.wire", "pd_service.cli", "pd_service.metrics"},
    "pd_service.__main__": {"pd_service.service"},
    "pd_service": {"pd_service.native"},
    "pd_client.tools": {"pd_client", "pd_service.estimation", "pd_service.wire",
                        "pd_service.errors", "pd_service.logs", "pd_service.transport",
                        "pd_service.scenarios", "pd_service.backends", "pd_service.ros2",
                        "pd_service.intake"},
    # backends: an Operator's check of u needs the model's input dimension
    "pd_client": {"pd_service.wire", "pd_service.errors", "pd_service.transport",
                  "pd_service.backends"},
}

#: All the wire layer may import of the estimation layer: pure data helpers (checks.py: the
#: PSD tolerance). No estimator, no model, no model registry: a spec becomes an estimator
#: in pd_service.backends alone.
WIRE_FROM_ESTIMATION = {"pd_service.estimation.checks"}

#: Third-party imports a layer may use (None: any). The estimation core is pure numpy (plus
#: mypy_extensions' compile hints for mypyc, which do nothing at run time).
THIRD_PARTY: dict[str, set[str] | None] = {
    "pd_service.estimation": {"numpy", "mypy_extensions"},
    "pd_service.research": {"numpy"},
    "pd_service.errors": set(),
    "pd_service.logs": set(),
    "pd_service.ratelimit": set(),
    "pd_service.native": set(),
    "pd_service.metrics": {"prometheus_client"},
}

STDLIB = set(sys.stdlib_module_names) | {"__future__"}


def layer_of(module: str) -> str:
    """The most specific key of ``ALLOWED`` that ``module`` falls under."""
    best = ""
    for name in ALLOWED:
        if (module == name or module.startswith(name + ".")) and len(name) > len(best):
            best = name
    assert best, f"{module} belongs to no layer: add it to ALLOWED and docs/architecture.md"
    return best


def modules() -> Iterator[tuple[str, Path]]:
    for top, base in SOURCES.items():
        for path in sorted(base.rglob("*.py")):
            rel = path.relative_to(base).with_suffix("")
            parts = [top, *rel.parts]
            if parts[-1] == "__init__":
                parts.pop()
            yield ".".join(parts), path


def imports_of(module: str, path: Path) -> Iterator[tuple[str, int]]:
    """Absolute names imported by the module (``from a import b`` gives ``a.b`` when ``a.b``
    is a module of the project, else ``a``), with line numbers."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    is_pkg = path.name == "__init__.py"
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield a.name, node.lineno
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".")
                if not is_pkg:
                    base = base[:-1]
                base = base[: len(base) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            for a in node.names:
                sub = f"{mod}.{a.name}"
                yield (sub if sub in KNOWN else mod), node.lineno


KNOWN = {m for m, _ in modules()}


def project_root(name: str) -> str | None:
    top = name.split(".")[0]
    return top if top in SOURCES else None


def edges() -> Iterator[tuple[str, str, int, Path]]:
    for module, path in modules():
        for target, line in imports_of(module, path):
            yield module, target, line, path


def test_every_module_has_a_layer() -> None:
    for module, _ in modules():
        layer_of(module)


def test_no_upward_or_sideways_import() -> None:
    bad = []
    for module, target, line, path in edges():
        src = layer_of(module)
        if project_root(target):
            dst = layer_of(target)
            if dst != src and dst not in ALLOWED[src]:
                bad.append(f"{path.relative_to(ROOT)}:{line}: {src} imports {target} ({dst})")
        else:
            allowed = THIRD_PARTY.get(src)
            top = target.split(".")[0]
            if allowed is not None and top not in STDLIB and top not in allowed:
                bad.append(f"{path.relative_to(ROOT)}:{line}: {src} imports {target}")
    assert not bad, "imports against docs/architecture.md:\n" + "\n".join(bad)


#: Layers of the daemon's path: none of them may import the research layer (its baselines
#: and research estimators serve benchmarks and tests only).
DAEMON_LAYERS = ("pd_service.service", "pd_service.backends", "pd_service.intake",
                 "pd_service.wire")


def test_the_daemon_never_imports_research() -> None:
    bad = [f"{path.relative_to(ROOT)}:{line}: imports {target}"
           for module, target, line, path in edges()
           if layer_of(module) in DAEMON_LAYERS and project_root(target)
           and layer_of(target) == "pd_service.research"]
    assert not any("pd_service.research" in ALLOWED[layer] for layer in DAEMON_LAYERS)
    assert not bad, "the daemon imports pd_service.research:\n" + "\n".join(bad)


def test_wire_builds_no_model_and_no_estimator() -> None:
    bad = [f"{path.relative_to(ROOT)}:{line}: {module} imports {target}"
           for module, target, line, path in edges()
           if layer_of(module) == "pd_service.wire"
           and (target == "pd_service.estimation" or target.startswith("pd_service.estimation."))
           and target not in WIRE_FROM_ESTIMATION]
    assert not bad, "the wire layer imports estimators or models:\n" + "\n".join(bad)


def test_no_import_cycle() -> None:
    """Tarjan's strongly connected components over the module graph. An edge from a module to
    a package that contains it is left out (Python imports the parent first anyway)."""
    graph: dict[str, set[str]] = {m: set() for m in KNOWN}
    for module, target, _, _ in edges():
        while target not in KNOWN and "." in target:
            target = target.rsplit(".", 1)[0]
        if target in KNOWN and target != module and not module.startswith(target + "."):
            graph[module].add(target)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10_000))
    for v in sorted(graph):
        if v not in index:
            visit(v)
    assert not cycles, f"import cycles: {cycles}"


@pytest.mark.parametrize("forbidden", ["matplotlib", "pd_client.tools", "pd_service.service",
                                       "pd_service.link"])
def test_import_pd_client_is_light(forbidden: str) -> None:
    code = f"import pd_client, sys; print({forbidden!r} in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False", f"import pd_client loads {forbidden}"


def _short(layer: str) -> str:
    return layer.removeprefix("pd_service.") if layer != "pd_service" else layer


def layer_table() -> list[str]:
    """The rows of docs/architecture.md's layer table, as ``ALLOWED`` and ``THIRD_PARTY`` say."""
    rows = []
    for layer, allowed in ALLOWED.items():
        project = ", ".join(sorted(_short(a) for a in allowed)) or "nothing"
        third = THIRD_PARTY.get(layer)
        party = "any" if third is None else " + ".join(sorted(third) + ["stdlib"])
        rows.append(f"| `{layer}` | {project} | {party} |")
    return rows


def test_architecture_doc_states_the_enforced_table() -> None:
    """docs/architecture.md's table is this test's table, row for row (regenerate it with
    ``python -c "from tests.test_layers import layer_table; print(*layer_table(), sep='\\n')"``)."""
    doc = (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8").splitlines()
    rows = [line for line in doc if line.startswith("| `pd_")]
    assert rows == layer_table()
