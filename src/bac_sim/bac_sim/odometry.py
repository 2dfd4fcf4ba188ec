"""The simulated car's odometry as a standard source publishes it (REP 105), run after run.

The road is straight and lies along the x axis of the ``odom`` frame, whose origin is where the car
started its first run. A run publishes the pose of the car on the road (``x`` = where on the road it
is, from that origin; ``y = z = 0``, heading along +x) and its forward speed in ``base_link``
(``twist.linear.x``). Between two runs the driver comes back to the start and drives again: the way
back is not simulated (nothing is published meanwhile, as for the IMU), but it takes the time it
takes at ``way_back_speed_mps``, so the next run starts no earlier than that after the previous one
ended, where the car then is: the start of the next run. The pose never moves faster than the car
could have driven it; a segmenter sees a silence and then a new drive.

:class:`OdomTrack` keeps where the car is between runs; :meth:`OdomTrack.place` puts a run on the
track (when it may start, its poses).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from bac_sim.run import RunRecording

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class PlacedRun:
    """A run on the odometry track: its first sample's sim time and the pose x of each odometry sample."""

    t0: float  # sim time of the run's start (odometry and IMU times are t0 + the run's own times), s
    x: FloatArray  # (m,) pose.position.x in the odom frame, m
    way_back_m: float  # how far the car came back to this run's start (0 for the first run), m
    way_back_s: float  # how long that took at the way-back speed, s


class OdomTrack:
    """Where the simulated car is between runs (see the module doc)."""

    def __init__(self, way_back_speed_mps: float) -> None:
        if not (way_back_speed_mps > 0 and math.isfinite(way_back_speed_mps)):
            raise ValueError(f"the way-back speed must be > 0 m/s, got {way_back_speed_mps}")
        self.way_back_speed_mps = way_back_speed_mps
        self.origin_m: float | None = None  # road position of the odom frame's origin
        self.last: tuple[float, float] | None = None  # (sim time, x) of the last published pose

    def place(self, rec: RunRecording, earliest_t0: float) -> PlacedRun:
        """The run ``rec`` starting no earlier than ``earliest_t0`` (sim s), nor before the car is back."""
        if self.origin_m is None:
            self.origin_m = float(rec.start_m)
        x = (float(rec.start_m) - self.origin_m) + np.asarray(rec.distance, dtype=np.float64)
        t0 = earliest_t0
        back_m = back_s = 0.0
        if self.last is not None and x.size:
            t_last, x_last = self.last
            back_m = abs(x_last - float(x[0]))
            back_s = back_m / self.way_back_speed_mps
            t0 = max(t0, t_last + back_s)
        return PlacedRun(t0, x, back_m, back_s)

    def driven(self, t_last: float, x_last: float) -> None:
        """The run was published: its last pose was ``x_last`` at sim time ``t_last``."""
        self.last = (t_last, x_last)
