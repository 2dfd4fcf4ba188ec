"""Started with the graph: ``bac launch sim`` prints the cockpit's address at start, also when the nodes' output goes
to log files (``--log-dir``), and the page answers there."""

from __future__ import annotations

import json
import re
import urllib.request
from pathlib import Path

import pytest

from conftest import Procs, wait_for

pytestmark = pytest.mark.integration


def test_bac_launch_sim_prints_the_cockpit_s_address(procs: Procs, tmp_path: Path) -> None:
    camp = tmp_path / "camp"
    (camp).mkdir()
    (camp / "cockpit.json").write_text(json.dumps({"url": "http://127.0.0.1:1/stale"}))  # an earlier launch's
    procs.python("launch", ["-m", "bac_bringup.cli", "launch", "sim", "--campaign-dir", str(camp),
                            "--log-dir", str(tmp_path / "logs"), "-p", "bo_agent.budget:=2"])  # fmt: skip
    m = wait_for(lambda: re.search(r"cockpit: (http://\S+)", procs.log("launch")), 120, what="the cockpit's address")
    url = m.group(1)
    assert url.startswith("http://127.0.0.1:") and "stale" not in procs.log("launch"), procs.log("launch")
    with urllib.request.urlopen(url + "api/health", timeout=10) as r:
        assert json.loads(r.read())["mode"] == "live"
