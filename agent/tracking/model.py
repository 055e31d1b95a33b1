"""The motion and measurement model on the ground: a constant-velocity Kalman filter per track, and the
error of a georeferenced detection from the viewing geometry (heading, pitch, height and pixel errors).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from agent.tracking.config import ClassMotion, TrackerConfig

__all__ = ["FloatArray", "MotionModels", "ground_measurement_cov", "kalman_update", "mahalanobis2_and_logdet",
           "predict_constant_velocity", "sigma_max"]

FloatArray = NDArray[np.float64]


def ground_measurement_cov(
    rel_east_m: FloatArray, rel_north_m: FloatArray, height_m: float | FloatArray, focal_px: float, *,
    position_sigma_m: float, heading_sigma_deg: float, pitch_sigma_deg: float, height_sigma_m: float,
    pixel_sigma_px: float, max_sigma_m: float = math.inf,
) -> FloatArray:
    """Covariance of georeferenced ground points from the telemetry and pixel errors.

    Parameters
    ----------
    rel_east_m, rel_north_m : (N,) float
        Ground points relative to the point below the UAV, metres.
    height_m : float or (N,) float
        UAV height above the ground, metres (> 0); per point over a terrain (shared.terrain.effective_height_m).
    focal_px : float
        Focal length, pixels.
    position_sigma_m : float
        Isotropic error (GPS, anchor), metres.
    heading_sigma_deg, pitch_sigma_deg : float
        Heading and pitch errors, degrees: sideways error range * d_theta, along the ray
        slant^2 / h * d_beta.
    height_sigma_m : float
        Height error, metres: along the ray range / h * dh.
    pixel_sigma_px : float
        Pixel error of the anchor point: slant / f sideways, slant^2 / (h f) along the ray.
    max_sigma_m : float
        Cap of the sideways and along-ray standard deviations, metres.

    Returns
    -------
    (N, 2, 2) float64
        East/north covariance, square metres. A point right below the UAV uses north as its ray.
    """
    e = np.asarray(rel_east_m, dtype=np.float64).reshape(-1)
    n = np.asarray(rel_north_m, dtype=np.float64).reshape(-1)
    r = np.hypot(e, n)
    slant2 = r * r + height_m * height_m
    d_theta = math.radians(heading_sigma_deg)
    d_beta = math.radians(pitch_sigma_deg)
    px = pixel_sigma_px / focal_px
    side_var = (r * d_theta) ** 2 + slant2 * px * px
    along_var = (slant2 / height_m * d_beta) ** 2 + (r / height_m * height_sigma_m) ** 2 \
        + (slant2 / height_m * px) ** 2
    cap = max_sigma_m * max_sigma_m
    side_var = np.minimum(side_var, cap)
    along_var = np.minimum(along_var, cap)
    safe = r > 1e-9
    ue = np.where(safe, e / np.where(safe, r, 1.0), 0.0)
    un = np.where(safe, n / np.where(safe, r, 1.0), 1.0)
    cov = np.empty((len(e), 2, 2))
    pos_var = position_sigma_m * position_sigma_m
    cov[:, 0, 0] = pos_var + along_var * ue * ue + side_var * un * un
    cov[:, 1, 1] = pos_var + along_var * un * un + side_var * ue * ue
    cov[:, 0, 1] = cov[:, 1, 0] = (along_var - side_var) * ue * un
    return cov


def mahalanobis2_and_logdet(diff: FloatArray, cov: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Squared Mahalanobis distance and log-determinant for 2-D residuals.

    diff: (..., 2) residuals; cov: (..., 2, 2) symmetric positive definite covariances (broadcast).
    Returns d2 (...,) and logdet (...,) float64.
    """
    a, b, d = cov[..., 0, 0], cov[..., 0, 1], cov[..., 1, 1]
    det = np.maximum(a * d - b * b, 1e-12)
    x, y = diff[..., 0], diff[..., 1]
    return (d * x * x - 2.0 * b * x * y + a * y * y) / det, np.log(det)


def sigma_max(cov: FloatArray) -> FloatArray:
    """(N, 2, 2) covariances -> (N,) square root of the largest eigenvalue (the longest 1-sigma axis)."""
    a, b, d = cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1]
    return np.sqrt(np.maximum(0.5 * (a + d) + np.sqrt(0.25 * (a - d) ** 2 + b * b), 0.0))


