"""Pure-Python foundations shared by the bac packages: calibration definitions (parameter spaces, meta-
parameters), progress metrics and common errors.
"""
