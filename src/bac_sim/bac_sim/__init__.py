"""Simulated vehicle for bac: a vectorized full-car model with semi-active dampers, roads, the
controllers under calibration, IMU and driver models, the simulated ECU on CAN and the vehicle_sim
node.
"""
