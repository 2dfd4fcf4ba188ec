"""Conversions between the measurement chain's pure types and its messages (bac_msgs RunSegment, RunScore)."""

from __future__ import annotations

import numpy as np

from bac_measure.kpi import Score
from bac_measure.segmentation import RunId, Segment
from bac_msgs.msg import RunScore, RunSegment


def segment_to_msg(seg: Segment) -> RunSegment:
    """A segment as a bac_msgs/RunSegment."""
    m = RunSegment()
    m.header.stamp.sec = seg.window_start_ns // 1_000_000_000
    m.header.stamp.nanosec = seg.window_start_ns % 1_000_000_000
    m.header.frame_id = "base_link"
    m.campaign_id = seg.run.campaign_id
    m.trial_id = seg.run.trial_id
    m.attempt = seg.run.attempt
    m.mode = seg.mode
    m.window_start_s = seg.window_start_ns / 1e9
    m.window_length_s = float(seg.window_length_s)
    m.distance_start_m = float(seg.distance_start_m)
    m.distance_step_m = float(seg.distance_step_m)
    m.sample_rate_hz = float(seg.sample_rate_hz)
    m.lag_s = float(seg.lag_s)
    m.alignment_score = float(seg.alignment_score)
    m.mean_speed_mps = float(seg.mean_speed_mps)
    m.target_speed_mps = float(seg.target_speed_mps)
    m.coverage = float(seg.coverage)
    m.accel_z = np.asarray(seg.accel_z, dtype=np.float64)
    m.pitch_rate = np.asarray(seg.pitch_rate, dtype=np.float64)
    m.accel_z_pre_roll = np.asarray(seg.pre_roll_accel_z, dtype=np.float64)
    m.valid = bool(seg.valid)
    m.reason = seg.reason
    return m


def segment_from_msg(m: RunSegment) -> Segment:
    """A bac_msgs/RunSegment as a segment."""
    return Segment(
        run=RunId(str(m.campaign_id), int(m.trial_id), int(m.attempt)),
        mode=int(m.mode),
        window_start_ns=m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec,
        window_length_s=float(m.window_length_s),
        distance_start_m=float(m.distance_start_m),
        distance_step_m=float(m.distance_step_m),
        sample_rate_hz=float(m.sample_rate_hz),
        lag_s=float(m.lag_s),
        alignment_score=float(m.alignment_score),
        mean_speed_mps=float(m.mean_speed_mps),
        target_speed_mps=float(m.target_speed_mps),
        coverage=float(m.coverage),
        accel_z=np.array(m.accel_z, dtype=np.float64),
        pitch_rate=np.array(m.pitch_rate, dtype=np.float64),
        valid=bool(m.valid),
        reason=str(m.reason),
        # a bag recorded before the field existed has none
        pre_roll_accel_z=np.array(getattr(m, "accel_z_pre_roll", []), dtype=np.float64),
    )


def score_to_msg(s: Score) -> RunScore:
    """A score as a bac_msgs/RunScore."""
    m = RunScore()
    m.header.stamp.sec = s.window_start_ns // 1_000_000_000
    m.header.stamp.nanosec = s.window_start_ns % 1_000_000_000
    m.header.frame_id = "base_link"
    m.campaign_id = s.run.campaign_id
    m.trial_id = s.run.trial_id
    m.attempt = s.run.attempt
    m.j = float(s.j)
    m.rms_accel_z = float(s.rms_accel_z)
    m.rms_pitch_rate = float(s.rms_pitch_rate)
    m.weighted_rms_accel_z = float(s.weighted_rms_accel_z)
    m.vdv_accel_z = float(s.vdv_accel_z)
    m.kpi = s.kpi
    m.weight_accel_z = float(s.weight_accel_z)
    m.weight_pitch_rate = float(s.weight_pitch_rate)
    m.psd_frequency_hz = np.asarray(s.psd_frequency_hz, dtype=np.float64)
    m.psd_accel_z = np.asarray(s.psd_accel_z, dtype=np.float64)
    m.psd_pitch_rate = np.asarray(s.psd_pitch_rate, dtype=np.float64)
    m.outcome_names = [str(k) for k in s.outcomes]
    m.outcome_values = [float(v) for v in s.outcomes.values()]
    m.valid = bool(s.valid)
    m.reason = s.reason
    return m
