"""A fault-injecting CAN bus: wrap any python-can bus to drop, corrupt, delay, duplicate and reorder frames.

:class:`FaultyBus` is a :class:`can.BusABC` around another bus. It works on
either side of the protocol (around the bridge's bus or the ECU's), on frames
sent, received or both, with given probabilities and a seed:

* ``drop``: the frame disappears;
* ``corrupt``: 1-4 random bits of the data flip, or (one time in four) every
  data byte after the first is replaced by random bytes, which the frame CRC-8
  misses one time in 256: the layers above must still never be fooled;
* ``duplicate``: the frame arrives twice;
* ``delay``: the frame arrives ``delay_s`` later at most (uniform), so after
  frames sent after it;
* ``reorder``: the frame is held back and released right after the next one;
* ``silent``: nothing passes at all (a dead or unplugged ECU);
* ``nack``: positive protocol responses (ACK by default, any with
  ``nack_ops``) are replaced by a well-formed negative response with this
  reason, with probability ``nack_p`` (an ECU that refuses).

Faults are applied to frames whose id is in ``ids`` and whose opcode (data
byte 1) is in ``ops`` (all when empty; e.g. ``drop=1,ops=ack`` loses every
acknowledgment). Counters
in :attr:`FaultyBus.counts` say what was done.

The same settings parse from a compact spec for command lines::

    drop=0.15,corrupt=0.15,duplicate=0.05,delay=0.05,delay_s=0.02,reorder=0.05,seed=7
    silent
    nack=busy            (nack_p defaults to 1)
    nack=crc_mismatch,nack_p=0.5,direction=send
"""

from __future__ import annotations

import heapq
import itertools
import random
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, fields, replace
from typing import Any, Literal

import can

from bac_ecu_bridge.errors import FrameError
from bac_ecu_bridge.protocol import RESPONSE_OFFSET, Nack, Op, Reason, decode, encode

Direction = Literal["send", "recv", "both"]

_REASON_ALIASES = {
    "range": Reason.OUT_OF_RANGE,
    "out_of_range": Reason.OUT_OF_RANGE,
    "unknown": Reason.UNKNOWN_PARAMETER,
    "unknown_parameter": Reason.UNKNOWN_PARAMETER,
    "busy": Reason.BUSY,
    "crc": Reason.CRC_MISMATCH,
    "crc_mismatch": Reason.CRC_MISMATCH,
    "sequence": Reason.SEQUENCE,
    "count": Reason.COUNT_MISMATCH,
    "count_mismatch": Reason.COUNT_MISMATCH,
    "malformed": Reason.MALFORMED,
}

_OP_ALIASES = {op.name.lower(): op for op in Op}


class FaultSpecError(ValueError):
    """A fault spec that cannot be parsed."""


