"""Publish the cockpit of a graph that runs in a private network namespace.

``bac launch sim`` runs the graph inside a private network namespace (CAN over udp_multicast between
processes must stay on this machine): a port the cockpit opens in there is out of the user's browser's reach.
A Unix socket is a file, not a network address, so it is shared across namespaces: the cockpit serves on one
(its ``unix_socket`` parameter) and the launcher, still outside, listens on the cockpit's host and port and
relays each connection to it, byte for byte (the cockpit still checks the token of every request).

:func:`publish_cockpit` is what the launcher calls: it starts the relay and returns the ``-p`` arguments that
tell the cockpit node where to serve and which address to print.
"""

from __future__ import annotations

import asyncio
import contextlib
import shutil
import tempfile
import threading
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from bac_cockpit.server import DEFAULT_HOST, DEFAULT_PORT, CockpitError, check_exposure, page_url

NODE = "cockpit"
CHUNK = 65536


class Relay:
    """host:port (TCP) -> a Unix socket, in a thread of its own."""

    def __init__(self, host: str, port: int, unix_path: str) -> None:
        self.host = host
        self.port = int(port)
        self.unix_path = unix_path
        self.bound_port = 0
        self.fallback_from = 0
        self.connections = 0
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._thread: threading.Thread | None = None

    def start(self, timeout_s: float = 10.0) -> int:
        self._thread = threading.Thread(target=self._run, name="bac-cockpit-relay", daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout_s):
            raise CockpitError("the cockpit relay did not start")
        if self._error is not None:
            raise CockpitError(f"the cockpit relay cannot listen on {self.host}:{self.port}: {self._error}")
        return self.bound_port

    def _run(self) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        try:
            loop.run_until_complete(self._serve())
        except BaseException as exc:
            if not self._ready.is_set():
                self._error = exc
                self._ready.set()
        finally:
            loop.close()

    async def _serve(self) -> None:
        self._stop = asyncio.Event()
        try:
            server = await asyncio.start_server(self._handle, self.host, self.port)
        except OSError:
            if self.port == 0:
                raise
            server = await asyncio.start_server(self._handle, self.host, 0)
            self.fallback_from = self.port
        self.bound_port = int(server.sockets[0].getsockname()[1])
        self._ready.set()
        async with server:
            await self._stop.wait()

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.connections += 1
        try:
            up_r, up_w = await asyncio.open_unix_connection(self.unix_path)
        except OSError:
            body = b"the cockpit is starting (or has stopped); reload in a moment\n"
            writer.write(
                b"HTTP/1.1 503 Service Unavailable\r\nContent-Type: text/plain\r\nRetry-After: 1\r\n"
                + f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n".encode()
                + body
            )
            with contextlib.suppress(OSError):
                await writer.drain()
            writer.close()
            return

        async def pump(r: asyncio.StreamReader, w: asyncio.StreamWriter) -> None:
            try:
                while data := await r.read(CHUNK):
                    w.write(data)
                    await w.drain()
            except (OSError, asyncio.CancelledError):
                pass
            finally:
                with contextlib.suppress(OSError, RuntimeError):
                    w.close()

        await asyncio.gather(pump(reader, up_w), pump(up_r, writer))

    def stop(self) -> None:
        loop, stop = self._loop, self._stop
        if loop is not None and stop is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(stop.set)
        if self._thread is not None:
            self._thread.join(3.0)


class Published:
    """A relay and its socket folder; :meth:`close` stops it and removes the folder."""

    def __init__(self, relay: Relay, folder: Path, url: str) -> None:
        self.relay = relay
        self.folder = folder
        self.url = url

    def close(self) -> None:
        self.relay.stop()
        shutil.rmtree(self.folder, ignore_errors=True)


def cockpit_params(params_files: Sequence[str | Path], overrides: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The cockpit node's parameters from the profile's files and the launch's overrides (later wins)."""
    from bac_measure.measure_config import load_node_params

    return load_node_params(list(params_files), NODE, overrides)


def publish_cockpit(
    params_files: Sequence[str | Path], overrides: Mapping[str, Any] | None = None
) -> tuple[list[str], Published]:
    """Start the relay for a cockpit that will run in a private network namespace; returns the launcher's extra
    ``-p`` arguments for the node and the relay (close it when the graph ends)."""
    p = cockpit_params(params_files, overrides)
    host = str(p.get("host", DEFAULT_HOST) or DEFAULT_HOST)
    port = int(p.get("port", DEFAULT_PORT))
    check_exposure(host, str(p.get("token", "") or ""))  # refused here too: nothing listens on the network untokened
    folder = Path(tempfile.mkdtemp(prefix="bac-cockpit-"))  # 0700: only this user reaches the socket
    sock = folder / "cockpit.sock"
    relay = Relay(host, port, str(sock))
    try:
        bound = relay.start()
    except CockpitError:
        shutil.rmtree(folder, ignore_errors=True)
        raise
    url = page_url(host, bound)
    args = ["-p", f"{NODE}.unix_socket:={sock}", "-p", f"{NODE}.public_url:={url}"]
    return args, Published(relay, folder, url)
