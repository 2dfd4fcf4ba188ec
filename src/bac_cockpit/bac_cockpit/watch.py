"""``bac watch``: the cockpit in a terminal, for a laptop without a browser (rich, full screen).

    bac watch [TARGET] [--token TOKEN] [--once]

TARGET is a cockpit's address (default http://127.0.0.1:8765/), or a campaign folder: its live cockpit when
the graph runs (``<campaign>/cockpit.json``), else the folder itself, read offline and followed as it grows.
It shows the same state as the page: the driver's instruction in a coloured band, trial n of N, the target
speed, why a run was rejected, the trials with J and the best so far, the recommendation, the ECU link and the
IMU stream. ``--once`` prints one screen and exits (for scripts and logs).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import threading
import time
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from rich.console import Console, Group, RenderableType
from rich.panel import Panel
from rich.table import Table
from rich.text import Text

from bac_cockpit.server import DEFAULT_PORT

DEFAULT_URL = f"http://127.0.0.1:{DEFAULT_PORT}/"
TONES = {
    "go": "bold white on green4",
    "wait": "bold black on yellow3",
    "info": "bold white on blue3",
    "warn": "bold white on dark_orange3",
    "error": "bold white on red3",
    "done": "bold white on purple4",
    "idle": "bold white on grey35",
}
LEVELS = {"OK": "green", "WARN": "yellow", "ERROR": "red", "STALE": "grey50"}
SPARK = "▁▂▃▄▅▆▇█"


class WatchError(Exception):
    """The target cannot be watched."""


def _ok(x: Any) -> bool:
    return isinstance(x, int | float) and math.isfinite(x)


def fj(x: Any) -> str:
    return f"{x:.4f}" if _ok(x) else "–"


def fparams(p: Mapping[str, Any] | None) -> str:
    return "  ".join(f"{k}={v:.3g}" if _ok(v) else f"{k}=–" for k, v in (p or {}).items())


def sparkline(values: Sequence[float]) -> str:
    vals = [v for v in values if _ok(v)]
    if not vals:
        return ""
    lo, hi = min(vals), max(vals)
    span = hi - lo or 1.0
    return "".join(SPARK[min(len(SPARK) - 1, int((v - lo) / span * (len(SPARK) - 1) + 0.5))] for v in vals)


def render(s: Mapping[str, Any], source: str = "", connected: bool = True, max_rows: int = 12) -> RenderableType:
    """One screen of the cockpit from a state snapshot (the page's JSON)."""
    t = s.get("trial") or {"headline": "WAITING FOR THE CAMPAIGN", "tone": "idle", "state_name": "IDLE"}
    live = s.get("mode") != "offline"
    headline, tone, instruction = t.get("headline", ""), t.get("tone", "idle"), t.get("instruction", "")
    if live and not connected:
        headline, tone = "NO CONNECTION", "idle"
        instruction = "This view lost the cockpit: do not rely on it until it reconnects."
    parts: list[RenderableType] = []
    band = Text(f"\n{headline}\n", style=TONES.get(tone, TONES["idle"]), justify="center")
    parts.append(Panel(band, padding=(0, 1), style=TONES.get(tone, TONES["idle"])))
    if instruction:
        parts.append(Text(instruction, style="bold"))
    facts = []
    if t.get("state_name") == "DONE":
        facts.append(f"{t.get('trials_done')} of {t.get('budget')} trials done")
    elif t.get("confirmation"):
        facts.append("confirmation run")
    elif t.get("trial_id"):
        facts.append(f"trial {t.get('trial_id')} of {t.get('budget')}")
    if (t.get("attempt") or 0) > 1 and t.get("state_name") != "DONE":
        facts.append(f"run {t.get('attempt')}")
    sp = s.get("speed") or {}
    if _ok(sp.get("target_kmh")):
        facts.append(f"target speed {sp['target_kmh']:.0f} km/h")
    if _ok(sp.get("last_mean_kmh")):
        facts.append(f"last run {sp['last_mean_kmh']:.1f} km/h")
    if facts:
        parts.append(Text("  ·  ".join(facts)))
    if t.get("reason"):
        prefix = "last run rejected: " if t.get("state_name") == "READY_TO_DRIVE" else "why: "
        parts.append(Text(prefix + str(t["reason"]), style="bold dark_orange3"))

    rows = list(s.get("trials") or [])
    best = s.get("best") or {}
    scored = [r for r in rows if r.get("status") == "scored" and _ok(r.get("j")) and r.get("kind") != "confirmation"]
    table = Table(expand=True, show_edge=False, pad_edge=False, header_style="bold")
    for col, just in (
        ("trial", "right"),
        ("kind", "left"),
        ("calibration", "left"),
        ("J", "right"),
        ("runs", "right"),
        ("status", "left"),
    ):
        table.add_column(col, justify=just, no_wrap=col != "status")  # type: ignore[arg-type]
    for r in rows[-max_rows:]:
        rej = "; ".join(f"run {a}: {why}" for a, why in r.get("rejected") or [])
        status = (
            str(r.get("status", "")) + (f": {r['reason']}" if r.get("reason") else "") + (f" ({rej})" if rej else "")
        )
        style = (
            "bold green"
            if r.get("trial_id") == best.get("trial_id")
            else ("red" if r.get("status") == "failed" else "")
        )
        table.add_row(
            str(r.get("trial_id")),
            str(r.get("kind", "")),
            fparams(r.get("params")),
            fj(r.get("j")),
            str(r.get("attempts", "")),
            status,
            style=style,
        )
    title = f"trials ({len(scored)} scored)"
    if len(rows) > max_rows:
        title += f", the last {max_rows} of {len(rows)}"
    parts.append(Panel(table, title=title, title_align="left"))
    js = [float(r["j"]) for r in scored]
    lines = Text()
    if js:
        lines.append(f"J per trial {sparkline(js)}   best J {fj(best.get('j'))} (trial {best.get('trial_id')})\n")
    rec = s.get("recommendation") or (s.get("model") or {}).get("recommendation")
    if rec and rec.get("params"):
        final = bool(s.get("recommendation"))
        lines.append("recommendation: " if final else "model's current best: ", style="bold")
        lines.append(f"{fparams(rec['params'])}   predicted J {fj(rec.get('predicted_j'))}")
        if _ok(rec.get("predicted_std")):
            lines.append(f" ± {fj(2 * rec['predicted_std'])} (2σ)")
        lines.append("\n")
    ecu = s.get("ecu") or {}
    link = ecu.get("link")
    lines.append("ECU link  ", style="bold")
    if link:
        lines.append(f"{link['level']}: {link['message']}", style=LEVELS.get(link["level"], ""))
    else:
        lines.append("not recorded" if not live else "no diagnostics yet", style="grey50")
    la = ecu.get("last_apply")
    if la:
        lat = f", {1000 * la['latency_s']:.1f} ms" if _ok(la.get("latency_s")) else ""
        lines.append(
            f"   last apply {'confirmed' if la.get('success') else 'FAILED'} (trial {la.get('trial_id')}, "
            f"try {la.get('apply_try')}{lat})"
        )
    holds = ecu.get("holds")
    if holds:
        lines.append(f"   ECU holds trial {holds.get('trial_id')}: {fparams(holds.get('params'))}")
    lines.append("\n")
    imu = (s.get("imu") or {}).get("stream")
    lines.append("IMU       ", style="bold")
    if imu:
        lines.append(f"{imu['level']}: {imu['message']}", style=LEVELS.get(imu["level"], ""))
        v = imu.get("values") or {}
        if "gaps" in v:
            lines.append(f"   gaps {v.get('gaps')}, saturated {v.get('saturated')}")
    else:
        lines.append("not recorded" if not live else "no diagnostics yet", style="grey50")
    parts.append(lines)
    camp = s.get("campaign") or {}
    foot = f"{camp.get('campaign_id', 'no campaign yet')} · {source}"
    if live:
        foot += " · live" if connected else " · DISCONNECTED"
    parts.append(Text(foot + " · Ctrl-C quits", style="grey50"))
    return Group(*parts)


# --- sources ------------------------------------------------------------------------------------------------------


class HttpSource:
    """A running cockpit: its state, then its server-sent events (reconnecting)."""

    def __init__(self, url: str, token: str = "") -> None:
        parts = urllib.parse.urlsplit(url if "://" in url else "http://" + url)
        query = dict(urllib.parse.parse_qsl(parts.query))
        if token:
            query["token"] = token
        self.base = f"{parts.scheme}://{parts.netloc}"
        self.query = urllib.parse.urlencode(query)
        self.describe = self.base + "/"
        self.state: dict[str, Any] = {}
        self.connected = False
        self.version = 0
        self.error = ""
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="bac-watch", daemon=True)

    def _url(self, path: str) -> str:
        return f"{self.base}{path}" + (f"?{self.query}" if self.query else "")

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()

    def snapshot(self) -> dict[str, Any]:
        with self._lock:
            return dict(self.state)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self._stream()
            except urllib.error.HTTPError as exc:
                self.error = f"{exc.code}: {exc.read().decode(errors='replace').strip()}"
                if exc.code in (401, 403):
                    self.connected = False
                    return
            except (OSError, ValueError) as exc:
                self.error = str(exc)
            self.connected = False
            self._stop.wait(1.0)

    def _stream(self) -> None:
        req = urllib.request.Request(self._url("/events"), headers={"Accept": "text/event-stream"})
        with urllib.request.urlopen(req, timeout=30) as resp:  # a ping comes every 10 s
            event, data = "", []
            for raw in resp:
                if self._stop.is_set():
                    return
                line = raw.decode("utf-8", errors="replace").rstrip("\r\n")
                if line.startswith("event:"):
                    event = line[6:].strip()
                elif line.startswith("data:"):
                    data.append(line[5:].lstrip())
                elif not line:
                    if data and event in ("snapshot", "patch"):
                        d = json.loads("\n".join(data))
                        with self._lock:
                            if event == "snapshot":
                                self.state = d
                            else:
                                self.state.update(d)
                            self.version += 1
                        self.connected = True
                        self.error = ""
                    event, data = "", []


