"""Safe by default: the cockpit listens on 127.0.0.1 only; another address is refused without an access token, and
with one every request without it gets 401 (403 with a wrong one). Real processes: ``bac cockpit`` and the
``cockpit`` node; and the address ``bac demo`` prints for its graph in a private network namespace is reached from
outside it (on 127.0.0.1 still)."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

import psutil
import pytest

from conftest import ROOT, Procs, wait_for

sys.path.insert(0, str(ROOT / "src" / "bac_cockpit" / "test"))
from campaign_maker import make_campaign

pytestmark = pytest.mark.integration
TOKEN = "tablet-in-the-car-0123456789"


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    camp = tmp_path_factory.mktemp("sec") / "camp"
    make_campaign(camp, budget=5)
    return camp


def status(url: str) -> int:
    try:
        with urllib.request.urlopen(url, timeout=10) as r:
            return int(r.status)
    except urllib.error.HTTPError as e:
        return int(e.code)


def listening(pid: int) -> list[tuple[str, int]]:
    """The TCP addresses a process (and its children: the model worker) listens on."""
    p = psutil.Process(pid)
    out = []
    for proc in [p, *p.children(recursive=True)]:
        try:
            conns = proc.net_connections(kind="tcp")
        except psutil.Error:
            continue
        out += [(c.laddr.ip, c.laddr.port) for c in conns if c.status == psutil.CONN_LISTEN]
    return out


def printed_url(procs: Procs, name: str) -> str:
    m = wait_for(lambda: re.search(r"cockpit: (http://\S+)", procs.log(name)), 60, what=f"{name}'s address")
    return str(m.group(1))


def test_another_host_without_a_token_is_refused(folder: Path) -> None:
    for extra, why in (([], "access token is required"), (["--token", "short"], "too short")):
        proc = subprocess.run(
            [sys.executable, "-m", "bac_bringup.cli", "cockpit", str(folder), "--host", "0.0.0.0", *extra],
            capture_output=True,
            text=True,
            timeout=120,
            check=False,
            env={k: v for k, v in os.environ.items() if k != "BAC_COCKPIT_TOKEN"},
        )
        assert proc.returncode == 2, proc.stdout + proc.stderr
        assert why in proc.stderr and "cockpit: http" not in proc.stdout


def test_the_node_refuses_another_host_without_a_token(procs: Procs, tmp_path: Path) -> None:
    p = procs.python(
        "cockpit",
        ["-m", "bac_cockpit.cockpit_node", "--ros-args", "-p", "host:=0.0.0.0", "-p", f"campaign_dir:={tmp_path}"],
    )
    assert p.wait(timeout=120) != 0
    assert "access token is required" in procs.log("cockpit")
    assert not (tmp_path / "cockpit.json").exists()


def test_by_default_only_127_0_0_1_is_listened_on(procs: Procs, folder: Path, tmp_path: Path) -> None:
    cli = procs.python("cli", ["-m", "bac_bringup.cli", "cockpit", str(folder)])
    node = procs.python("node", ["-m", "bac_cockpit.cockpit_node", "--ros-args", "-p", f"campaign_dir:={tmp_path}"])
    for name, proc in (("cli", cli), ("node", node)):
        url = printed_url(procs, name)
        assert url.startswith("http://127.0.0.1:") and "token" not in url
        port = int(url.split(":")[2].split("/")[0])
        assert status(url + "api/health") == 200
        socks = wait_for(lambda proc=proc: listening(proc.pid), 30, what=f"{name}'s listening sockets")
        assert (("127.0.0.1", port)) in socks
        assert all(ip == "127.0.0.1" for ip, _ in socks), (name, socks)
    # the node says where it is for bac demo and bac watch (readable by the user only)
    rec = tmp_path / "cockpit.json"
    assert rec.exists() and (rec.stat().st_mode & 0o077) == 0


def test_with_a_token_a_request_without_it_is_refused(procs: Procs, folder: Path, in_private_netns: bool) -> None:
    host = "0.0.0.0" if in_private_netns else "127.0.0.1"  # all interfaces only where loopback is the only one
    procs.python("cli", ["-m", "bac_bringup.cli", "cockpit", str(folder), "--host", host, "--port", "0",
                         "--token", TOKEN])  # fmt: skip
    url = printed_url(procs, "cli")
    assert url.endswith(f"/?token={TOKEN}")
    port = int(re.search(r":(\d+)/", url).group(1))  # type: ignore[union-attr]
    base = f"http://127.0.0.1:{port}"
    for path in ("/", "/api/state", "/events", "/static/cockpit.js"):
        assert status(base + path) == 401, path
        assert status(base + path + "?token=not-the-token-at-all") == 403, path
    assert status(base + f"/api/state?token={TOKEN}") == 200
    req = urllib.request.Request(base + "/api/state", method="POST", headers={"Authorization": f"Bearer {TOKEN}"})
    with pytest.raises(urllib.error.HTTPError) as err:
        urllib.request.urlopen(req, timeout=10)
    assert err.value.code == 405  # read-only, even with the token


def test_the_demo_s_private_graph_has_its_cockpit_published_here(procs: Procs, tmp_path: Path) -> None:
    """``bac demo`` runs its graph in a private network namespace of its own: the address it prints is reached
    from this one (the relay, through a Unix socket), and it still shows the live campaign."""
    camp = tmp_path / "demo"
    # this test already runs in a private namespace: unmarked, the demo makes one of its own, as from a shell
    procs.python("demo", ["-m", "bac_bringup.cli", "demo", "--budget", "2", "--campaign-dir", str(camp)],
                 env={"BAC_PRIVATE_NETNS": ""})  # fmt: skip
    url = printed_url(procs, "demo")
    assert url == "http://127.0.0.1:8765/", procs.log("demo")
    assert "in a private network namespace" in procs.log("demo")
    node_pid = int(json.loads((camp / "cockpit.json").read_text())["pid"])
    assert os.readlink(f"/proc/{node_pid}/ns/net") != os.readlink("/proc/self/ns/net")  # the node is elsewhere
    with urllib.request.urlopen(url + "api/health", timeout=10) as r:
        assert json.loads(r.read())["mode"] == "live"

    def trial_shown() -> Any:
        with urllib.request.urlopen(url + "api/state", timeout=10) as r:
            trial = json.loads(r.read()).get("trial")
        return trial if trial and int(trial.get("trial_id", 0)) >= 1 else None

    trial = wait_for(trial_shown, 180, what="the demo's first trial on the relayed page")
    assert int(trial["trial_id"]) >= 1
