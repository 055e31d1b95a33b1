"""Video anomaly detection (paper section IV-C): per-frame heatmaps (`methods`, `autoencoder`, `registry`), the anomaly
layer of the memory map on the ground grid (`ground`), regions of interest per frame (`detector`) and the
frame readers of `uavmm anomaly` (`frames`). docs/anomaly.md.
"""

from agent.anomaly.detector import AnomalyConfig, AnomalyDetector, AnomalyFrame, extract_rois
from agent.anomaly.ground import ANOMALY_CLASS, AnomalyMap, AnomalyMapConfig
from agent.anomaly.methods import AnomalyMethod
from agent.anomaly.registry import ANOMALY_METHODS, DEFAULT_METHOD, make_method

__all__ = ["ANOMALY_CLASS", "ANOMALY_METHODS", "DEFAULT_METHOD", "AnomalyConfig", "AnomalyDetector", "AnomalyFrame",
           "AnomalyMap", "AnomalyMapConfig", "AnomalyMethod", "extract_rois", "make_method"]
