"""Common core of uav-memory-maps: geometry, telemetry, tile grid and codec, message schemas.

Pure numpy/OpenCV; no network and no web code lives here.
"""
