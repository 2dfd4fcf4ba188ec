"""``bac replay`` takes ``-p node.param:=value`` and ``--params-file`` as ``bac launch`` does, and refuses a wrong
one before anything starts (exit 2, the reason on stderr)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from bac_bringup.tools import replay_main


def write_bag(path: Path, rate_hz: float, n: int = 60, topic: str = "/imu/data", bac: bool = False) -> Path:
    """A rosbag2 with sensor_msgs/Imu on ``topic`` at ``rate_hz`` (header stamps); ``bac``: a bac/trial too."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    from bac_measure.recording import bac_typestore

    store = bac_typestore()
    ty = store.types
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection(topic, "sensor_msgs/msg/Imu", typestore=store)
        for i in range(n):
            t = 1_000_000_000 + round(i * 1e9 / rate_hz)
            v = ty["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=9.81)
            cov = np.zeros(9)
            msg = ty["sensor_msgs/msg/Imu"](
                header=ty["std_msgs/msg/Header"](
                    stamp=ty["builtin_interfaces/msg/Time"](sec=t // 10**9, nanosec=t % 10**9), frame_id="imu"
                ),
                orientation=ty["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
                orientation_covariance=cov, angular_velocity=v, angular_velocity_covariance=cov,
                linear_acceleration=v, linear_acceleration_covariance=cov,
            )  # fmt: skip
            w.write(conn, t, bytes(store.serialize_cdr(msg, "sensor_msgs/msg/Imu")))
        if bac:
            tc = w.add_connection("/bac/trial", "bac_msgs/msg/Trial", typestore=store)
            from rclpy.serialization import serialize_message

            from bac_msgs.msg import Trial

            w.write(tc, 1_000_000_000, bytes(serialize_message(Trial(campaign_id="c", trial_id=1, attempt=1))))
    return path


@pytest.fixture
def bag(tmp_path: Path) -> Path:
    return write_bag(tmp_path / "some_bag", 400.0, topic="/imu/data_raw", bac=True)


class Graph:
    """run_graph replaced: the nodes' overrides as the launcher would pass them."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.params: dict[str, dict[str, Any]] = {}
        monkeypatch.setattr("bac_bringup.tools.run_graph", self.run)

    def run(self, profile: Any, single_process: bool = False) -> int:
        self.params = {n.name: dict(n.params) for n in profile.nodes}
        return 0


@pytest.fixture
def graph(monkeypatch: pytest.MonkeyPatch) -> Graph:
    return Graph(monkeypatch)


@pytest.mark.parametrize(
    ("args", "reason"),
    [
        (["-p", "nosuch.rate:=2"], "overrides for unknown nodes ['nosuch'] in profile 'replay'"),
        (["--params-file", "{tmp}/missing.yaml"], "--params-file {tmp}/missing.yaml: no such file"),
        (["--params-file", "{tmp}/flat.yaml"], "--params-file {tmp}/flat.yaml: not a ROS parameter file"),
    ],
)
def test_a_wrong_parameter_is_refused_before_the_graph_starts(
    bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], reason: str
) -> None:
    (tmp_path / "flat.yaml").write_text("rate: 2\n")
    argv = [str(bag), *(a.format(tmp=tmp_path) for a in args)]
    assert replay_main(argv) == 2
    assert f"bac replay: {reason.format(tmp=tmp_path)}" in capsys.readouterr().err


def test_a_malformed_assignment_is_a_usage_error(bag: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        replay_main([str(bag), "-p", "rate:=2"])
    assert exc.value.code == 2 and "expected node.param:=value, got 'rate:=2'" in capsys.readouterr().err


def test_a_param_wins_over_the_options_and_reaches_the_profile(bag: Path, graph: Graph) -> None:
    argv = [str(bag), "--rate", "3", "-p", "bag_player.rate:=7.5", "-p", "kpi_scorer.weight_pitch_rate:=0.0"]
    assert replay_main(argv) == 0
    seen = graph.params
    assert seen["bag_player"]["rate"] == 7.5 and seen["bag_player"]["bags"] == [str(bag.resolve())]
    assert seen["kpi_scorer"]["weight_pitch_rate"] == 0.0
    # bac's own bag: the profile's ingestion, untouched
    assert "input_rate_hz" not in seen["imu_ingest"] and "imu_rate_hz" not in seen["run_segmenter"]


MAP = ["--topic-map", "/imu/data:=imu/data_raw"]


def test_a_foreign_imu_sets_the_rates_the_user_did_not(
    tmp_path: Path, graph: Graph, capsys: pytest.CaptureFixture[str]
) -> None:
    b50 = write_bag(tmp_path / "b50", 50.0)
    assert replay_main([str(b50), *MAP]) == 0
    assert graph.params["imu_ingest"] == {"output_rate_hz": 50.0, "input_rate_hz": 0.0}
    assert graph.params["run_segmenter"] == {"imu_rate_hz": 50.0}
    assert "the IMU is 50.0 Hz" in capsys.readouterr().err
    # the topic map given as a -p works the same
    assert replay_main([str(b50), "-p", "bag_player.topic_map:=['/imu/data:=imu/data_raw']"]) == 0
    assert graph.params["run_segmenter"] == {"imu_rate_hz": 50.0}
    # a faster IMU than the profile's output: the output stays, the input is measured
    assert replay_main([str(write_bag(tmp_path / "b1k", 1000.0)), *MAP]) == 0
    assert graph.params["imu_ingest"] == {"input_rate_hz": 0.0} and graph.params["run_segmenter"]["imu_rate_hz"] == 200
    # what the user's params file sets is kept (the launcher's overrides file is read last: it would win)
    user = tmp_path / "user.yaml"
    user.write_text(yaml.safe_dump({"imu_ingest": {"ros__parameters": {"output_rate_hz": 25.0}},
                                    "run_segmenter": {"ros__parameters": {"imu_rate_hz": 25.0}}}))  # fmt: skip
    assert replay_main([str(b50), *MAP, "--params-file", str(user)]) == 0
    assert graph.params["imu_ingest"] == {"input_rate_hz": 0.0} and graph.params["run_segmenter"] == {}
    # a -p too, even one the node will refuse (its message, not a traceback here)
    assert replay_main([str(b50), *MAP, "-p", "imu_ingest.output_rate_hz:=fast"]) == 0
    assert graph.params["imu_ingest"]["output_rate_hz"] == "fast"
    assert graph.params["run_segmenter"] == {"imu_rate_hz": "fast"}


def test_replays_that_cannot_share_one_ingestion_are_refused(
    tmp_path: Path, bag: Path, graph: Graph, capsys: pytest.CaptureFixture[str]
) -> None:
    b50, b100 = write_bag(tmp_path / "b50", 50.0), write_bag(tmp_path / "b100", 100.0)
    assert replay_main([str(b50), str(b100), *MAP]) == 2
    assert "recordings of different IMU rates (b50 50.0 Hz, b100 100.0 Hz)" in capsys.readouterr().err
    assert replay_main([str(bag), str(b50), *MAP]) == 2
    assert "bac's campaign bags" in capsys.readouterr().err and graph.params == {}
    # nothing to play is refused before any node starts
    assert replay_main([str(b50)]) == 2
    err = capsys.readouterr().err
    assert "nothing to play:" in err and "--topic-map /imu/data:=imu/data_raw" in err and graph.params == {}
