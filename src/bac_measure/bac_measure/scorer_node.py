"""``kpi_scorer``: one ``bac/run_score`` for each ``bac/run_segment``, same (campaign, trial, attempt).

J and its parts come from :func:`bac_measure.kpi.score` (paper eq. 1 by default;
ISO 2631-1 Wk RMS or VDV by ``kpi``; per-term weights). An invalid segment
gives an invalid score carrying the segment's reason. A segment already scored
(the same triple again) is not scored twice. The KPI parameters are read-only:
a campaign's J must mean one thing.
"""

from __future__ import annotations

import sys
import traceback
from collections import OrderedDict
from dataclasses import replace
from typing import Any

from bac_common.contracts import TOPIC_RUN_SCORE, TOPIC_RUN_SEGMENT
from bac_common.node_params import ParamSpec, declare_config
from bac_common.rosnode import QOS_EVENTS, BacNode, run_node
from bac_measure.kpi import KpiConfig, score
from bac_measure.messages import score_to_msg, segment_from_msg
from bac_measure.segmentation import RunId, SegmentConfig, invalid_segment
from bac_msgs.msg import RunScore, RunSegment

KPI_PARAMS = {
    "kpi": ParamSpec(
        "the vertical term: rms (paper eq. 1), iso_wk_rms (ISO 2631-1 Wk-weighted RMS) or vdv",
        choices=("rms", "iso_wk_rms", "vdv"),
    ),
    "weight_accel_z": ParamSpec("weight of the vertical term, w_az", 0.0, 1e6),
    "weight_pitch_rate": ParamSpec("weight of RMS(pitch rate), w_q", 0.0, 1e6),
    "detrend": ParamSpec("remove each signal's mean over the window first (eq. 1 does not)"),
    "psd_segment_s": ParamSpec("Welch segment length, s", 0.05, 600.0),
    "psd_max_hz": ParamSpec("spectra kept up to this frequency, Hz", 0.1, 10_000.0),
    "max_rms_accel_z": ParamSpec("a run whose RMS a_z exceeds this is invalid (a unit error), m/s^2; 0: off", 0.0, 1e6),
    "max_rms_pitch_rate": ParamSpec(
        "a run whose RMS pitch rate exceeds this is invalid (a gyro in deg/s), rad/s; 0: no check", 0.0, 1e6
    ),
}
REMEMBERED = 10_000  # scored runs remembered to refuse duplicates


class KpiScorerNode(BacNode):
    def __init__(self, **kwargs: Any) -> None:
        super().__init__("kpi_scorer", **kwargs)
        self.config: KpiConfig = declare_config(self, KpiConfig, KPI_PARAMS)
        self.segment_config = SegmentConfig()
        self.scored: OrderedDict[tuple[str, int, int], float] = OrderedDict()
        self.pub = self.create_publisher(RunScore, TOPIC_RUN_SCORE, QOS_EVENTS)
        self.create_subscription(RunSegment, TOPIC_RUN_SEGMENT, self._on_segment, QOS_EVENTS)
        c = self.config
        self.get_logger().info(f"J = {c.weight_accel_z:g} * {c.kpi}(a_z) + {c.weight_pitch_rate:g} * RMS(pitch rate)")

    def _on_segment(self, msg: RunSegment) -> None:
        key = (str(msg.campaign_id), int(msg.trial_id), int(msg.attempt))
        if key in self.scored:
            self.get_logger().warning(f"segment of run {key} received again: already scored (J = {self.scored[key]})")
            return
        try:
            s = score(segment_from_msg(msg), self.config)
        except Exception as exc:  # a bug must cost one run, not the campaign
            self.get_logger().error(f"run {key}: scoring failed:\n{traceback.format_exc()}")
            stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            s = score(invalid_segment(self.segment_config, RunId(*key), stamp, "-"), self.config)
            s = replace(s, reason=f"internal error in the scoring ({type(exc).__name__}: {exc}); see the log")
        self.pub.publish(score_to_msg(s))
        self.scored[key] = s.j
        while len(self.scored) > REMEMBERED:
            self.scored.popitem(last=False)
        if s.valid:
            self.get_logger().info(
                f"run {key}: J = {s.j:.6f} (RMS a_z {s.rms_accel_z:.4f} m/s^2, "
                f"RMS pitch rate {s.rms_pitch_rate:.5f} rad/s)"
            )
        else:
            self.get_logger().warning(f"run {key}: no J: {s.reason}")


def main(args: list[str] | None = None) -> int:
    return run_node(KpiScorerNode, args)


if __name__ == "__main__":
    sys.exit(main())