class FolderSource:
    """A campaign folder read offline (no graph), followed as it grows."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.describe = str(folder)
        self.connected = True
        self.version = 0
        self.error = ""
        self.state: dict[str, Any] = {}
        self._stamp: tuple[float, int] | None = None

    def start(self) -> None:
        self.poll()

    def stop(self) -> None:
        return

    def poll(self) -> None:
        from bac_cockpit.feed import done_view
        from bac_cockpit.folder import journal_path, read_bags, read_folder, speed_config, why_no_campaign
        from bac_cockpit.state import CockpitState

        try:
            st = journal_path(self.folder).stat()
        except OSError as exc:
            self.error = str(exc)
            return
        stamp = (st.st_mtime, st.st_size)
        if stamp == self._stamp:
            return
        self._stamp = stamp
        facts = read_folder(self.folder)
        if facts is None:
            self.error = why_no_campaign(self.folder)
            return
        state = CockpitState("offline")
        state.set_campaign_info(facts.info)
        sc = speed_config(self.folder)
        if sc is not None:
            state.set_speed_config(*sc)
        rec = read_bags(self.folder)
        for c in rec.calibrations:
            state.on_calibration(c)
        for g in rec.segments:
            state.on_segment(g)
        state.set_rows(facts.rows, facts.recommendation, facts.last_apply)
        last = rec.last_trial
        if last is not None:
            state.on_trial(last)
        done = done_view(facts, last)
        if done is not None:
            state.on_trial(done)
        self.state = state.snapshot()
        self.version += 1

    def snapshot(self) -> dict[str, Any]:
        self.poll()
        return dict(self.state)


def open_source(target: str, token: str = "") -> HttpSource | FolderSource:
    if "://" in target:
        return HttpSource(target, token)
    p = Path(target).expanduser()
    if p.is_dir():
        addr = p / "cockpit.json"
        if addr.exists():
            try:
                url = str(json.loads(addr.read_text())["url"])
                req = urllib.request.Request(HttpSource(url, token)._url("/api/health"))
                with urllib.request.urlopen(req, timeout=2):
                    return HttpSource(url, token)
            except (OSError, ValueError, KeyError):
                pass  # a cockpit.json left by a graph that stopped: the folder itself
        return FolderSource(p.resolve())
    if ":" in target:  # host:port
        return HttpSource(target, token)
    raise WatchError(f"{target} is neither a cockpit's address nor a campaign folder")


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="bac watch", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "target", nargs="?", default=DEFAULT_URL, help=f"cockpit address or campaign folder ({DEFAULT_URL})"
    )
    ap.add_argument("--token", default="", help="the cockpit's access token (when it was started with one)")
    ap.add_argument("--once", action="store_true", help="print one screen and exit")
    ap.add_argument("--timeout", type=float, default=15.0, help="--once: wait this long for the state, s")
    args = ap.parse_args(list(sys.argv[1:] if argv is None else argv))
    console = Console()
    try:
        src = open_source(args.target, args.token)
    except WatchError as exc:
        console.print(f"bac watch: {exc}", style="red")
        return 2
    src.start()
    try:
        if args.once:
            deadline = time.monotonic() + args.timeout
            while not src.snapshot() and time.monotonic() < deadline:
                if isinstance(src, HttpSource) and src.error.startswith(("401", "403")):
                    break
                time.sleep(0.05)
            snap = src.snapshot()
            if not snap:
                console.print(
                    f"bac watch: no state from {src.describe}: {src.error or 'nothing received'}", style="red"
                )
                return 1
            console.print(render(snap, src.describe, src.connected))
            return 0
        from rich.live import Live

        with Live(
            render(src.snapshot(), src.describe, src.connected), console=console, screen=True, auto_refresh=False
        ) as live:
            shown = -1
            last_draw = 0.0
            while True:
                if src.version != shown or time.monotonic() - last_draw > 1.0:
                    shown = src.version
                    last_draw = time.monotonic()
                    rows = max(4, console.size.height - 22)
                    live.update(render(src.snapshot(), src.describe, src.connected, rows), refresh=True)
                time.sleep(0.1)
    except KeyboardInterrupt:
        return 0
    finally:
        src.stop()


if __name__ == "__main__":
    sys.exit(main())
