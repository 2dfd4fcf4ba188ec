"""The launcher-test Reporter in a module whose import loses the first SIGINT, as CPython can.

Python runs a signal's handler between two bytecodes wherever the main thread is; when that is a finalizer
(``__del__``) or a weakref callback, the handler's ``KeyboardInterrupt`` is printed as "Exception ignored" and
lost. Found in a node's first second (importlib's module-lock weakref callback, while the node imported numpy):
the node then started and spun on until the launcher's SIGTERM. Here a finalizer waits for the SIGINT, so that
it lands there every time; it says so by writing the file named by ``BAC_TEST_LOSSY_MARKER``.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path


class _FinalizerThatTakesTheSigint:
    def __del__(self) -> None:
        marker = os.environ.get("BAC_TEST_LOSSY_MARKER")
        if not marker:
            return
        Path(marker).write_text(str(os.getpid()))
        end = time.monotonic() + 60.0
        while time.monotonic() < end:  # the SIGINT's KeyboardInterrupt ends the loop, and is swallowed here
            time.sleep(0.01)


_FinalizerThatTakesTheSigint()  # finalized at once, while the module imports

from graph_nodes import Reporter  # noqa: E402

from bac_common.rosnode import run_node  # noqa: E402

__all__ = ["Reporter"]

if __name__ == "__main__":
    sys.exit(run_node(Reporter))
