"""What keeps the cockpit's state current, beside the web server: the graph's messages (from the node's
callbacks, any thread), the campaign journal (read again when a trial changes state, and polled), and the GP
view (fitted in a worker process, at most one fit at a time, the newest wins).

Nothing here runs on the ROS executor: the node's callbacks convert a message and hand it over
(:meth:`CampaignFeed.trial` and co. return at once); the journal is read in a thread of the server's loop and
the model is fitted in a separate, lower-priority process, so a fit neither holds the node's GIL nor takes a
core from the graph before the graph's own nodes.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import logging
import math
import multiprocessing
import os
import signal
import time
from collections.abc import Callable, Iterator, Sequence
from multiprocessing import resource_tracker
from pathlib import Path
from typing import Any, TypeVar

from bac_cockpit.folder import FolderFacts, journal_path, read_bags, read_folder, speed_config
from bac_cockpit.model import GRID, compute_model
from bac_cockpit.server import CockpitServer
from bac_cockpit.state import (
    STATE_DONE,
    CalibrationView,
    CockpitState,
    DiagView,
    ScoreView,
    SegmentView,
    TrialView,
)

LOG = logging.getLogger("bac.cockpit")
T = TypeVar("T")
PR_SET_PDEATHSIG = 1
DIAGNOSTICS_EVERY_S = 0.5  # the health cards at most twice a second (/diagnostics runs on sim time: 10 Hz at 10x)
WORKER_NICE = 5  # below the graph's nodes, yet not starved on a busy machine


def _worker_init() -> None:  # pragma: no cover - runs in the worker process
    """The model worker: lower priority than the graph, deaf to the launcher's SIGINT, gone with its parent."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a SIGINT held back while it started is dropped now
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    with contextlib.suppress(OSError):
        os.nice(WORKER_NICE)
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    except (OSError, AttributeError):
        pass


def model_pool() -> concurrent.futures.ProcessPoolExecutor:
    """The GP view's worker pool: one process, spawned (never forked from a process with DDS threads) at its first
    task (:func:`start_in_worker`), lower priority than the graph (:func:`_worker_init`)."""
    return concurrent.futures.ProcessPoolExecutor(
        max_workers=1, mp_context=multiprocessing.get_context("spawn"), initializer=_worker_init
    )


@contextlib.contextmanager
def sigint_held() -> Iterator[None]:
    """SIGINT blocked in this thread meanwhile: a process started here starts with it blocked (a signal mask is
    inherited through fork and exec), so the launcher's stop, a SIGINT to the node's whole process group, cannot
    interrupt the model worker while it still imports its modules (its KeyboardInterrupt traceback in the node's
    log, the pool broken); :func:`_worker_init` ignores SIGINT, then unblocks it. Other threads still take it."""
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def start_in_worker(
    pool: concurrent.futures.ProcessPoolExecutor, fn: Callable[..., T], *args: Any
) -> concurrent.futures.Future[T]:
    """``pool.submit(fn, *args)``, a worker it starts for it starting with SIGINT blocked (:func:`sigint_held`).

    multiprocessing's resource tracker is made sure of first, outside the block: starting it unblocks SIGINT and
    SIGTERM in the calling thread, which would undo the block for the worker started after it (the pool's
    constructor starts it already; this keeps it so if that changes)."""
    resource_tracker.ensure_running()
    with sigint_held():
        return pool.submit(fn, *args)


def model_key(state: CockpitState) -> tuple[Any, ...]:
    """What the GP view depends on: the scored runs (the confirmation run too) and the recommendation."""
    runs = tuple((r.trial_id, r.j) for r in state.scored_rows(include_confirmation=True))
    rec = state.recommendation
    return runs, tuple(sorted((rec or {}).get("params", {}).items()))