@dataclass(frozen=True)
class FaultConfig:
    drop: float = 0.0
    corrupt: float = 0.0
    duplicate: float = 0.0
    delay: float = 0.0
    delay_s: float = 0.02
    reorder: float = 0.0
    reorder_hold_s: float = 0.05  # a held frame is released after this even if no other frame follows
    silent: bool = False
    nack: int | None = None  # a Reason
    nack_p: float = 1.0
    nack_ops: tuple[int, ...] = (int(Op.ACK),)
    direction: Direction = "both"
    ids: tuple[int, ...] = ()
    ops: tuple[int, ...] = ()  # only protocol frames with these opcodes (all frames when empty)
    seed: int | None = None

    def __post_init__(self) -> None:
        for name in ("drop", "corrupt", "duplicate", "delay", "reorder", "nack_p"):
            p = getattr(self, name)
            if not 0.0 <= p <= 1.0:
                raise FaultSpecError(f"fault probability {name}={p} must lie in [0, 1]")
        if self.drop + self.corrupt > 1.0:
            raise FaultSpecError("drop + corrupt must not exceed 1")
        if self.delay_s < 0 or self.reorder_hold_s < 0:
            raise FaultSpecError("delays must be >= 0")
        if self.direction not in ("send", "recv", "both"):
            raise FaultSpecError(f"direction must be send, recv or both, got {self.direction!r}")

    @property
    def any(self) -> bool:
        return bool(
            self.silent
            or self.nack is not None
            or self.drop
            or self.corrupt
            or self.duplicate
            or self.delay
            or self.reorder
        )

    @classmethod
    def parse(cls, spec: str) -> FaultConfig:
        """Parse ``key=value,...`` (see the module docstring); an empty spec means no fault."""
        kwargs: dict[str, Any] = {}
        names = {f.name for f in fields(cls)}
        for item in filter(None, (s.strip() for s in spec.split(","))):
            key, _, value = item.partition("=")
            key = key.strip().replace("-", "_")
            value = value.strip()
            if key not in names:
                raise FaultSpecError(f"unknown fault '{key}' in {spec!r}; known: {sorted(names)}")
            try:
                if key == "silent":
                    kwargs[key] = value.lower() not in ("0", "false", "no", "off")
                elif key == "nack":
                    kwargs[key] = (
                        int(_REASON_ALIASES[value.lower()]) if value.lower() in _REASON_ALIASES else int(value, 0)
                    )
                elif key in ("nack_ops", "ops"):
                    kwargs[key] = tuple(
                        int(_OP_ALIASES[v.lower()]) if v.lower() in _OP_ALIASES else int(v, 0) for v in value.split("+")
                    )
                elif key == "ids":
                    kwargs[key] = tuple(int(v, 0) for v in value.split("+"))
                elif key == "seed":
                    kwargs[key] = int(value)
                elif key == "direction":
                    kwargs[key] = value
                else:
                    kwargs[key] = float(value)
            except (ValueError, KeyError) as exc:
                raise FaultSpecError(f"bad value for fault '{key}': {value!r} ({exc})") from None
        return cls(**kwargs)


@dataclass
class FaultCounts:
    frames: int = 0
    dropped: int = 0
    corrupted: int = 0
    duplicated: int = 0
    delayed: int = 0
    reordered: int = 0
    nacked: int = 0
    by_direction: dict[str, int] = field(default_factory=dict)


