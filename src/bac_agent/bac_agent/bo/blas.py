"""BLAS on one thread while the GP works (threadpoolctl), or nothing without it.

The GP works on many small matrices (tens to a few hundred rows). A multi-threaded OpenBLAS spends more time
synchronizing its threads than computing on them there, and on a busy 2-core machine it spins on descheduled
threads: one ask took 7 s instead of 0.09 s (bench/agent_latency.py, 2026-11-23), and a transfer source's fit
(64 points) 9 s instead of 0.05 s while other processes kept both cores busy (2026-11-25). The engine's ask and
recommendation and every GP fit run inside :func:`one_blas_thread`; nesting is harmless.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any


def _make_blas_limiter() -> Callable[[], Any]:
    try:
        from threadpoolctl import ThreadpoolController

        controller = ThreadpoolController()
    except Exception:  # threadpoolctl missing or unable to inspect the BLAS: leave it alone
        controller = None

    @contextmanager
    def limit() -> Iterator[None]:
        if controller is None:
            yield
            return
        with controller.limit(limits=1, user_api="blas"):
            yield

    return limit


one_blas_thread = _make_blas_limiter()
