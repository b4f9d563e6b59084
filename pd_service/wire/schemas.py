"""Export the JSON Schema of every message to ``docs/schemas/<Message>.json``.

    python -m pd_service.wire.schemas [OUT_DIR]            # write (default docs/schemas)
    python -m pd_service.wire.schemas --check [OUT_DIR]    # exit 1 if the files are stale

The schemas describe the *validation* side (what the daemon accepts): fields with a
default may be omitted. Every message the service publishes carries every field.
JSON Schema cannot express the cross-field rules (dimensions consistent with each other,
covariances symmetric PSD, exactly one of step / t_ns); those are in each schema's
description and in docs/protocol.md.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from .camera import CameraFrame
from .messages import MESSAGE_TYPES, Message
from .path import PredictedPath
from .session_state import SessionState
from .truth import Truth

DEFAULT_DIR = Path("docs/schemas")
DIALECT = "https://json-schema.org/draft/2020-12/schema"


def schemas() -> dict[str, dict[str, Any]]:
    """File name -> JSON Schema, for every message type."""
    out: dict[str, dict[str, Any]] = {}
    types: tuple[type[Message], ...] = (*MESSAGE_TYPES, PredictedPath, SessionState, Truth,
                                           CameraFrame)
    for cls in types:
        schema = cls.model_json_schema(mode="validation")
        schema = {"$schema": DIALECT, "$id": f"pd-service/v1/{cls.__name__}.json", **schema}
        out[f"{cls.__name__}.json"] = schema
    return out


def render(schema: dict[str, Any]) -> str:
    """Stable text of one schema (sorted keys, 2-space indent, trailing newline)."""
    return json.dumps(schema, indent=2, sort_keys=True, ensure_ascii=False) + "\n"


def stale(out_dir: Path = DEFAULT_DIR) -> list[str]:
    """File names in ``out_dir`` that are missing, different or left over (empty: up to date)."""
    wanted = {name: render(s) for name, s in schemas().items()}
    problems = []
    for name, text in wanted.items():
        path = out_dir / name
        if not path.is_file() or path.read_text(encoding="utf-8") != text:
            problems.append(name)
    if out_dir.is_dir():
        problems += sorted(p.name for p in out_dir.glob("*.json") if p.name not in wanted)
    return problems


def export(out_dir: Path = DEFAULT_DIR) -> list[Path]:
    """Write every schema to ``out_dir`` and delete schema files of messages that no
    longer exist. Returns the written paths."""
    out_dir.mkdir(parents=True, exist_ok=True)
    wanted = schemas()
    written = []
    for name, schema in wanted.items():
        path = out_dir / name
        path.write_text(render(schema), encoding="utf-8")
        written.append(path)
    for old in out_dir.glob("*.json"):
        if old.name not in wanted:
            old.unlink()
    return written


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pd_service.wire.schemas",
                                     description="Export the wire JSON Schemas.")
    parser.add_argument("out_dir", nargs="?", type=Path, default=DEFAULT_DIR)
    parser.add_argument("--check", action="store_true",
                        help="do not write; exit 1 if the files are stale")
    args = parser.parse_args(argv)
    if args.check:
        problems = stale(args.out_dir)
        for name in problems:
            print(f"stale: {args.out_dir / name}", file=sys.stderr)
        return 1 if problems else 0
    for path in export(args.out_dir):
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
