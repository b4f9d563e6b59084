"""A script of the repository (bench/*.py, deploy/*.py) loaded as a module by its path, for the
tests that drive what a script does without running it as a process."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[1]


def load_script(relative: str, name: str) -> ModuleType:
    """``ROOT / relative`` as a module called ``name``."""
    spec = importlib.util.spec_from_file_location(name, ROOT / relative)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod  # what a dataclass of the script looks its module up by
    spec.loader.exec_module(mod)
    return mod
