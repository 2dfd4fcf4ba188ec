"""Where bac's installed data are: calibration definitions (here), profiles and parameter files (bac_bringup).

Each package installs its data to ``share/<package>/`` (``colcon build``; ``scripts/setup.sh`` links the source
folders there for the development install) and they are found through the ament index, so the tools work from an
install space as well as from the repository, whatever the working directory. The repository's ``ros_ws/``
folder links to the same files (``ros_ws/config/calibrations`` -> ``src/bac_common/calibrations``,
``ros_ws/profiles`` and ``ros_ws/params`` -> ``src/bac_bringup/``).

``$BAC_WS`` names a folder of one's own (with ``config/calibrations/``, ``profiles/``, ``params/``) searched first.
"""

from __future__ import annotations

import os
from pathlib import Path

from bac_common.errors import DefinitionError

CALIBRATIONS = "calibrations"  # share/bac_common/calibrations


def package_share(package: str) -> Path | None:
    """``share/<package>`` of an installed package (ament index), or None when it is not installed."""
    try:
        from ament_index_python.packages import PackageNotFoundError, get_package_share_directory
    except ImportError:  # no ament index (a plain Python install): only the source tree
        return None
    try:
        return Path(get_package_share_directory(package))
    except (PackageNotFoundError, ValueError, LookupError):
        return None


def _user_workspace() -> Path | None:
    env = os.environ.get("BAC_WS", "").strip()
    return Path(env).expanduser() if env else None


def calibration_dirs() -> list[Path]:
    """The folders searched for a definition by name, in order."""
    out: list[Path] = []
    ws = _user_workspace()
    if ws is not None:
        out.append(ws / "config" / "calibrations")
    share = package_share("bac_common")
    if share is not None:
        out.append(share / CALIBRATIONS)
    out.append(Path(__file__).resolve().parents[1] / CALIBRATIONS)  # the source tree (an editable install)
    seen: list[Path] = []
    for d in out:
        if d.is_dir() and all(d.resolve() != s.resolve() for s in seen):
            seen.append(d)
    return seen


def calibration_file(name: str) -> Path | None:
    """The shipped (or $BAC_WS) definition called ``name`` (``controller_ii``), or None."""
    for d in calibration_dirs():
        for cand in (d / name, d / f"{name}.yaml"):
            if cand.is_file():
                return cand.resolve()
    return None


def resolve_definition(value: str | Path) -> Path:
    """A calibration definition file: a path (absolute or relative to the working directory), or the name of a
    shipped definition (``controller_i``, ``controller_ii``, ``controller_ii_reduced``, or one in $BAC_WS)."""
    text = str(value).strip()
    if not text:
        raise DefinitionError("no calibration definition given (set the definition_file parameter)")
    p = Path(text).expanduser()
    if p.is_file():
        return p.resolve()
    found = calibration_file(p.name if p.suffix in (".yaml", ".yml") else text)
    if found is not None:
        return found
    dirs = calibration_dirs()
    names = sorted({f.stem for d in dirs for f in d.glob("*.yaml")})
    raise DefinitionError(
        f"calibration definition '{text}' not found: not a file, and not a definition shipped with bac "
        f"({', '.join(names) or 'none found'}; looked in {', '.join(str(d) for d in dirs) or 'no folder'}); "
        "give a YAML path"
    )
