"""uavmm package."""
