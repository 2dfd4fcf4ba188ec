"""IMU ingestion for bac: mounting rotation, bias and gravity removal, resampling and stream-health
diagnostics.
"""
