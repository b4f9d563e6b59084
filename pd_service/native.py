"""The daemon's hot modules that ``setup.py`` compiles with mypyc, and the switch back to their
Python source.

The compiled modules are the same source as the .py files beside them; Python imports an
extension module in place of the .py file when both are there. When ``pd_service`` is first
imported, this module decides (:data:`STATUS`):

- ``PD_SERVICE_PURE=1`` in the environment: the .py files (the reference the compiled build
  is tested against, and the fallback should a compiled module ever misbehave);
- a compiled build whose sources differ from the .py files now there (an edited checkout not
  rebuilt: ``make venv`` rebuilds): the .py files, with a RuntimeWarning, never stale code;
- else the compiled modules if built, the .py files if not.

``setup.py`` writes the digest of the sources it compiled to :data:`DIGEST_FILE`.
:func:`compiled` tells which modules run compiled.

Stdlib only: ``setup.py`` reads :data:`HOT_MODULES` from this file without importing the
package.
"""

from __future__ import annotations

import hashlib
import importlib
import os
import sys
import warnings
from collections.abc import Callable, Sequence
from importlib.machinery import ModuleSpec
from pathlib import Path
from types import ModuleType
from typing import Any, cast

#: The per-message path: decode and checks, the estimator's window and bookkeeping,
#: publishing. (Module names; setup.py compiles their files.)
HOT_MODULES = (
    "pd_service.estimation.checks",
    "pd_service.estimation.delay_learning",
    "pd_service.estimation.inputs",
    "pd_service.estimation.linear",
    "pd_service.estimation.observer",
    "pd_service.estimation.replay",
    "pd_service.intake",
    "pd_service.ratelimit",
    "pd_service.service.core",
    "pd_service.service.dispatch",
    "pd_service.service.handover.keeper",
    "pd_service.service.health",
    "pd_service.service.latency",
    "pd_service.service.outbox",
    "pd_service.service.robot_time",
    "pd_service.service.session",
    "pd_service.transport.zenoh_transport",
    "pd_service.wire.convert",
)

#: Kernels written in C (module -> source file, relative to the repository): built with the
#: compiled modules (all or none) and used only where these run compiled (:func:`kernel`);
#: each has a numpy form beside its caller, the reference it is tested against.
C_KERNELS = {
    "pd_service.estimation._kalman": "pd_service/estimation/_kalman.c",
    "pd_service.intake._fastread": "pd_service/intake/_fastread.c",
    "pd_service.service._moments": "pd_service/service/_moments.c",
    "pd_service.wire._encode": "pd_service/wire/_encode.c",
}

#: ``PD_SERVICE_PURE=1``: import the .py files even where an extension is built.
PURE_ENV = "PD_SERVICE_PURE"

_ROOT = Path(__file__).resolve().parent.parent

#: sha256 of the hot modules' sources that the compiled build was made from (setup.py).
DIGEST_FILE = Path(__file__).with_name("native.sha256")


def source_path(module: str) -> Path:
    """The .py file of a hot module (a package's ``__init__.py``)."""
    path = _ROOT.joinpath(*module.split("."))
    return path / "__init__.py" if path.is_dir() else path.with_suffix(".py")


class _SourceFirst:
    """Finds the hot modules' .py files ahead of their extension modules (a meta path
    finder; importlib.abc is not imported for it: its import would slow every start)."""

    def find_spec(self, fullname: str, path: Sequence[str] | None = None,
                  target: ModuleType | None = None) -> ModuleSpec | None:
        if fullname not in HOT_MODULES:
            return None
        import importlib.util

        src = source_path(fullname)
        package = src.name == "__init__.py"
        return importlib.util.spec_from_file_location(
            fullname, src, submodule_search_locations=[str(src.parent)] if package else None)


