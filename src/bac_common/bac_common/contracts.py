"""Names of the graph's topics and services (the node graph in README.md).

Topic names are relative, so a whole graph can be pushed into a namespace.
"""

from __future__ import annotations

# sensors (the IMU driver in the car, or vehicle_sim)
TOPIC_IMU_RAW = "imu/data_raw"  # sensor_msgs/Imu, sensor-data QoS, driver frame
TOPIC_IMU_VEHICLE = "imu/vehicle"  # sensor_msgs/Imu, vehicle frame, bias and gravity removed, fixed rate
TOPIC_ODOM = "vehicle/odom"  # nav_msgs/Odometry: twist.linear.x = speed (m/s), pose.position.x = distance (m)
TOPIC_CLOCK = "/clock"  # rosgraph_msgs/Clock (vehicle_sim, replay)
TOPIC_DIAGNOSTICS = "/diagnostics"  # diagnostic_msgs/DiagnosticArray

# algorithm 1
TOPIC_TRIAL = "bac/trial"  # bac_msgs/Trial, latched (transient local, depth 1)
TOPIC_RUN_SEGMENT = "bac/run_segment"  # bac_msgs/RunSegment, reliable
TOPIC_RUN_SCORE = "bac/run_score"  # bac_msgs/RunScore, reliable
TOPIC_CALIBRATION = "bac/calibration"  # bac_msgs/Calibration confirmed active by the ECU, latched

# the ECU bridge
SRV_APPLY_CALIBRATION = "ecu_bridge/apply_calibration"  # bac_msgs/srv/ApplyCalibration
SRV_READ_CALIBRATION = "ecu_bridge/read_calibration"  # bac_msgs/srv/ReadCalibration
SRV_RESTORE_BASELINE = "ecu_bridge/restore_baseline"  # std_srvs/srv/Trigger

# environment every ROS process of bac gets (README.md, "The network rule")
# the parameter through which bac launch tells a node which parameters the user set (-p, the profile's node
# parameters), "name=<JSON value>" each: the node checks them once made (bac_common.rosnode.BacNode)
USER_PARAMS = "bac_user_params"

ROS_ENV_DEFAULTS = {
    "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
    "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
}