class FaultyBus(can.BusABC):
    """A python-can bus that injects faults into the frames of another bus."""

    def __init__(
        self,
        inner: can.BusABC,
        config: FaultConfig,
        *,
        owns_inner: bool = True,
        clock: Callable[[], float] = time.monotonic,
        **kwargs: Any,
    ) -> None:
        self.inner = inner
        self.config = config
        self.owns_inner = owns_inner
        self.counts = FaultCounts()
        self._clock = clock
        self._rng = random.Random(config.seed)
        self._lock = threading.Lock()
        self._tie = itertools.count()
        # frames waiting to be sent / delivered: (due time, tie, message)
        self._tx_heap: list[tuple[float, int, can.Message]] = []
        self._rx_heap: list[tuple[float, int, can.Message]] = []
        self._tx_held: list[can.Message] = []  # reordered, released after the next frame
        self._rx_held: list[can.Message] = []
        self._tx_wake = threading.Condition(self._lock)
        self._tx_thread: threading.Thread | None = None
        self._closing = False
        self._ready = False
        self.channel_info = f"faulty({inner.channel_info})"
        super().__init__(channel=getattr(inner, "channel", None) or inner.channel_info, **kwargs)
        self._can_protocol = inner.protocol
        self._ready = True

    # --- decisions ----------------------------------------------------------------------------
    def _applies(self, msg: can.Message, direction: str) -> bool:
        cfg = self.config
        if cfg.direction not in ("both", direction):
            return False
        if cfg.ids and msg.arbitration_id not in cfg.ids:
            return False
        return not cfg.ops or (len(msg.data) > 1 and msg.data[1] in cfg.ops)

    def _corrupt(self, msg: can.Message) -> can.Message:
        """Flip 1-4 distinct bits, or (one time in four) replace bytes 1.. at random; never a no-op."""
        data = bytearray(msg.data)
        if not data:
            return msg
        original = bytes(data)
        if self._rng.random() < 0.25 and len(data) > 1:
            data[1:] = bytes(self._rng.randrange(256) for _ in range(len(data) - 1))
        else:
            for bit in self._rng.sample(range(8 * len(data)), min(self._rng.randint(1, 4), 8 * len(data))):
                data[bit // 8] ^= 1 << (bit % 8)
        if bytes(data) == original:
            data[-1] ^= 0x01
        return _copy(msg, bytes(data))

    def _nack(self, msg: can.Message) -> can.Message | None:
        cfg = self.config
        if cfg.nack is None:
            return None
        try:
            pdu = decode(msg.data)
        except FrameError:
            return None
        if int(pdu.op) not in cfg.nack_ops or self._rng.random() >= cfg.nack_p:
            return None
        index = getattr(pdu, "index", 0)
        return _copy(msg, encode(Nack(pdu.seq, int(pdu.op) - RESPONSE_OFFSET, cfg.nack, index)))

    def _fate(self, msg: can.Message, direction: str) -> list[tuple[float, can.Message]] | None:
        """What happens to one frame: None = dropped, else [(extra delay, message), ...]."""
        if not self._applies(msg, direction):
            return [(0.0, msg)]
        cfg = self.config
        self.counts.frames += 1
        self.counts.by_direction[direction] = self.counts.by_direction.get(direction, 0) + 1
        if cfg.silent:
            self.counts.dropped += 1
            return None
        nacked = self._nack(msg)
        if nacked is not None:
            self.counts.nacked += 1
            msg = nacked
        r = self._rng.random()
        if r < cfg.drop:
            self.counts.dropped += 1
            return None
        if r < cfg.drop + cfg.corrupt:
            self.counts.corrupted += 1
            msg = self._corrupt(msg)
        delay = 0.0
        if cfg.delay and self._rng.random() < cfg.delay:
            self.counts.delayed += 1
            delay = self._rng.uniform(0.0, cfg.delay_s)
        out = [(delay, msg)]
        if cfg.duplicate and self._rng.random() < cfg.duplicate:
            self.counts.duplicated += 1
            out.append((delay, _copy(msg, bytes(msg.data))))
        if cfg.reorder and self._rng.random() < cfg.reorder:
            self.counts.reordered += 1
            return [(-1.0, m) for _, m in out]  # -1: hold back until the next frame
        return out

    # --- sending ---------------------------------------------------------------------------------
    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        with self._lock:
            fate = self._fate(msg, "send")
            held = self._tx_held
            self._tx_held = []
            now_out: list[can.Message] = []
            if fate is not None:
                for delay, m in fate:
                    if delay < 0:
                        self._tx_held.append(m)
                        self._schedule_tx(self._clock() + self.config.reorder_hold_s, m)
                    elif delay > 0:
                        self._schedule_tx(self._clock() + delay, m)
                    else:
                        now_out.append(m)
            # a frame held back for reordering goes right after this one
            now_out.extend(m for m in held if self._unschedule_tx(m))
        for m in now_out:
            self.inner.send(m, timeout)

    def _schedule_tx(self, due: float, msg: can.Message) -> None:
        heapq.heappush(self._tx_heap, (due, next(self._tie), msg))
        if self._tx_thread is None:
            self._tx_thread = threading.Thread(target=self._tx_loop, name="faulty-bus-tx", daemon=True)
            self._tx_thread.start()
        self._tx_wake.notify()

    def _unschedule_tx(self, msg: can.Message) -> bool:
        for k, (_, _, m) in enumerate(self._tx_heap):
            if m is msg:
                self._tx_heap.pop(k)
                heapq.heapify(self._tx_heap)
                return True
        return False  # already sent by the timer

    def _tx_loop(self) -> None:
        while True:
            with self._lock:
                while not self._closing and (not self._tx_heap or self._tx_heap[0][0] > self._clock()):
                    wait = self._tx_heap[0][0] - self._clock() if self._tx_heap else None
                    self._tx_wake.wait(timeout=wait)
                if self._closing:
                    return
                _, _, msg = heapq.heappop(self._tx_heap)
                if msg in self._tx_held:
                    self._tx_held.remove(msg)
            try:
                self.inner.send(msg)
            except can.CanError:
                pass

    # --- receiving ------------------------------------------------------------------------------------
    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        start = self._clock()
        while True:
            now = self._clock()
            with self._lock:
                if self._rx_heap and self._rx_heap[0][0] <= now:
                    msg = heapq.heappop(self._rx_heap)[2]
                    if msg in self._rx_held:
                        self._rx_held.remove(msg)
                    return msg, False
                next_due = self._rx_heap[0][0] if self._rx_heap else None
            wait = None if timeout is None else max(0.0, timeout - (now - start))
            if next_due is not None:
                wait = max(0.0, next_due - now) if wait is None else min(wait, max(0.0, next_due - now))
            got = self.inner.recv(timeout=wait)
            if got is None:
                if next_due is not None and self._clock() >= next_due:
                    continue
                if timeout is not None and self._clock() - start >= timeout:
                    return None, False
                continue
            with self._lock:
                fate = self._fate(got, "recv")
                if fate is None:
                    continue
                t = self._clock()
                # frames held back for reordering are released right after this one
                for m in self._rx_held:
                    self._rx_push(t, m, replace_existing=True)
                self._rx_held = []
                first: can.Message | None = None
                for delay, m in fate:
                    if delay < 0:
                        self._rx_held.append(m)
                        self._rx_push(t + self.config.reorder_hold_s, m)
                    elif delay > 0:
                        self._rx_push(t + delay, m)
                    elif first is None:
                        first = m
                    else:
                        self._rx_push(t, m)
                if first is not None:
                    return first, False

    def _rx_push(self, due: float, msg: can.Message, replace_existing: bool = False) -> None:
        if replace_existing:
            for k, (_, _, m) in enumerate(self._rx_heap):
                if m is msg:
                    self._rx_heap.pop(k)
                    heapq.heapify(self._rx_heap)
                    break
        heapq.heappush(self._rx_heap, (due, next(self._tie), msg))

    # --- the rest of BusABC ---------------------------------------------------------------------------
    def _apply_filters(self, filters: Any) -> None:
        # forwarded to the wrapped bus (hardware filtering where it has some), once constructed:
        # the constructor's set_filters(None) must not clear filters set on the inner bus before
        if getattr(self, "_ready", False):
            self.inner.set_filters(filters)

    @property  # type: ignore[misc]
    def state(self) -> can.BusState:
        return self.inner.state

    def flush_tx_buffer(self) -> None:
        with self._lock:
            self._tx_heap.clear()
            self._tx_held.clear()
        self.inner.flush_tx_buffer()

    def shutdown(self) -> None:
        with self._lock:
            self._closing = True
            self._tx_wake.notify_all()
        if self._tx_thread is not None:
            self._tx_thread.join(timeout=1.0)
        super().shutdown()
        if self.owns_inner:
            self.inner.shutdown()

    def with_config(self, config: FaultConfig) -> None:
        """Change the faults at run time (e.g. make an ECU silent mid-test)."""
        with self._lock:
            self.config = config

    def set_silent(self, silent: bool) -> None:
        self.with_config(replace(self.config, silent=silent))


def _copy(msg: can.Message, data: bytes) -> can.Message:
    return can.Message(
        timestamp=msg.timestamp,
        arbitration_id=msg.arbitration_id,
        is_extended_id=msg.is_extended_id,
        is_remote_frame=msg.is_remote_frame,
        is_error_frame=msg.is_error_frame,
        channel=msg.channel,
        dlc=len(data),
        data=data,
        is_fd=msg.is_fd,
        is_rx=msg.is_rx,
    )