def done_view(facts: FolderFacts, last: TrialView | None) -> TrialView | None:
    """The DONE state of a finished campaign from its journal (the bags may end before the agent's last word)."""
    rec = facts.recommendation
    if facts.ended != "done" or rec is None:
        return None
    params = dict(rec["params"])
    pj = rec.get("predicted_j")
    text = ", ".join(f"{k}={v:.4g}" for k, v in params.items())
    scored = [r for r in facts.rows if r.status == "scored" and r.kind != 2 and math.isfinite(r.j)]
    best = min(scored, key=lambda r: r.j) if scored else None
    return TrialView(
        campaign_id=str(facts.info.get("campaign_id", "")),
        trial_id=last.trial_id if last is not None else (facts.rows[-1].trial_id if facts.rows else 0),
        attempt=last.attempt if last is not None else 1,
        state=STATE_DONE,
        kind=last.kind if last is not None else 1,
        params=params,
        budget=int(facts.info.get("budget") or 0),
        trials_done=sum(1 for r in facts.rows if r.kind != 2 and r.status in ("scored", "failed")),
        last_j=last.last_j if last is not None else math.nan,
        best_j=best.j if best else math.nan,
        best_trial_id=best.trial_id if best else 0,
        predicted_j=float(pj) if pj is not None else math.nan,
        predicted_j_std=float(rec.get("predicted_std") or math.nan),
        instruction=f"Campaign done. Recommended calibration {text}"
        + (f" (predicted J={float(pj):.4g})." if pj is not None else ".")
        + " You can stop.",
        reason="",
        stamp_s=last.stamp_s if last is not None else 0.0,
    )


