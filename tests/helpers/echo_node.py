"""A node that echoes every bac_msgs type back (for the cross-process round-trip test).

For each message type T it subscribes ``rt/in/T`` and republishes on
``rt/out/T``; it serves both bac_msgs services on ``rt/srv/<Service>`` and
answers with a response built from the request (see :func:`answer`).
"""

from __future__ import annotations

import sys

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

import bac_msgs.msg as M
import bac_msgs.srv as S

MSG_TYPES = ["Calibration", "Trial", "RunSegment", "RunScore"]
QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)


def answer_apply(req: S.ApplyCalibration.Request) -> S.ApplyCalibration.Response:
    res = S.ApplyCalibration.Response()
    res.success = True
    res.error_code = S.ApplyCalibration.Response.ERROR_NONE
    res.message = f"timeout {req.timeout_s}"
    res.applied = req.calibration
    res.attempts = len(req.calibration.names)
    res.latency_s = req.timeout_s / 2
    return res


def answer_read(_req: S.ReadCalibration.Request) -> S.ReadCalibration.Response:
    res = S.ReadCalibration.Response()
    res.success = True
    res.message = "echo"
    res.active.names = ["a", "b"]
    res.active.values = [1.5, -2.25]
    res.active.crc32 = 0xDEADBEEF
    return res


class Echo(Node):
    def __init__(self) -> None:
        super().__init__("echo")
        self.pubs = {}
        self.subs = []
        for t in MSG_TYPES:
            cls = getattr(M, t)
            pub = self.create_publisher(cls, f"rt/out/{t}", QOS)
            self.pubs[t] = pub
            self.subs.append(self.create_subscription(cls, f"rt/in/{t}", pub.publish, QOS))
        self.srv_apply = self.create_service(
            S.ApplyCalibration, "rt/srv/ApplyCalibration", lambda req, res: answer_apply(req)
        )
        self.srv_read = self.create_service(
            S.ReadCalibration, "rt/srv/ReadCalibration", lambda req, res: answer_read(req)
        )


def main() -> int:
    rclpy.init()
    node = Echo()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
