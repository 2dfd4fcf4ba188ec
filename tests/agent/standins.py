"""Stand-ins for the agent's neighbours in integration tests, run as real processes.

    python standins.py bridge --ros-args -p fail_trials:=2 -p log_file:=/tmp/b.jsonl
    python standins.py chain  --ros-args -p invalid_runs:=1:1 -p log_file:=/tmp/c.jsonl

* ``bridge`` serves ecu_bridge/apply_calibration: success with the values echoed, except
  for the trial ids in ``fail_trials`` (comma list), answered with ERROR_ECU_OUT_OF_RANGE;
  and ecu_bridge/read_calibration. ``link_down_s``: for that long after start there is no CAN
  link (reads fail, applies answer ERROR_BUS); ``bus_down_trial`` / ``bus_down_applies``: the
  first applies of that trial answer ERROR_BUS (the link lost mid-campaign).
* ``chain`` plays the driver, the segmenter and the scorer: on each READY_TO_DRIVE it
  publishes, after ``delay_s`` (wall), a RunScore with the same (campaign, trial, attempt)
  and J = 1 + (x0 - 0.3)^2 + (x1 - 0.6)^2 of the calibration in the Trial message,
  invalid for the "trial:attempt" pairs in ``invalid_runs``.
Both append what they did to ``log_file`` (JSON lines, flushed).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

from rclpy.clock import Clock, ClockType

from bac_common.contracts import SRV_APPLY_CALIBRATION, SRV_READ_CALIBRATION, TOPIC_RUN_SCORE, TOPIC_TRIAL
from bac_common.rosnode import QOS_EVENTS, QOS_LATCHED, BacNode, run_node
from bac_msgs.msg import RunScore, Trial
from bac_msgs.srv import ApplyCalibration, ReadCalibration

NO_ADAPTER = "cannot open CAN interface socketcan:can0: No such device; is the adapter plugged in and 'can0' up?"


def known_j(values: list[float]) -> float:
    return 1.0 + (values[0] - 0.3) ** 2 + (values[1] - 0.6) ** 2


def known_peak(values: list[float]) -> float:
    """The stand-in's outcome besides J: soft front dampers shake more (8 at 0, 2 at 1)."""
    return 2.0 + 6.0 * (1.0 - values[0])


def _log(path: str, rec: dict[str, Any]) -> None:
    if path:
        with Path(path).open("a") as f:
            f.write(json.dumps(rec) + "\n")
            f.flush()


class FakeBridge(BacNode):
    def __init__(self, **kwargs: Any) -> None:
        super().__init__("ecu_bridge", **kwargs)
        self.fail = {int(x) for x in self.declare_str("fail_trials", "", "trial ids to refuse").split(",") if x}
        self.log_file = self.declare_str("log_file", "", "JSONL log of the requests")
        self.link_down_s = self.declare_float("link_down_s", 0.0, "no CAN link for this long after start (wall), s")
        self.bus_down_trial = self.declare_int("bus_down_trial", 0, "a trial whose first applies find the link down")
        self.bus_down_left = self.declare_int("bus_down_applies", 0, "how many applies of it answer ERROR_BUS")
        self.t0 = time.monotonic()
        self.srv = self.create_service(ApplyCalibration, SRV_APPLY_CALIBRATION, self._apply)
        self.read_srv = self.create_service(ReadCalibration, SRV_READ_CALIBRATION, self._read)

    def _link_down(self) -> bool:
        return time.monotonic() - self.t0 < self.link_down_s

    def _read(self, req: Any, res: Any) -> Any:
        res.success = not self._link_down()
        res.message = NO_ADAPTER if not res.success else ""
        _log(self.log_file, {"read": True, "trial_id": 0, "success": res.success})
        return res

    def _apply(self, req: Any, res: Any) -> Any:
        cal = req.calibration
        if self._link_down() or (cal.trial_id == self.bus_down_trial and self.bus_down_left > 0):
            if cal.trial_id == self.bus_down_trial:
                self.bus_down_left -= 1
            res.success = False
            res.error_code = ApplyCalibration.Response.ERROR_BUS
            res.message = NO_ADAPTER
            _log(self.log_file, {"trial_id": cal.trial_id, "values": list(cal.values), "success": False, "bus": True})
            return res
        ok = cal.trial_id not in self.fail
        res.success = ok
        res.error_code = 0 if ok else ApplyCalibration.Response.ERROR_ECU_OUT_OF_RANGE
        res.message = "" if ok else "ECU refuses a value as out of its range (stand-in refuses this trial)"
        res.attempts = 1
        res.latency_s = 0.01
        if ok:
            res.applied.trial_id = cal.trial_id
            res.applied.names = list(cal.names)
            res.applied.values = list(cal.values)
        _log(self.log_file, {"trial_id": cal.trial_id, "values": list(cal.values), "success": ok})
        return res


class FakeChain(BacNode):
    def __init__(self, **kwargs: Any) -> None:
        super().__init__("fake_chain", **kwargs)
        spec = self.declare_str("invalid_runs", "", "trial:attempt pairs scored invalid")
        self.invalid = {tuple(int(v) for v in x.split(":")) for x in spec.split(",") if x}
        self.delay = self.declare_float("delay_s", 0.2, "wall time from READY_TO_DRIVE to the score")
        self.log_file = self.declare_str("log_file", "", "JSONL log of the scores")
        self.seen: set[tuple[str, int, int]] = set()
        self.pub = self.create_publisher(RunScore, TOPIC_RUN_SCORE, QOS_EVENTS)
        self.sub = self.create_subscription(Trial, TOPIC_TRIAL, self._on_trial, QOS_LATCHED)
        self.timers_: list[Any] = []

    def _on_trial(self, t: Trial) -> None:
        key = (t.campaign_id, int(t.trial_id), int(t.attempt))
        if t.state != Trial.STATE_READY_TO_DRIVE or key in self.seen:
            return
        self.seen.add(key)
        values = list(t.calibration.values)
        holder: list[Any] = []

        def fire() -> None:
            holder[0].cancel()
            msg = RunScore()
            msg.campaign_id, msg.trial_id, msg.attempt = key
            valid = (key[1], key[2]) not in self.invalid
            msg.valid = valid
            msg.j = known_j(values) if valid else float("nan")
            msg.reason = "" if valid else "speed off target (stand-in)"
            msg.kpi = "rms"
            if valid:
                msg.outcome_names = ["peak_accel_z"]
                msg.outcome_values = [known_peak(values)]
            self.pub.publish(msg)
            _log(self.log_file, {"trial_id": key[1], "attempt": key[2], "valid": valid, "j": msg.j, "values": values})

        holder.append(self.create_timer(self.delay, fire, clock=Clock(clock_type=ClockType.STEADY_TIME)))
        self.timers_.append(holder[0])


if __name__ == "__main__":
    which = sys.argv.pop(1)
    sys.exit(run_node({"bridge": FakeBridge, "chain": FakeChain}[which], sys.argv))