class CampaignFeed:
    """Feeds a :class:`CockpitServer`'s state from the graph and the campaign folder (see the module doc)."""

    def __init__(
        self,
        server: CockpitServer,
        campaign_dir: str | Path | None,
        *,
        model_grid: int = GRID,
        model_in_process: bool = True,
        poll_s: float = 1.0,
        follow_bags: bool = False,
        follow: bool = True,
    ) -> None:
        self.server = server
        self.dir = Path(campaign_dir) if campaign_dir else None
        self.model_grid = model_grid
        self.model_in_process = model_in_process
        self.poll_s = poll_s
        self.follow_bags = follow_bags
        self.follow = follow
        self._pool: concurrent.futures.ProcessPoolExecutor | None = None
        self._refreshing = False
        self._refresh_again = False
        self._computing = False
        self._model_key: tuple[Any, ...] | None = None
        self._journal_stamp: tuple[float, int] | None = None
        self._speed_done = False
        self._bags_read: set[str] = set()
        self._last_state: tuple[int, int, int] | None = None
        self.model_fits = 0
        self.model_seconds = 0.0  # the last fit's wall time
        self.model_seconds_total = 0.0
        self._closed = False

    # --- from the node's callbacks (any thread) ----------------------------------------------------------
    def trial(self, view: TrialView) -> None:
        wall = time.time()
        self.server.apply(lambda st: st.on_trial(view, wall))
        key = (view.trial_id, view.attempt, view.state)
        if key != self._last_state:
            self._last_state = key
            self.server.spawn(self.refresh)

    def segment(self, view: SegmentView) -> None:
        self.server.apply(lambda st: st.on_segment(view))

    def score(self, view: ScoreView) -> None:
        self.server.apply(lambda st: st.on_score(view))

    def calibration(self, view: CalibrationView) -> None:
        self.server.apply(lambda st: st.on_calibration(view))

    def diagnostics(self, views: Sequence[DiagView]) -> None:
        wall = time.time()
        self.server.apply(lambda st: st.on_diagnostics(views, wall), throttle_s=DIAGNOSTICS_EVERY_S)

    # --- in the server's loop ---------------------------------------------------------------------------------
    def start(self) -> None:
        if self.dir is not None:
            self.server.spawn(self._poll)

    async def _poll(self) -> None:
        if not self.follow:
            await self.refresh()
            return
        while not self._closed:
            stamp = self._stamp()
            if stamp != self._journal_stamp:
                await self.refresh()
            await asyncio.sleep(self.poll_s)

    def _stamp(self) -> tuple[float, int] | None:
        if self.dir is None:
            return None
        try:
            st = journal_path(self.dir).stat()
        except OSError:
            return None
        return st.st_mtime, st.st_size

    async def refresh(self) -> None:
        """Read the journal again and bring the trials, the recommendation and the GP view up to date."""
        if self.dir is None or self._closed:
            return
        if self._refreshing:
            self._refresh_again = True
            return
        self._refreshing = True
        try:
            while True:
                self._refresh_again = False
                self._journal_stamp = self._stamp()
                facts = await asyncio.to_thread(read_folder, self.dir)
                if facts is not None:
                    self._apply_facts(facts)
                if not self._speed_done:
                    sc = await asyncio.to_thread(speed_config, self.dir)
                    if sc is not None:
                        self._speed_done = True
                        target, mode, section = sc
                        self.server.hub.apply(lambda st: st.set_speed_config(target, mode, section))  # noqa: B023
                if self.follow_bags:
                    await self._read_new_bags(facts)
                self._maybe_fit()
                if not self._refresh_again:
                    break
        except Exception:  # a journal being written, a folder going away: logged, the next poll tries again
            LOG.exception("cockpit: reading the campaign folder %s failed", self.dir)
        finally:
            self._refreshing = False

    def _apply_facts(self, facts: FolderFacts) -> None:
        hub = self.server.hub
        hub.apply(lambda st: st.set_campaign_info(facts.info))
        hub.apply(lambda st: st.set_rows(facts.rows, facts.recommendation, facts.last_apply))
        st = hub.state
        if facts.ended == "done" and (st.trial is None or st.trial.state != STATE_DONE):
            # the journal says the campaign ended (its last bac/trial missed, or the agent long gone)
            done = done_view(facts, st.trial)
            if done is not None:
                hub.apply(lambda s: s.on_trial(done, time.time()))

    async def _read_new_bags(self, facts: FolderFacts | None) -> None:
        """Offline: the bags written since the last look (the newest is read again: it may have grown)."""
        assert self.dir is not None
        skip = set(self._bags_read)
        if skip:
            skip.discard(max(skip))
        rec = await asyncio.to_thread(read_bags, self.dir, skip)
        self._bags_read |= set(rec.bags)
        hub = self.server.hub

        def feed(st: CockpitState) -> list[str]:
            keys: list[str] = []
            for c in rec.calibrations:
                keys += st.on_calibration(c)
            for s in rec.scores:
                keys += st.on_score(s)
            for g in rec.segments:
                keys += st.on_segment(g)
            last = rec.last_trial
            if last is not None:
                keys += st.on_trial(last, time.time())
            done = done_view(facts, last or st.trial) if facts is not None else None
            if done is not None:
                keys += st.on_trial(done, time.time())
            return keys

        hub.apply(feed)

    def _maybe_fit(self) -> None:
        if self.dir is None or self._closed:
            return
        key = model_key(self.server.hub.state)
        if key == self._model_key or not key[0]:
            return
        if self._computing:
            return  # the fit in flight is followed by another when it ends (the key is looked at again)
        self._model_key = key
        self._computing = True
        self.server.spawn(self._fit)

    async def _fit(self) -> None:
        assert self.dir is not None
        t0 = time.monotonic()
        try:
            if self.model_in_process:
                # the worker starts here, at the first fit
                pool = self._model_pool()
                model = await asyncio.wrap_future(start_in_worker(pool, compute_model, str(self.dir), self.model_grid))
            else:
                model = await asyncio.to_thread(compute_model, str(self.dir), self.model_grid)
            self.model_fits += 1
            self.model_seconds = time.monotonic() - t0
            self.model_seconds_total += self.model_seconds
            model["fit_s"] = round(self.model_seconds, 3)
            self.server.hub.apply(lambda st: st.set_model(model))
        except concurrent.futures.process.BrokenProcessPool:
            self._pool = None  # the worker died (killed at shutdown?): a new one next time
            self._model_key = None
        except Exception:
            LOG.exception("cockpit: fitting the GP view failed")
        finally:
            self._computing = False
        if not self._closed:
            self._maybe_fit()

    def _model_pool(self) -> concurrent.futures.ProcessPoolExecutor:
        if self._pool is None:
            self._pool = model_pool()
        return self._pool

    def close(self) -> None:
        self._closed = True
        if self._pool is not None:
            # a fit in flight is not waited for: its worker is ended (the view dies with the node)
            workers = list((getattr(self._pool, "_processes", None) or {}).values())
            self._pool.shutdown(wait=False, cancel_futures=True)
            for w in workers:
                with contextlib.suppress(Exception):
                    w.terminate()
            self._pool = None
