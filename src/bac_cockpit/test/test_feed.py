"""The feed: a campaign folder followed as it grows (the journal polled, the GP fitted in a worker process)."""

from __future__ import annotations

import concurrent.futures
import multiprocessing
import os
import signal
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from campaign_maker import make_campaign

from bac_cockpit.feed import CampaignFeed, _worker_init, sigint_held
from bac_cockpit.server import CockpitServer
from bac_cockpit.state import CockpitState


def wait(cond: Callable[[], Any], timeout: float = 60.0) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        v = cond()
        if v:
            return v
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {cond}")


@pytest.mark.slow
def test_a_growing_folder_is_followed_and_the_model_refitted_in_a_worker(tmp_path: Path) -> None:
    folder = tmp_path / "camp"
    make_campaign(folder, budget=6, stop_after=2)
    srv = CockpitServer(CockpitState("offline"), port=0)
    srv.start()
    feed = CampaignFeed(srv, folder, model_grid=11, poll_s=0.1, follow_bags=True)
    feed.start()
    try:
        st = srv.hub.state
        wait(lambda: st.model and st.model.get("n_runs") == 2)
        assert len(st.part("trials")) == 3 and st.part("recommendation") is None  # trial 3 proposed, not run
        make_campaign(folder, budget=6)  # the campaign goes on to its end (resumed from the journal)
        wait(lambda: st.trial is not None and st.part("trial")["state_name"] == "DONE")
        wait(lambda: st.model and st.model.get("n_runs") == 7)  # 6 trials and the confirmation run
        assert st.part("recommendation")["final"] is True
        assert st.part("trial")["headline"] == "CAMPAIGN DONE" and "Recommended calibration" in st.trial.instruction
        assert feed.model_fits >= 2 and st.model["fit_s"] > 0
    finally:
        feed.close()
        srv.stop()


def test_the_model_worker_cannot_be_interrupted_while_it_starts() -> None:
    """The launcher stops a node with SIGINT to its whole process group, the model worker included: one that
    lands while the worker still starts (before it ignores SIGINT) must not kill it (seen in CI logs: a
    KeyboardInterrupt traceback in the cockpit's log at every stop that came just after the first J)."""
    pool = concurrent.futures.ProcessPoolExecutor(
        max_workers=1, mp_context=multiprocessing.get_context("spawn"), initializer=_worker_init
    )
    try:
        with sigint_held():  # as CampaignFeed starts it
            fut = pool.submit(os.getpid)
        (worker,) = pool._processes.values()  # type: ignore[attr-defined]
        deadline = time.monotonic() + 60
        sent = 0
        while not fut.done() and time.monotonic() < deadline:  # SIGINT after SIGINT from its first instant on
            os.kill(worker.pid, signal.SIGINT)
            sent += 1
            concurrent.futures.wait([fut], timeout=0.005)
        assert fut.result(timeout=1) == worker.pid
        assert sent >= 2
        assert pool.submit(os.getpid).result(timeout=30) == worker.pid  # and it still works, deaf to SIGINT
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
    # the caller's own mask is back as it was: this thread still takes SIGINT
    assert signal.SIGINT not in signal.pthread_sigmask(signal.SIG_BLOCK, set())
