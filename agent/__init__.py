"""The per-drone product: detection, memory map, joint detections, GPS tracking and the live agent.

docs/architecture.md maps each step to its module; nothing here imports sim/, benchmarks/ or uavmm/.
"""
