"""pyxcp, imported without its side effects on the process.

Importing ``pyxcp`` installs rich's pretty-printer as ``sys.displayhook`` and
rich's traceback handler, with local variables shown, as ``sys.excepthook``
(pyxcp/__init__.py). A calibration tool must not print the locals of every
frame of a crash (they can hold keys and seeds) nor change how a host
application prints: the hooks in force before the import are put back. pyxcp
writes no file when its master is built from the configuration objects, as
here (it reads and writes ``pyxcp_conf.py`` only through its command-line
application, which the bridge never starts); its loggers (``pyxcp.*``) carry
a NullHandler and propagate to the caller's logging, at CRITICAL unless the
application set a level (pyxcp logs each garbled frame it cannot place).
"""

from __future__ import annotations

import logging
import sys
import threading
from typing import Any

_LOCK = threading.Lock()
_LOADED: dict[str, Any] = {}


def load() -> dict[str, Any]:
    """pyxcp's pieces the bridge uses: Master, the configuration classes, types, the error matrix."""
    with _LOCK:
        if _LOADED:
            return _LOADED
        hooks = (sys.excepthook, sys.displayhook)
        try:
            import pyxcp  # noqa: F401  (the side effects happen here)
            from construct import ConstructError
            from pyxcp import types
            from pyxcp.config import General, Transport
            from pyxcp.errormatrix import ERROR_MATRIX, ERROR_TABLE, Action, PreAction
            from pyxcp.master.errorhandler import disable_error_handling
            from pyxcp.master.master import Master
            from pyxcp.transport.base import EmptyFrameError
            from traitlets.config import Config
        finally:
            sys.excepthook, sys.displayhook = hooks
        # pyxcp logs every frame it cannot place (an event packet too short, an unknown event code) at WARNING and
        # ERROR with tracebacks: on a noisy bus that drowns the console; the bridge counts them in its own
        # statistics (/diagnostics). A level set by the application is kept.
        pyxcp_logger = logging.getLogger("pyxcp")
        if pyxcp_logger.level == logging.NOTSET:
            pyxcp_logger.setLevel(logging.CRITICAL)
        # pyxcp's own error handler is a process-wide singleton whose "repeat infinite times" is unbounded: the
        # bridge runs XCP's error matrix itself, bounded and per client (bac_ecu_bridge.xcp.client)
        disable_error_handling(True)
        _LOADED.update(
            Master=Master,
            General=General,
            Transport=Transport,
            Config=Config,
            types=types,
            ERROR_MATRIX=ERROR_MATRIX,
            ERROR_TABLE=ERROR_TABLE,
            ConstructError=ConstructError,
            EmptyFrameError=EmptyFrameError,
            Action=Action,
            PreAction=PreAction,
        )
        return _LOADED
