"""XCP on CAN for the ECU bridge: the memory layout of a calibration, the settings, the client (over pyxcp)."""
