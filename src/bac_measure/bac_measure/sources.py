"""Any recording in: a bag (rosbag2 mcap/sqlite3, ROS 1) or an MDF file (MDF4 / MDF 3), as the same arrays.

The offline tools (``bac rescore``, ``imu_health``, ``bac replay``) read their input through :func:`read_source`,
so that a run recorded with INCA or CANape goes through the same pure cores as one recorded in a bag and gives
the same J. What the file is, is told by its first bytes, not its name.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from bac_measure.bagio import BagError, ImuArrays, OdomArrays, read_imu, read_odom
from bac_measure.mdfio import ChannelMap, is_mdf, read_mdf


@dataclass
class Source:
    path: Path
    kind: str  # "bag" or "mdf"
    imu: ImuArrays
    odom: OdomArrays | None
    notes: list[str] = field(default_factory=list)

    @property
    def what(self) -> str:
        if self.kind == "mdf":
            return f"MDF file {self.path.name}, IMU channels {self.imu.topic.removeprefix('mdf:')} ..."
        return f"IMU topic {self.imu.topic}"


def read_source(
    path: str | Path,
    imu_topic: str | None = None,
    odom_topic: str | None = None,
    channels: ChannelMap | None = None,
    need_odom: bool = False,
) -> Source:
    """The IMU (and odometry when there is some) of a bag or an MDF file.

    ``imu_topic``/``odom_topic`` choose topics of a bag, ``channels`` maps the channels of an MDF file (None:
    guessed from units and names). ``need_odom``: raise when there is no odometry (cutting runs needs it).
    """
    p = Path(path)
    if is_mdf(p):
        rec = read_mdf(p, channels, need_odom=need_odom)
        return Source(p, "mdf", rec.imu, rec.odom, list(rec.notes))
    if channels is not None and p.is_file():
        raise BagError(f"{p} is not an MDF file: a channel map applies to MDF recordings only")
    imu = read_imu(p, imu_topic)
    try:
        odom: OdomArrays | None = read_odom(p, odom_topic)
    except BagError:
        if odom_topic is not None or need_odom:
            raise
        odom = None
    return Source(p, "bag", imu, odom)