def predict_constant_velocity(x: FloatArray, P: FloatArray, dt: float, accel_sigma_mps2: FloatArray) -> None:
    """Predict states dt seconds ahead in place (white-acceleration constant-velocity model).

    x (N, 4) east, north (m), v_east, v_north (m/s); P (N, 4, 4) their covariances; accel_sigma_mps2 (N,)
    process noise per row.
    """
    x[:, :2] += dt * x[:, 2:]
    # P <- F P F^T with F = [[I, dt I], [0, I]], written blockwise.
    pxx, pxv, pvv = P[:, :2, :2], P[:, :2, 2:], P[:, 2:, 2:]
    new_xx = pxx + dt * (pxv + pxv.transpose(0, 2, 1)) + dt * dt * pvv
    new_xv = pxv + dt * pvv
    q = accel_sigma_mps2 * accel_sigma_mps2
    eye = np.eye(2)
    P[:, :2, :2] = new_xx + (q * dt**4 / 4.0)[:, None, None] * eye
    P[:, :2, 2:] = new_xv + (q * dt**3 / 2.0)[:, None, None] * eye
    P[:, 2:, :2] = P[:, :2, 2:].transpose(0, 2, 1)
    P[:, 2:, 2:] = pvv + (q * dt * dt)[:, None, None] * eye


def kalman_update(x: FloatArray, P: FloatArray, z: FloatArray, R: FloatArray,
                  max_speed_mps: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Kalman update of states x (N, 4), P (N, 4, 4) with ground points z (N, 2), covariances R (N, 2, 2).

    The updated velocity is capped at max_speed_mps (N,). Returns new x and P (the inputs are not changed).
    """
    S = P[:, :2, :2] + R
    a, b, d = S[:, 0, 0], S[:, 0, 1], S[:, 1, 1]
    det = np.maximum(a * d - b * b, 1e-12)
    S_inv = np.empty_like(S)
    S_inv[:, 0, 0], S_inv[:, 1, 1] = d / det, a / det
    S_inv[:, 0, 1] = S_inv[:, 1, 0] = -b / det
    K = P[:, :, :2] @ S_inv  # (n, 4, 2)
    y = z - x[:, :2]
    x = x + np.einsum("nij,nj->ni", K, y)
    P = P - K @ P[:, :2, :]
    P = 0.5 * (P + P.transpose(0, 2, 1))
    speed = np.hypot(x[:, 2], x[:, 3])
    x[:, 2:] *= np.minimum(1.0, max_speed_mps / np.maximum(speed, 1e-9))[:, None]
    return x, P


class MotionModels:
    """Each class id's `ClassMotion` (looked up by class name in the config, cached) as per-row arrays.

    config: the tracker's configuration; class_names: class id -> name.
    """

    def __init__(self, config: TrackerConfig, class_names: dict[int, str]) -> None:
        self.config = config
        self.class_names = class_names
        self._cache: dict[int, ClassMotion] = {}

    def of(self, cid: int) -> ClassMotion:
        """The motion of class id cid."""
        m = self._cache.get(cid)
        if m is None:
            m = self.config.motion_for(self.class_names.get(cid))
            self._cache[cid] = m
        return m

    def accel_and_cap(self, cls: NDArray[np.int64]) -> tuple[FloatArray, FloatArray]:
        """(N,) class ids -> (N,) process noise (m/s^2) and (N,) speed cap (m/s)."""
        accel = np.empty(len(cls))
        cap = np.empty(len(cls))
        for cid in np.unique(cls):
            m = self.of(int(cid))
            sel = cls == cid
            accel[sel], cap[sel] = m.accel_sigma_mps2, m.max_speed_mps
        return accel, cap

    def reid_arrays(self, cls: NDArray[np.int64]) -> tuple[FloatArray, FloatArray, FloatArray]:
        """(N,) class ids -> speed cap (m/s), re-ID spread (m/s) and persistence (s) per row."""
        out = np.empty((3, len(cls)))
        for cid in np.unique(cls):
            m = self.of(int(cid))
            out[:, cls == cid] = np.array([[m.max_speed_mps], [m.reid_spread_mps], [m.persistence_s]])
        return out[0], out[1], out[2]

    def initial_velocity_cov(self, cls: NDArray[np.int64]) -> FloatArray:
        """(N,) class ids -> (N, 2, 2) velocity covariance of a new track: (cap / 2)^2 I."""
        _, cap = self.accel_and_cap(cls)
        return ((cap / 2.0) ** 2)[:, None, None] * np.eye(2)
