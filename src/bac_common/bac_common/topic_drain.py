"""Read a high-rate topic in batches, as raw bytes, without one executor callback per message.

rclpy's executors pay a few hundred microseconds per callback: a
MultiThreadedExecutor tops out near 2,000 messages/s, so a 500 Hz IMU played
5x faster than real time loses a quarter of its samples (measured:
``docs/measurement.md``). A :class:`TopicDrain` owns its subscription on a
hidden helper node that no executor spins; the DDS reader keeps up to
``depth`` samples, and the owner's timer takes them all at once with
:meth:`take` (a few microseconds each) and decodes them vectorized
(:mod:`bac_common.cdr`). Topic remapping of the owner node applies: the topic is
resolved through it.
"""

from __future__ import annotations

import itertools
from typing import Any

import rclpy
from rclpy.node import Node
from rclpy.qos import QoSProfile

_COUNTER = itertools.count(1)


class TopicDrain:
    """A subscription whose messages are taken in batches by the owner (see the module docstring)."""

    def __init__(self, owner: Node, msg_type: Any, topic: str, qos: QoSProfile) -> None:
        self.topic = owner.resolve_topic_name(topic)
        name = f"_{owner.get_name()}_drain_{next(_COUNTER)}"  # a leading underscore hides it from node lists
        self._node = rclpy.create_node(
            name,
            context=owner.context,
            use_global_arguments=False,  # the launcher's __node:= remap must not rename it
            start_parameter_services=False,
            enable_rosout=False,
        )
        self._sub = self._node.create_subscription(msg_type, self.topic, lambda _m: None, qos, raw=True)

    def take(self, limit: int = 1_000_000) -> list[bytes]:
        """Every message received since the last call (at most ``limit``), oldest first, as CDR bytes."""
        out: list[bytes] = []
        sub = self._sub
        with sub.handle:
            while len(out) < limit:
                got = sub.handle.take_message(sub.msg_type, True)
                if got is None:
                    break
                out.append(got[0])
        return out

    def publisher_count(self) -> int:
        return int(self._sub.get_publisher_count()) if hasattr(self._sub, "get_publisher_count") else 0

    def destroy(self) -> None:
        self._node.destroy_node()
