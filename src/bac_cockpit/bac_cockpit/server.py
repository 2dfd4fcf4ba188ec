"""The cockpit's web server: one page, its scripts and styles, the state as JSON and live updates as
server-sent events (aiohttp, in a thread of its own with its own event loop).

* ``GET /``: the page; ``GET /static/<file>``: its scripts and styles (plotly.js vendored: nothing is
  fetched from the internet); ``GET /api/state``: the whole state; ``GET /events``: ``text/event-stream``,
  a ``snapshot`` event on connect then a ``patch`` event (the changed top-level keys) per change.
* Read-only: only GET and HEAD are routed; the server changes nothing in the campaign.
* Safe by default: it binds 127.0.0.1. Any other address needs an access token (:func:`check_exposure`);
  with a token every request must carry it (``?token=`` in the URL, then a same-site cookie, or
  ``Authorization: Bearer``): none gives 401, a wrong one 403. Without a token only a loopback ``Host``
  header is served (a web page elsewhere cannot reach it by DNS rebinding).

The state is owned by the server's loop: other threads hand it changes with :meth:`CockpitServer.apply`
(a function of the state returning the keys it changed), which never blocks the caller.
"""

from __future__ import annotations

import asyncio
import contextlib
import gzip
import hashlib
import hmac
import ipaddress
import json
import math
import mimetypes
import os
import secrets
import socket
import threading
from collections.abc import Awaitable, Callable, Coroutine
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

from aiohttp import web

from bac_cockpit.state import CockpitState
from bac_common.errors import BacError

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8765
MIN_TOKEN_LENGTH = 16
COOKIE = "bac_cockpit_token"
HEARTBEAT_S = 10.0
CLIENT_QUEUE = 512
LOOPBACK_NAMES = ("localhost", "localhost.localdomain", "ip6-localhost")
# every script and style comes from this server; plotly sets inline styles on its elements
CSP = (
    "default-src 'none'; script-src 'self'; style-src 'self' 'unsafe-inline'; img-src 'self' data:; "
    "connect-src 'self'; font-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'"
)

StateFn = Callable[[CockpitState], list[str]]


class CockpitError(BacError):
    """The cockpit cannot serve as configured."""


def is_loopback(host: str) -> bool:
    h = host.strip().strip("[]")
    if h.lower() in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(h).is_loopback
    except ValueError:
        return False


def check_exposure(host: str, token: str) -> str:
    """The token the server must require for ``host``: '' on loopback without one; refused (CockpitError) for
    another address without a token of at least MIN_TOKEN_LENGTH characters. ``auto`` makes a random one."""
    tok = token.strip()
    if tok == "auto":
        tok = secrets.token_urlsafe(18)
    if not is_loopback(host) and not tok:
        raise CockpitError(
            f"refusing to serve the cockpit on {host}: another address than 127.0.0.1 reaches the car's network, "
            "so an access token is required (--token TOKEN of 16+ characters, or --token auto for a random one "
            "printed in the address; on a graph: -p cockpit.token:=auto)"
        )
    if tok and len(tok) < MIN_TOKEN_LENGTH:
        raise CockpitError(f"the access token is too short ({len(tok)} characters, at least {MIN_TOKEN_LENGTH})")
    return tok


def page_url(host: str, port: int, token: str = "") -> str:
    shown = host
    if host in ("0.0.0.0", "::", ""):  # every interface: name this machine
        shown = socket.gethostname()
    if ":" in shown and not shown.startswith("["):
        shown = f"[{shown}]"
    return f"http://{shown}:{port}/" + (f"?token={token}" if token else "")


def json_bytes(obj: Any) -> bytes:
    try:
        return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()
    except ValueError:  # a non-finite float slipped through: strict JSON has no NaN
        return json.dumps(_clean(obj), separators=(",", ":"), allow_nan=False).encode()


