"""Finding calibration definitions and the workspace."""

from __future__ import annotations

import os
from pathlib import Path

from bac_common.errors import DefinitionError


def _workspaces() -> list[Path]:
    found: list[Path] = []
    env = os.environ.get("BAC_WS")
    if env:
        found.append(Path(env))
    for start in (Path.cwd(), Path(__file__).resolve()):
        for d in (start, *start.parents):
            if (d / "ros_ws" / "config" / "calibrations").is_dir():
                found.append(d / "ros_ws")
                break
    return found


def resolve_definition(value: str | Path) -> Path:
    """A definition file: a path (absolute, or relative to the working directory or to the
    repository), or a name of ``ros_ws/config/calibrations`` (``controller_ii``)."""
    text = str(value).strip()
    if not text:
        raise DefinitionError("no calibration definition given (set the definition_file parameter)")
    p = Path(text).expanduser()
    if p.is_file():
        return p.resolve()
    for ws in _workspaces():
        for candidate in (
            ws.parent / p,
            ws / p,
            ws / "config" / "calibrations" / p,
            ws / "config" / "calibrations" / f"{text}.yaml",
        ):
            if candidate.is_file():
                return candidate.resolve()
    raise DefinitionError(
        f"calibration definition '{text}' not found (looked in the working directory and ros_ws/config/calibrations)"
    )
