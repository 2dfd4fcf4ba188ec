"""The ECU bridge of bac: the CAN calibration protocol (DBC), a bounded apply/acknowledge transaction
and the ecu_bridge node.
"""
