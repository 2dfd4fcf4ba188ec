"""What the offline tools do differently from the live nodes when they ingest a foreign recording.

A live node sees a stream as it comes; an offline tool (``imu_health``, ``bac rescore`` of a bag or an MDF file
that is not a bac campaign) has the whole recording, so, unless the user set the parameter with ``-p``:

* the health figures (rate, jitter, arrival jitter) cover the whole recording (``health_window: 0``), not the
  last 1000 steps;
* the standstill (mount and bias) is searched over the whole recording, not only its first
  ``standstill_timeout_s``, and without one the mount's roll and pitch come from the mean accelerometer over
  the whole recording;
* mount and bias come from a standstill (``OFFLINE_DEFAULTS``) unless a parameter file or ``-p`` says otherwise;
  the report says when there is none;
* the ingestion's output rate is kept at or below the recording's rate (upsampling would lower the RMS);
* an axis that sits flat at the recording's extreme (a clipped sensor) lowers ``accel_range`` / ``gyro_range`` to
  that level, so the clipped samples are saturated samples: holes, an invalid window, never a silent J.

A campaign rescored with its own configuration gets none of this: it must reproduce the live J.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

import numpy as np

from bac_imu.ingest import NS, Clipping, IngestConfig, find_clipping
from bac_measure.bagio import ImuArrays
from bac_measure.segmentation import SegmentConfig

# the nodes' defaults are the sim's (a configured mount); a foreign recording's mount is unknown
OFFLINE_DEFAULTS: dict[str, Any] = {"mount_source": "standstill", "bias_source": "standstill"}


def measured_rate(raw: ImuArrays) -> float:
    """1 / median stamp step of a recording (0 when it has fewer than 3 samples)."""
    if len(raw) < 3:
        return 0.0
    steps = np.diff(raw.stamp_ns)
    steps = steps[steps > 0]
    return NS / float(np.median(steps)) if steps.size else 0.0


def fit_rates(
    raw: ImuArrays,
    ing: IngestConfig,
    seg: SegmentConfig | None,
    user_ingest: Mapping[str, Any],
    user_segment: Mapping[str, Any],
    notes: list[str],
) -> tuple[IngestConfig, SegmentConfig | None]:
    """Keep the ingestion's output rate at or below the recording's rate, and the segmenter's equal to it,
    unless the user set them."""
    if len(raw) > 10:
        measured = measured_rate(raw)
        if measured > 0 and ing.output_rate_hz > measured * 1.01 and "output_rate_hz" not in user_ingest:
            notes.append(
                f"the recording is {measured:.1f} Hz: ingestion output {ing.output_rate_hz:g} -> {measured:.1f} Hz"
            )
            ing = dataclasses.replace(ing, output_rate_hz=round(measured, 6), input_rate_hz=0.0)
        elif (
            ing.input_rate_hz
            and abs(ing.input_rate_hz - measured) > 0.05 * measured
            and "input_rate_hz" not in user_ingest
        ):
            notes.append(f"the recording is {measured:.1f} Hz, not {ing.input_rate_hz:g} Hz: input rate measured")
            ing = dataclasses.replace(ing, input_rate_hz=0.0)
    if seg is not None and abs(seg.imu_rate_hz - ing.output_rate_hz) > 1e-9 and "imu_rate_hz" not in user_segment:
        seg = dataclasses.replace(seg, imu_rate_hz=ing.output_rate_hz)
    return ing, seg


def whole_recording(
    raw: ImuArrays, ing: IngestConfig, user_ingest: Mapping[str, Any], notes: list[str]
) -> tuple[IngestConfig, list[Clipping]]:
    """The whole-recording settings and the clipping check (see the module doc)."""
    changes: dict[str, Any] = {}
    if "health_window" not in user_ingest:
        changes["health_window"] = 0
    span = (int(raw.stamp_ns.max()) - int(raw.stamp_ns.min())) / NS if len(raw) else 0.0
    if "standstill_timeout_s" not in user_ingest and span > ing.standstill_timeout_s:
        changes["standstill_timeout_s"] = round(span + 1.0, 3)
    clips = find_clipping(raw.accel, raw.gyro)
    for prefix, key in (("accel", "accel_range"), ("gyro", "gyro_range")):
        levels = [abs(c.level) for c in clips if c.axis.startswith(prefix)]
        if not levels:
            continue
        level = min(levels)
        configured = float(getattr(ing, key))
        if configured == 0 or level < configured:
            changes[key] = level
            notes.append(
                f"{'; '.join(c.describe() for c in clips if c.axis.startswith(prefix))}: {key} taken as {level:.4g} "
                f"(configured {configured:g}), so the clipped samples count as saturated"
            )
    return (dataclasses.replace(ing, **changes) if changes else ing), clips