def sources_digest() -> str:
    """sha256 over the hot modules' names and sources, in :data:`HOT_MODULES` order, then
    the C kernels' (:data:`C_KERNELS`)."""
    h = hashlib.sha256()
    for name in HOT_MODULES:
        h.update(name.encode() + b"\0" + source_path(name).read_bytes() + b"\0")
    for name, src in C_KERNELS.items():
        h.update(name.encode() + b"\0" + _ROOT.joinpath(src).read_bytes() + b"\0")
    return h.hexdigest()


def _built() -> bool:
    """Whether a compiled build is installed beside the sources."""
    here = Path(__file__).parent
    return any(here.glob("native__mypyc.*"))


def use_pure() -> None:
    """Import the hot modules from their .py files from now on (before they are imported)."""
    if not any(isinstance(f, _SourceFirst) for f in sys.meta_path):
        sys.meta_path.insert(0, _SourceFirst())


def compiled() -> dict[str, bool]:
    """Hot module -> whether it runs compiled (imports them)."""
    out = {}
    for name in HOT_MODULES:
        mod = importlib.import_module(name)
        out[name] = not str(getattr(mod, "__file__", "")).endswith(".py")
    return out


def kernel(name: str) -> ModuleType | None:
    """The C kernel ``name`` (a key of :data:`C_KERNELS`) when the hot path runs compiled
    (built, fresh, not ``PD_SERVICE_PURE=1``), else None: the caller then runs its numpy
    form."""
    if not STATUS.startswith("compiled"):
        return None
    if name in sys.modules:
        return sys.modules[name]
    # Loaded from its file beside the C source, not by name: a package that runs compiled
    # (pd_service.intake) gets a wrong __path__ from mypyc, where the import system would
    # not find a module of its own.
    import importlib.machinery
    import importlib.util

    src = _ROOT / C_KERNELS[name]
    try:
        for suffix in importlib.machinery.EXTENSION_SUFFIXES:
            path = src.with_suffix(suffix)
            if path.is_file():
                spec = importlib.util.spec_from_file_location(name, path)
                assert spec is not None and spec.loader is not None
                mod = importlib.util.module_from_spec(spec)
                spec.loader.exec_module(mod)
                sys.modules[name] = mod
                return mod
        raise ImportError(f"no extension module beside {src}")
    except ImportError:  # e.g. a numpy older than the one it was built against
        warnings.warn(f"pd_service: the C kernel {name} does not load; running its numpy "
                      "form (rebuild: make venv)", RuntimeWarning, stacklevel=2)
        return None


def kernel_function(name: str, attr: str) -> Callable[..., Any] | None:
    """The function ``attr`` of the C kernel ``name`` (None where :func:`kernel` is None).
    Bound once at import into a ``Final`` module attribute, a compiled caller reads it from
    a C static and calls it directly: a call through the module object looks the function
    up on the module each time."""
    mod = kernel(name)
    return None if mod is None else cast("Callable[..., Any]", getattr(mod, attr))


def _decide() -> str:
    if os.environ.get(PURE_ENV) == "1":
        use_pure()
        return f"pure Python ({PURE_ENV}=1)"
    if not _built():
        return "pure Python (not compiled: no C compiler at install time, or PD_SERVICE_PURE=1)"
    try:
        fresh = DIGEST_FILE.read_text().strip() == sources_digest()
    except OSError:
        fresh = False
    if not fresh:
        use_pure()
        warnings.warn("pd_service: the compiled hot path was built from other sources than the "
                      ".py files now installed; running them as pure Python (rebuild: make "
                      "venv, or pip install -e .)", RuntimeWarning, stacklevel=2)
        return "pure Python (the compiled build is stale: rebuild with make venv)"
    return f"compiled with mypyc ({len(HOT_MODULES)} modules)"


#: How the hot modules run: "compiled with mypyc (...)" or "pure Python (why)". (Decided
#: only as part of the package: setup.py reads this file on its own.)
STATUS = _decide() if __name__ == "pd_service.native" else "undecided"
