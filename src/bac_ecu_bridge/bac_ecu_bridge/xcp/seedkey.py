"""Seed & key for XCP resource unlocking, with the key algorithm pluggable.

An ECU that protects its calibration (resource CAL/PAG) answers GET_SEED with a
seed and accepts UNLOCK only with the key its manufacturer's algorithm derives
from it. The bridge takes the algorithm by name (``xcp.key_algorithm``):

* ``xor:<hex secret>``: key = seed XOR the secret repeated (the simulated ECU's; a bench ECU's);
* ``module.path:function``: any Python function ``f(resource: int, seed: bytes) -> bytes`` (wrap the
  supplier's seed & key DLL there, e.g. with ctypes: XCP seed & key DLLs export
  ``XCP_ComputeKeyFromSeed``);
* ``""``: no algorithm (an ECU that asks for one is then reported as locked).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable

from bac_ecu_bridge.errors import ProtocolConfigError

KeyAlgorithm = Callable[[int, bytes], bytes]

RESOURCE_CAL_PAG = 0x01
RESOURCE_DAQ = 0x04
RESOURCE_STIM = 0x08
RESOURCE_PGM = 0x10


def xor_algorithm(secret: bytes) -> KeyAlgorithm:
    if not secret:
        raise ProtocolConfigError("the xor key algorithm needs a non-empty secret")

    def key(resource: int, seed: bytes) -> bytes:
        return bytes(b ^ secret[(i + resource) % len(secret)] for i, b in enumerate(seed))

    return key


def load_key_algorithm(spec: str) -> KeyAlgorithm | None:
    """The algorithm named by ``spec`` (see the module doc); None for ``""``."""
    spec = spec.strip()
    if not spec:
        return None
    if spec.startswith("xor:"):
        try:
            return xor_algorithm(bytes.fromhex(spec[4:]))
        except ValueError as exc:
            raise ProtocolConfigError(f"key algorithm {spec!r}: the secret must be hex bytes ({exc})") from None
    module, _, name = spec.partition(":")
    if not module or not name:
        raise ProtocolConfigError(f"key algorithm {spec!r}: give 'xor:<hex>' or 'module.path:function'")
    try:
        fn = getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError) as exc:
        raise ProtocolConfigError(f"key algorithm {spec!r} cannot be loaded: {exc}") from None
    if not callable(fn):
        raise ProtocolConfigError(f"key algorithm {spec!r} is not a function")
    return fn  # type: ignore[no-any-return]
