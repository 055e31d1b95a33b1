"""GPS-space multi-object tracker with long-term re-identification (PAPER.md 3, DESIGN.md 1).

Tracks live on the ground in local east/north metres, so they survive turns, blur and looking away.
Arrays in, arrays out: no I/O (files and datasets are handled by `agent.tracking_io`).

Per frame with a pose (docs/tracking.md has the details and the measured effect of each step):

1. every active track is predicted with a constant-velocity Kalman filter (x, y, vx, vy) (`model`);
2. detections get ground points (turned about the UAV by the heading change the telemetry has
   not reported yet) and covariances from the viewing geometry: a heading error moves a point
   sideways by range * d_theta, a pitch error along the ray by slant^2 / h * d_beta (`model`);
3. leftovers of NMS (boxes overlapping a stronger one, or much weaker ones at the same ground spot)
   are set aside: the memory map boosts every box around a remembered object (`association`);
4. detections are assigned to tracks of their class with `scipy.optimize.linear_sum_assignment`
   on the negative log-likelihood of the ground distance (Mahalanobis gate), the detector's
   confidence and, while the camera is steady, the image overlap with the track's last box;
   confirmed tracks first, then tentative ones, then weak detections to confirmed tracks
   (`association`, `assignment`; appearance descriptors add a term when present: `appearance`);
5. free detections are matched to lost tracks remembered for `reid_horizon_s` (predicted with a
   damped, capped velocity; the gate grows with the time lost): a match gives the old id back; so
   does a young track whose id is not being reported when its detection matches a lost track (`reid`);
6. the rest start tentative tracks, confirmed after `confirm_hits` convincing detections; tracks
   following one object are merged; unmatched ones coast, then are lost (confirmed) or deleted
   (`lifecycle`).

Frames without a pose coast every track and match detections by image IoU with each track's last box.
`tracker.GpsTracker` runs the stages in this order on the tables of `state`; `config` holds the settings.
"""

from agent.tracking.config import DEFAULT_CLASS_MOTION, ClassMotion, TrackerConfig
from agent.tracking.state import EvidenceFn
from agent.tracking.tracker import GpsTracker, TrackOutput

__all__ = ["DEFAULT_CLASS_MOTION", "ClassMotion", "EvidenceFn", "GpsTracker", "TrackOutput", "TrackerConfig"]
