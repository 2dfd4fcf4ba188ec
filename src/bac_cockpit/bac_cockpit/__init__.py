"""The calibration cockpit of bac: a live page for the engineer and the driver (the ``cockpit`` node,
``bac cockpit CAMPAIGN``), and the same in a terminal (``bac watch``).
"""
