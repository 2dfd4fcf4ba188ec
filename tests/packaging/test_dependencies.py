"""Every import of every package is declared in its package.xml with a key that exists, and no package imports
one that imports it back (imports inside functions included: they are read from the syntax tree).

The keys are checked against the rosdistro key lists kept in ``tests/data/rosdistro`` (``rosdep/base.yaml``,
``rosdep/python.yaml``, the packages released for Jazzy), the workspace's own packages, and the project's rosdep
file for the pip packages rosdistro lacks (``rosdep/bac.yaml``).
"""

from __future__ import annotations

import ast
import re
import sys
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[2]
SRC = ROOT / "src"
DATA = ROOT / "tests" / "data" / "rosdistro"

# import name -> dependency key (a rosdep key, or the ROS package that provides the Python module)
KEY_OF_IMPORT = {
    "rclpy": "rclpy",
    "rcl_interfaces": "rcl_interfaces",
    "builtin_interfaces": "builtin_interfaces",
    "std_msgs": "std_msgs",
    "std_srvs": "std_srvs",
    "sensor_msgs": "sensor_msgs",
    "nav_msgs": "nav_msgs",
    "diagnostic_msgs": "diagnostic_msgs",
    "rosgraph_msgs": "rosgraph_msgs",
    "ament_index_python": "ament_index_python",
    "numpy": "python3-numpy",
    "scipy": "python3-scipy",
    "matplotlib": "python3-matplotlib",
    "yaml": "python3-yaml",
    "can": "python3-can",
    "cantools": "python3-cantools-pip",
    "rosbags": "python3-rosbags-pip",
    "asammdf": "python3-asammdf-pip",
    "msgpack": "python3-msgpack",
    "threadpoolctl": "python3-threadpoolctl-pip",
    "dask": "python3-dask-pip",
    "distributed": "python3-distributed-pip",
    "pytest": "python3-pytest",
    "sklearn": "python3-sklearn",
}
RUN_TAGS = ("depend", "exec_depend", "build_export_depend")
ALL_TAGS = ("depend", "exec_depend", "build_depend", "build_export_depend", "buildtool_depend", "test_depend")


@dataclass
class Package:
    name: str
    path: Path
    run: set[str] = field(default_factory=set)  # declared for the code
    test: set[str] = field(default_factory=set)  # declared for the tests only
    declared: set[str] = field(default_factory=set)  # every dependency tag

    @property
    def code(self) -> Path:
        return self.path / self.name


def packages() -> dict[str, Package]:
    out = {}
    for xml in sorted(SRC.glob("*/package.xml")):
        root = ET.parse(xml).getroot()
        name = root.findtext("name") or ""
        pkg = Package(name, xml.parent)
        for tag in ALL_TAGS:
            for el in root.findall(tag):
                key = (el.text or "").strip()
                pkg.declared.add(key)
                if tag in RUN_TAGS:
                    pkg.run.add(key)
                elif tag == "test_depend":
                    pkg.test.add(key)
        out[name] = pkg
    return out


def imports(path: Path) -> Iterator[tuple[str, int]]:
    """Top-level module names imported anywhere in the file (inside functions too), with their line."""
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield a.name.split(".")[0], node.lineno
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            yield node.module.split(".")[0], node.lineno


def local_modules(folder: Path) -> set[str]:
    return {p.stem for p in folder.glob("*.py")}


def key_of(module: str, pkgs: dict[str, Package]) -> str | None:
    """The dependency key of an imported module; None for the standard library."""
    if module in sys.stdlib_module_names or module == "__future__":
        return None
    if module in pkgs or module == "bac_msgs":
        return module
    if module in KEY_OF_IMPORT:
        return KEY_OF_IMPORT[module]
    raise KeyError(module)


def used(pkg: Package, pkgs: dict[str, Package], tests: bool) -> dict[str, list[str]]:
    """key -> where it is imported (file:line), for the package's code or for its tests."""
    folder = pkg.path / "test" if tests else pkg.code
    out: dict[str, list[str]] = {}
    if not folder.is_dir():
        return out
    for f in sorted(folder.rglob("*.py")):
        local = local_modules(f.parent)
        for module, line in imports(f):
            if module in local:
                continue
            try:
                key = key_of(module, pkgs)
            except KeyError:
                key = f"<no key known for the import '{module}': add it to KEY_OF_IMPORT>"
            if key is not None and key != pkg.name:
                out.setdefault(key, []).append(f"{f.relative_to(ROOT)}:{line}")
    return out


