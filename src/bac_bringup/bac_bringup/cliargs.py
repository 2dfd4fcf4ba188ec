"""Command-line parameter arguments shared by ``bac launch`` and ``bac replay``: ``-p node.param:=value`` and
``--params-file FILE``, checked before anything is made."""

from __future__ import annotations

import argparse
import re
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import yaml

from bac_bringup.profile import ProfileError


def parse_assignment(text: str) -> tuple[str, str, Any]:
    """``node.param:=value`` -> (node, param, value parsed as YAML)."""
    if ":=" not in text or "." not in text.split(":=", 1)[0]:
        raise argparse.ArgumentTypeError(f"expected node.param:=value, got {text!r}")
    key, raw = text.split(":=", 1)
    node, param = key.split(".", 1)
    value = yaml.safe_load(raw) if raw != "" else ""
    if isinstance(value, str) and re.fullmatch(r"[-+]?(\d+\.?\d*|\.\d+)[eE][-+]?\d+", raw.strip()):
        value = float(raw)  # 1e-05: a string to PyYAML (YAML 1.1), a number to rcl and to the user
    return node, param, value


def ros_params_layout(data: Any) -> bool:
    """A ROS parameter file: a mapping whose leaves are ``{ros__parameters: {...}}`` blocks, at any depth of
    namespaces (``ns: {node: {ros__parameters: ...}}``, as rcl reads them)."""
    if not isinstance(data, dict) or not data:
        return False
    return all(isinstance(v, dict) and ("ros__parameters" in v or ros_params_layout(v)) for v in data.values())


def check_params_files(files: Iterable[str | Path]) -> None:
    """Refuse (:class:`ProfileError`) a ``--params-file`` that is missing, not YAML or not a ROS parameter file."""
    for f in files:
        if not Path(f).is_file():
            raise ProfileError(f"--params-file {f}: no such file")
        try:
            data = yaml.safe_load(Path(f).read_text())
        except (yaml.YAMLError, UnicodeDecodeError) as exc:
            raise ProfileError(f"--params-file {f}: not YAML: {exc}") from None
        if data is not None and not ros_params_layout(data):
            raise ProfileError(
                f"--params-file {f}: not a ROS parameter file ({{node: {{ros__parameters: {{...}}}}}} per node)"
            )


def add_param_arguments(ap: argparse.ArgumentParser) -> None:
    """``-p/--param NODE.PARAM:=VALUE`` and ``--params-file FILE``, both repeatable."""
    ap.add_argument(
        "-p",
        "--param",
        action="append",
        default=[],
        type=parse_assignment,
        metavar="NODE.PARAM:=VALUE",
        help="override one node parameter (repeatable)",
    )
    ap.add_argument("--params-file", action="append", default=[], help="extra ROS parameter YAML (repeatable)")


def overrides_of(assignments: Sequence[tuple[str, str, Any]]) -> dict[str, dict[str, Any]]:
    """The parsed ``-p`` assignments as {node: {param: value}}, a later one winning."""
    out: dict[str, dict[str, Any]] = {}
    for node, param, value in assignments:
        out.setdefault(node, {})[param] = value
    return out
