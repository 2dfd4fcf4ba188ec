"""Run a command inside a private network namespace (README.md, "The network rule").

CAN over python-can's ``udp_multicast`` between processes, and the DDS traffic
of the graph, must never leave this machine. Inside a fresh network namespace
the only interface is a loopback we bring up with multicast on and a route
for 224.0.0.0/4, so nothing *can* leave, whatever a library does.

Root uses ``unshare --net``; others ``unshare --user --map-root-user --net``
(unprivileged user namespaces). The namespace dies with its last process: no
clean-up is needed after a crash.

Usage::

    python -m bac_bringup.netns -- COMMAND [ARG ...]
    python -m bac_bringup.netns --new -- COMMAND [ARG ...]

``--new`` makes a namespace of its own even inside one, and *becomes* the command (exec: same process id, same
standard streams): ``make test`` starts each of its pytest workers this way (``scripts/test-worker``), so that two
tests running at once never share a loopback, a CAN multicast port or a DDS discovery port.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections.abc import Sequence

from bac_common.errors import BacError

ENV_MARKER = "BAC_PRIVATE_NETNS"

_SETUP = 'ip link set lo up multicast on && ip route add 224.0.0.0/4 dev lo 2>/dev/null; exec "$@"'


class NetnsError(BacError, RuntimeError):
    """A private network namespace could not be created."""


def in_private_netns() -> bool:
    """True inside a namespace made by :func:`wrap_command` (or marked as such)."""
    return os.environ.get(ENV_MARKER) == "1"


def wrap_command(argv: Sequence[str]) -> list[str]:
    """The command line that runs ``argv`` in a new private network namespace."""
    unshare = shutil.which("unshare")
    ip = shutil.which("ip")
    if unshare is None or ip is None:
        raise NetnsError(
            "a private network namespace needs 'unshare' (util-linux) and 'ip' (iproute2); "
            "install them (apt-get install util-linux iproute2) or use the single-process "
            "launcher (virtual CAN bus)"
        )
    flags = ["--net"] if os.geteuid() == 0 else ["--user", "--map-root-user", "--net"]
    return [unshare, *flags, "--", "/bin/sh", "-c", _SETUP, "sh", *argv]


def private_env(env: dict[str, str] | None = None) -> dict[str, str]:
    out = dict(os.environ if env is None else env)
    out[ENV_MARKER] = "1"
    out.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    return out


def check_available() -> None:
    """Raise :class:`NetnsError` with the reason when no private namespace can be made."""
    cmd = wrap_command(["true"])
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise NetnsError(
            "cannot create a private network namespace "
            f"({' '.join(cmd[:4])} failed: {proc.stderr.strip() or proc.returncode}); "
            "run as root or enable unprivileged user namespaces "
            "(sysctl kernel.unprivileged_userns_clone=1)"
        )


def run(argv: Sequence[str]) -> int:
    """Run ``argv`` in a private network namespace (or directly if already in one)."""
    if in_private_netns():
        return subprocess.call(list(argv))
    return subprocess.call(wrap_command(argv), env=private_env())


def exec_new(argv: Sequence[str]) -> None:
    """Replace this process by ``argv`` inside a new private network namespace (also when already in one)."""
    cmd = wrap_command(argv)
    os.execve(cmd[0], cmd, private_env())


def main(args: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if args is None else args)
    new = bool(argv) and argv[0] == "--new"
    if new:
        argv = argv[1:]
    if argv and argv[0] == "--":
        argv = argv[1:]
    if not argv:
        sys.stderr.write("usage: python -m bac_bringup.netns [--new] -- COMMAND [ARG ...]\n")
        return 2
    try:
        if new:
            exec_new(argv)
        return run(argv)
    except NetnsError as exc:
        sys.stderr.write(f"bac netns: {exc}\n")
        return 3


if __name__ == "__main__":
    sys.exit(main())