def known_keys(pkgs: dict[str, Package]) -> set[str]:
    keys = set(pkgs) | {"bac_msgs"}
    for name in ("base.yaml", "python.yaml"):
        keys |= set(yaml.safe_load((DATA / name).read_text()))
    keys |= {x.strip() for x in (DATA / "jazzy_packages.txt").read_text().splitlines() if x.strip()}
    keys |= set(yaml.safe_load((ROOT / "rosdep" / "bac.yaml").read_text()))
    return keys


PKGS = packages()


def test_every_python_package_is_found() -> None:
    assert {"bac_common", "bac_ecu_bridge", "bac_imu", "bac_measure", "bac_sim", "bac_agent", "bac_reduce",
            "bac_campaign", "bac_bringup", "bac_msgs"} <= set(PKGS)  # fmt: skip


@pytest.mark.parametrize("name", sorted(n for n, p in PKGS.items() if p.code.is_dir()))
def test_every_import_is_declared(name: str) -> None:
    pkg = PKGS[name]
    missing = {k: w for k, w in used(pkg, PKGS, tests=False).items() if k not in pkg.run}
    assert not missing, f"{name}/package.xml lacks exec_depend (or depend) for: " + "; ".join(
        f"{k} ({', '.join(w[:3])})" for k, w in sorted(missing.items())
    )
    missing_t = {k: w for k, w in used(pkg, PKGS, tests=True).items() if k not in pkg.run | pkg.test}
    assert not missing_t, f"{name}/package.xml lacks test_depend for: " + "; ".join(
        f"{k} ({', '.join(w[:3])})" for k, w in sorted(missing_t.items())
    )


@pytest.mark.parametrize("name", sorted(PKGS))
def test_every_dependency_key_exists(name: str) -> None:
    keys = known_keys(PKGS)
    unknown = sorted(PKGS[name].declared - keys)
    assert not unknown, (
        f"{name}/package.xml names keys that are neither rosdistro keys, Jazzy packages, workspace packages nor "
        f"defined in rosdep/bac.yaml: {unknown}"
    )


def test_no_package_imports_one_that_imports_it() -> None:
    graph = {
        name: {k for k in used(p, PKGS, False).keys() | used(p, PKGS, True).keys() if k in PKGS}
        for name, p in PKGS.items()
    }
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(n: str) -> None:
        state[n] = 1
        stack.append(n)
        for m in sorted(graph[n]):
            if state.get(m) == 1:
                cycle = [*stack[stack.index(m) :], m]
                pytest.fail("a cycle between packages (code and tests): " + " -> ".join(cycle))
            if m not in state:
                visit(m)
        stack.pop()
        state[n] = 2

    for n in sorted(graph):
        if n not in state:
            visit(n)


def test_the_readme_draws_the_package_graph_as_it_is() -> None:
    """The README's layout block names, for each package, exactly the bac packages its code imports."""
    text = (ROOT / "README.md").read_text()
    block = text[text.index("## Layout") :]
    block = block[block.index("```") + 3 :]
    block = block[: block.index("```")]
    drawn: dict[str, set[str]] = {}
    for line in block.strip().splitlines():
        name, _role, deps = re.split(r"\s{2,}", line.strip(), maxsplit=2)
        drawn[name] = {d.strip() for d in deps.split("(")[0].split(",") if d.strip().startswith("bac_")}
    assert set(drawn) == set(PKGS)
    for name, p in PKGS.items():
        if not p.code.is_dir():
            continue
        actual = {k for k in used(p, PKGS, tests=False) if k in PKGS and k != "bac_msgs"}
        assert drawn[name] == actual, f"README draws {name} -> {sorted(drawn[name])}, its code imports {sorted(actual)}"


def test_the_checks_catch_what_they_guard(tmp_path: Path) -> None:
    """An import hidden in a function is seen, and an unknown module has no key (the checks can fail)."""
    f = tmp_path / "m.py"
    f.write_text("def f():\n    import bac_campaign.report\n    from cantools import db\n")
    assert [m for m, _ in imports(f)] == ["bac_campaign", "cantools"]
    with pytest.raises(KeyError):
        key_of("no_such_module_anywhere", PKGS)
