"""Small nodes for launcher tests: they report what they see and can crash or finish on demand."""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path
from typing import Any

from bac_common.rosnode import BacNode, run_node


def _write_atomically(path: Path, text: str) -> None:
    """Write then rename: a test polling for the file never reads it half-written (an empty start.json was
    once read as invalid JSON under CI load)."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


class Reporter(BacNode):
    def __init__(self, **kwargs: Any) -> None:
        super().__init__("reporter", **kwargs)
        self.out_dir = Path(self.declare_str("out_dir", "/tmp", "where to write reports"))
        self.tag = self.declare_str("tag", "", "a value to report back")
        crash = self.declare_float("crash_after_s", -1.0, "raise after this long (wall), -1 = never")
        finish = self.declare_float("finish_after_s", -1.0, "finish(0) after this long (wall), -1 = never")
        self.can_interface = self.declare_str("can.interface", "", "CAN interface given by the launcher")
        busy = self.declare_float("busy_callback_s", -1.0, "a callback 0.1 s after start that runs this long")
        self.hang_on_destroy = self.declare_bool("hang_on_destroy", False, "destroy_node never returns")
        self.slow_destroy_s = self.declare_float("slow_destroy_s", 0.0, "destroy_node takes this long (a clean-up)")
        self.stop_exit_code = self.declare_int(
            "stop_exit_code", 0, "destroy_node ends the process with this code (a hard deadline's 1), 0 = no"
        )
        self._callback_done = False
        refuse = self.declare_str("refuse_start", "", "raise a BacError with this message in the constructor")
        if refuse:
            from bac_common.errors import BacError

            raise BacError(refuse)
        report = {
            "name": self.get_name(),
            "pid": os.getpid(),
            "tag": self.tag,
            "can_interface": self.can_interface,
            "discovery_range": os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE"),
            "netns": os.stat("/proc/self/ns/net").st_ino,
            "use_sim_time": self.get_parameter("use_sim_time").value,
        }
        _write_atomically(self.out_dir / f"{self.get_name()}.start.json", json.dumps(report))
        if crash >= 0:
            self._t1 = self.create_timer(crash, self._crash, clock=self._wall())
        if finish >= 0:
            self._t2 = self.create_timer(finish, lambda: self.finish(0), clock=self._wall())
        if busy >= 0:
            self._busy_s = busy
            self._t3 = self.create_timer(0.1, self._busy, clock=self._wall())

    def _wall(self) -> Any:
        from rclpy.clock import Clock, ClockType

        return Clock(clock_type=ClockType.STEADY_TIME)

    def _crash(self) -> None:
        raise RuntimeError("reporter crashed on purpose")

    def _busy(self) -> None:
        """A long callback (a score being computed as SIGINT arrives); it publishes a log line at its end."""
        self._t3.cancel()
        _write_atomically(self.out_dir / f"{self.get_name()}.busy.json", "{}")
        end = time.monotonic() + self._busy_s
        while time.monotonic() < end:
            time.sleep(0.01)
        self._callback_done = True
        self.get_logger().info("busy callback done")

    def cleanup_time_s(self) -> float:
        return self.slow_destroy_s  # the clean-up it takes beyond the default watchdog time

    def destroy_node(self) -> None:
        _write_atomically(self.out_dir / f"{self.get_name()}.destroying.json", "{}")
        time.sleep(self.slow_destroy_s)  # e.g. the ECU bridge retrying a baseline restore the ECU refuses
        report = {"callback_done": self._callback_done}
        _write_atomically(self.out_dir / f"{self.get_name()}.clean.json", json.dumps(report))
        if self.stop_exit_code:  # the process ended by its hard deadline while stopping (StopSignals: exit 1)
            os._exit(self.stop_exit_code)
        while self.hang_on_destroy:  # an rclpy clean-up that never returns
            time.sleep(0.05)
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return run_node(Reporter, args)


if __name__ == "__main__":
    sys.exit(main())