def _clean(v: Any) -> Any:
    if isinstance(v, float):
        return v if math.isfinite(v) else None
    if isinstance(v, dict):
        return {k: _clean(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_clean(x) for x in v]
    return v


# --- static files --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Asset:
    body: bytes
    gz: bytes | None
    content_type: str
    etag: str


def static_dir() -> Path:
    return Path(str(resources.files("bac_cockpit") / "static"))


def load_assets(folder: Path | None = None) -> dict[str, Asset]:
    """Every file of the page, in memory, the large ones gzipped once."""
    root = folder or static_dir()
    out: dict[str, Asset] = {}
    for p in sorted(root.rglob("*")):
        if not p.is_file() or p.name.startswith("."):
            continue
        rel = p.relative_to(root).as_posix()
        body = p.read_bytes()
        ctype = mimetypes.guess_type(p.name)[0] or "application/octet-stream"
        if ctype.startswith("text/") or ctype in ("application/javascript", "text/javascript"):
            ctype += "; charset=utf-8"
        gz = gzip.compress(body, 6) if len(body) > 4096 else None
        out[rel] = Asset(body, gz, ctype, '"' + hashlib.sha256(body).hexdigest()[:20] + '"')
    if "index.html" not in out:
        raise CockpitError(f"the cockpit's page is missing from {root}")
    return out


# --- live updates ----------------------------------------------------------------------------------------------


@dataclass(eq=False)
class _Client:
    queue: asyncio.Queue[bytes | None] = field(default_factory=lambda: asyncio.Queue(CLIENT_QUEUE))
    resync: bool = False


class Hub:
    """The state and the browsers following it (used in the server's loop only).

    Some parts change faster than anyone reads them (``/diagnostics`` at 10x real time: tens of messages a
    second): :meth:`apply` with ``throttle_s`` sends them at most that often (the latest state each time), so that
    they never crowd out what the driver must see.
    """

    def __init__(self, state: CockpitState) -> None:
        self.state = state
        self.clients: set[_Client] = set()
        self.on_change: list[Callable[[list[str]], None]] = []
        self._held: set[str] = set()
        self._last_sent: dict[str, float] = {}
        self._timer: asyncio.TimerHandle | None = None

    def apply(self, fn: StateFn, throttle_s: float = 0.0) -> list[str]:
        keys = fn(self.state)
        if keys and throttle_s > 0:
            loop = asyncio.get_running_loop()
            now = loop.time()
            group = ",".join(sorted(keys))
            if now - self._last_sent.get(group, -math.inf) < throttle_s:
                self._held.update(keys)
                if self._timer is None:
                    self._timer = loop.call_later(throttle_s, self._send_held)
                return keys
            self._last_sent[group] = now
        if keys:
            self.broadcast(keys)
            for cb in self.on_change:
                cb(keys)
        return keys

    def _send_held(self) -> None:
        self._timer = None
        keys, self._held = sorted(self._held), set()
        if keys:
            self._last_sent[",".join(keys)] = asyncio.get_running_loop().time()
            self.broadcast(keys)

    def broadcast(self, keys: list[str]) -> None:
        if not self.clients:
            return
        frame = b"event: patch\ndata: " + json_bytes(self.state.patch(keys)) + b"\n\n"
        for c in self.clients:
            try:
                c.queue.put_nowait(frame)
            except asyncio.QueueFull:  # a browser that stopped reading: it gets a whole snapshot when it reads again
                c.resync = True
                while not c.queue.empty():
                    c.queue.get_nowait()
                c.queue.put_nowait(None)

    def snapshot_frame(self) -> bytes:
        return b"event: snapshot\ndata: " + json_bytes(self.state.snapshot()) + b"\n\n"


# --- the app ------------------------------------------------------------------------------------------------------


def _host_of(request: web.Request) -> str:
    host = request.host or ""
    if host.startswith("["):
        return host[1 : host.index("]")] if "]" in host else host
    return host.rsplit(":", 1)[0] if host.count(":") == 1 else host


def make_app(
    hub: Hub, token: str, title: str = "bac cockpit", assets: dict[str, Asset] | None = None
) -> web.Application:
    files = assets if assets is not None else load_assets()

    @web.middleware
    async def guard(request: web.Request, handler: Callable[[web.Request], Awaitable[web.StreamResponse]]) -> Any:
        if token:
            given = request.query.get("token") or request.cookies.get(COOKIE) or ""
            auth = request.headers.get("Authorization", "")
            if not given and auth.lower().startswith("bearer "):
                given = auth[7:].strip()
            if not given:
                raise web.HTTPUnauthorized(
                    text="401: this cockpit needs its access token: open the address printed when it started "
                    "(…/?token=…)\n",
                    headers={"WWW-Authenticate": 'Bearer realm="bac cockpit"'},
                )
            if not hmac.compare_digest(given.encode(), token.encode()):
                raise web.HTTPForbidden(text="403: wrong access token\n")
        elif not is_loopback(_host_of(request)):
            raise web.HTTPForbidden(text="403: this cockpit serves 127.0.0.1 only (Host header refused)\n")
        resp = await handler(request)
        if token and request.query.get("token") and request.path == "/":
            resp.set_cookie(COOKIE, token, httponly=True, samesite="Strict", path="/")
        return resp

    async def on_prepare(request: web.Request, response: web.StreamResponse) -> None:
        response.headers.setdefault("Content-Security-Policy", CSP)
        response.headers.setdefault("X-Content-Type-Options", "nosniff")
        response.headers.setdefault("Referrer-Policy", "no-referrer")
        response.headers.setdefault("X-Frame-Options", "DENY")

    def asset_response(request: web.Request, name: str, cache: str) -> web.Response:
        a = files.get(name)
        if a is None:
            raise web.HTTPNotFound()
        if request.headers.get("If-None-Match") == a.etag:
            return web.Response(status=304, headers={"ETag": a.etag, "Cache-Control": cache})
        headers = {"ETag": a.etag, "Cache-Control": cache, "Vary": "Accept-Encoding"}
        body = a.body
        if a.gz is not None and "gzip" in request.headers.get("Accept-Encoding", ""):
            body = a.gz
            headers["Content-Encoding"] = "gzip"
        return web.Response(
            body=body,
            headers=headers,
            content_type=a.content_type.split(";")[0],
            charset="utf-8" if "charset" in a.content_type else None,
        )

    async def index(request: web.Request) -> web.Response:
        return asset_response(request, "index.html", "no-store")

    async def static(request: web.Request) -> web.Response:
        name = request.match_info["name"]
        if name == "index.html" or ".." in name.split("/"):
            raise web.HTTPNotFound()
        return asset_response(request, name, "max-age=3600")

    async def state(request: web.Request) -> web.Response:
        return web.Response(
            body=json_bytes(hub.state.snapshot()),
            content_type="application/json",
            headers={"Cache-Control": "no-store"},
        )

    async def events(request: web.Request) -> web.StreamResponse:
        resp = web.StreamResponse(
            headers={"Content-Type": "text/event-stream", "Cache-Control": "no-store", "X-Accel-Buffering": "no"}
        )
        await resp.prepare(request)
        client = _Client()
        hub.clients.add(client)
        try:
            await resp.write(b"retry: 1000\n\n" + hub.snapshot_frame())
            while True:
                try:
                    frame = await asyncio.wait_for(client.queue.get(), HEARTBEAT_S)
                except TimeoutError:
                    frame = b": ping\n\n"
                if frame is None or client.resync:
                    client.resync = False
                    frame = hub.snapshot_frame()
                await resp.write(frame)
        except (ConnectionResetError, asyncio.CancelledError):
            pass
        finally:
            hub.clients.discard(client)
        return resp

    async def health(request: web.Request) -> web.Response:
        return web.json_response({"ok": True, "version": hub.state.version, "mode": hub.state.mode, "title": title})

    app = web.Application(middlewares=[guard])
    app.on_response_prepare.append(on_prepare)
    app.router.add_get("/", index)
    app.router.add_get("/static/{name:.+}", static)
    app.router.add_get("/api/state", state)
    app.router.add_get("/api/health", health)
    app.router.add_get("/events", events)
    return app


# --- the thread ---------------------------------------------------------------------------------------------------


@dataclass
class Bound:
    """Where the server listens."""

    host: str = ""
    port: int = 0
    unix_socket: str = ""
    fallback_from: int = 0  # the port asked for, when it was taken and another was used


class CockpitServer:
    """The app in a thread of its own; :meth:`apply` hands it state changes from any thread."""

    def __init__(
        self,
        state: CockpitState,
        *,
        host: str = DEFAULT_HOST,
        port: int = DEFAULT_PORT,
        token: str = "",
        unix_socket: str = "",
        serve_tcp: bool = True,
        port_fallback: bool = True,
        title: str = "bac cockpit",
    ) -> None:
        self.token = check_exposure(host, token)
        self.hub = Hub(state)
        self.host = host
        self.port = int(port)
        self.unix_socket = unix_socket
        self.serve_tcp = serve_tcp
        self.port_fallback = port_fallback
        self.title = title
        self.bound = Bound()
        self.loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._runner: web.AppRunner | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._stop: asyncio.Event | None = None

    @property
    def url(self) -> str:
        if not self.bound.port:
            return ""
        return page_url(self.bound.host, self.bound.port, self.token)

    def start(self, timeout_s: float = 20.0) -> Bound:
        """Bind and serve; returns where (raises CockpitError when it cannot bind)."""
        assets = load_assets()
        self._thread = threading.Thread(target=self._run, args=(assets,), name="bac-cockpit-web", daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout_s):
            raise CockpitError(f"the cockpit's web server did not start within {timeout_s:g} s")
        if self._error is not None:
            raise CockpitError(f"the cockpit cannot listen: {self._error}") from self._error
        return self.bound

    def _run(self, assets: dict[str, Asset]) -> None:
        loop = asyncio.new_event_loop()
        self.loop = loop
        asyncio.set_event_loop(loop)
        try:
            loop.run_until_complete(self._serve(assets))
        except BaseException as exc:  # reported to start(); the thread ends
            if not self._ready.is_set():
                self._error = exc
                self._ready.set()
        finally:
            with contextlib.suppress(Exception):
                tasks = [t for t in asyncio.all_tasks(loop) if not t.done()]
                for t in tasks:  # the feed's journal poll and the like
                    t.cancel()
                loop.run_until_complete(asyncio.gather(*tasks, return_exceptions=True))
                loop.run_until_complete(loop.shutdown_asyncgens())
            loop.close()

    async def _serve(self, assets: dict[str, Asset]) -> None:
        self._stop = asyncio.Event()
        app = make_app(self.hub, self.token, self.title, assets)
        runner = web.AppRunner(app, access_log=None, handle_signals=False, shutdown_timeout=0.5)
        await runner.setup()
        self._runner = runner
        try:
            if self.serve_tcp:
                await self._bind_tcp(runner)
            if self.unix_socket:
                path = Path(self.unix_socket)
                with contextlib.suppress(FileNotFoundError):
                    path.unlink()
                await web.UnixSite(runner, str(path)).start()
                os.chmod(path, 0o600)
                self.bound.unix_socket = str(path)
        except BaseException:
            await runner.cleanup()
            raise
        self._ready.set()
        try:
            await self._stop.wait()
        finally:
            for c in list(self.hub.clients):
                with contextlib.suppress(asyncio.QueueFull):
                    c.queue.put_nowait(None)
            await runner.cleanup()

    async def _bind_tcp(self, runner: web.AppRunner) -> None:
        try:
            site = web.TCPSite(runner, self.host, self.port, reuse_address=True)
            await site.start()
        except OSError as exc:
            if not self.port_fallback or self.port == 0:
                raise
            site = web.TCPSite(runner, self.host, 0)
            await site.start()
            self.bound.fallback_from = self.port
            _ = exc
        ports = [a[1] for a in runner.addresses if isinstance(a, tuple) and len(a) >= 2]  # which port the OS gave
        self.bound.host = self.host
        self.bound.port = int(ports[0]) if ports else self.port

    # --- from other threads ---------------------------------------------------------------------------------
    def apply(self, fn: StateFn, throttle_s: float = 0.0) -> None:
        """Run ``fn(state)`` in the server's loop and send what it changed (never blocks the caller); with
        ``throttle_s`` at most that often."""
        loop = self.loop
        if loop is None or loop.is_closed():
            return
        with contextlib.suppress(RuntimeError):  # the loop is closing
            loop.call_soon_threadsafe(self.hub.apply, fn, throttle_s)

    def spawn(self, coro_fn: Callable[[], Coroutine[Any, Any, None]]) -> None:
        """Start a coroutine in the server's loop."""
        loop = self.loop
        if loop is None or loop.is_closed():
            return
        with contextlib.suppress(RuntimeError):
            loop.call_soon_threadsafe(lambda: loop.create_task(coro_fn()))

    def stop(self, timeout_s: float = 3.0) -> None:
        loop, stop = self.loop, self._stop
        if loop is not None and stop is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(stop.set)
        if self._thread is not None:
            self._thread.join(timeout_s)
        if self.unix_socket:
            with contextlib.suppress(OSError):
                Path(self.unix_socket).unlink()


__all__ = [
    "DEFAULT_HOST",
    "DEFAULT_PORT",
    "Bound",
    "CockpitError",
    "CockpitServer",
    "Hub",
    "check_exposure",
    "is_loopback",
    "load_assets",
    "make_app",
    "page_url",
]
