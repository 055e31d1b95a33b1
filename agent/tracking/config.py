"""Tracker parameters: how each class moves, and the thresholds, gates and weights of every stage.

Metres, seconds and degrees throughout, so a configuration holds across frame rates and cameras.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field, fields
from typing import Any

__all__ = ["DEFAULT_CLASS_MOTION", "ClassMotion", "TrackerConfig"]


@dataclass(frozen=True, slots=True)
class ClassMotion:
    """How objects of one class move.

    Attributes
    ----------
    accel_sigma_mps2 : float
        White-acceleration process noise of the Kalman filter, m/s^2.
    max_speed_mps : float
        Speed cap of the filter's velocity and of a lost track's predicted motion, m/s.
    reid_spread_mps : float
        Growth of a lost track's position uncertainty (1 sigma) per second lost, m/s.
    persistence_s : float
        How long the class keeps its velocity (time constant of the exponential damping of a lost
        track's velocity), s: the predicted displacement after dt is v * tau * (1 - exp(-dt / tau)).
        Walkers keep their direction for several seconds; swimmers drift with the current.
    """

    accel_sigma_mps2: float = 1.0
    max_speed_mps: float = 3.0
    reid_spread_mps: float = 0.6
    persistence_s: float = 3.0

    def __post_init__(self) -> None:
        for name in ("accel_sigma_mps2", "max_speed_mps", "reid_spread_mps", "persistence_s"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
                raise ValueError(f"ClassMotion.{name}={value!r} must be a finite number > 0")


#: Built-in motion per class name: people walk (1.2-1.5 m/s, sudden turns), swimmers drift slowly. The person's
#: reid_spread_mps 0.8 (1.0 until 29 Nov 2026): +0.25 mean HOTA on the five grass re-ID tuning domains, seeds 0-5,
#: up in both seed halves; held out +0.4 / 0.0 (docs/tracking.md).
DEFAULT_CLASS_MOTION: tuple[tuple[str, ClassMotion], ...] = (
    ("person", ClassMotion(accel_sigma_mps2=1.0, max_speed_mps=3.0, reid_spread_mps=0.8, persistence_s=1.5)),
    ("swimmer", ClassMotion(accel_sigma_mps2=0.3, max_speed_mps=1.5, reid_spread_mps=0.25, persistence_s=20.0)),
    ("boat", ClassMotion(accel_sigma_mps2=1.5, max_speed_mps=15.0, reid_spread_mps=2.0, persistence_s=10.0)),
)


#: How the image cue compares a track's expected box with a detection's (TrackerConfig.image_overlap).
IMAGE_OVERLAPS = ("iou", "giou")


#: Windows (seconds) of TrackerConfig floored to this many frame intervals (`TrackerConfig.at_frame_interval`).
FRAME_FLOORS: dict[str, float] = {"tentative_coast_s": 1.5, "max_coast_s": 2.5, "image_max_age_s": 1.5,
                                  "merge_after_s": 1.5}


@dataclass(frozen=True, slots=True)
class TrackerConfig:
    """Tracker parameters, in metres, seconds and degrees (frame-rate independent).

    Defaults: the best measured on the simulator (docs/tracking.md). "Boosted" scores are the
    pipeline's (c + memory, may exceed 1), "raw" ones the detector's own (`FrameResult.raw_scores`).

    Track life
    ----------
    match_score : float
        Boosted score from which a detection is associated first (to every active track).
    low_score : float
        Weaker detections down to this boosted score may still update a confirmed track left over
        (a blurred or partly hidden object); they never start or revive tracks.
    birth_score, reid_score : float
        Score from which a free detection starts a tentative track, or revives a lost one.
    birth_on_raw : bool
        Judge birth_score and reid_score on the raw score: the memory map lifts every box near a
        remembered spot (persistent clutter too) to about 1 + c, so a new or returning track should
        rest on a convincing detection; boosted scores then keep it.
    confirm_hits, confirm_score : int, float
        A tentative track is confirmed after confirm_hits matches with a raw score >= confirm_score,
        within confirm_window_s of its birth (else deleted).
    confirm_window_s, tentative_coast_s, max_coast_s : float
        Seconds: see confirm_hits; a tentative track unmatched for tentative_coast_s is deleted; a
        confirmed one unmatched for max_coast_s is lost (goes to the re-ID memory).
    exit_margin_px, exit_coast_s : float
        A confirmed track whose last box came within exit_margin_px pixels of the image border and
        that has then been unmatched for more than exit_coast_s seconds (0: one frame) has left the
        view: it goes to the re-ID memory at once instead of coasting for max_coast_s. A coasting
        track of an object that left used to take a neighbour's detection near the border while the
        gimbal turned faster than the telemetry showed (an exit swap); a negative margin disables it.
    exit_expected : bool
        The border test takes the track's expected box (its last box moved by its image velocity,
        `image_velocity`) instead of its last box: in a sweep every box streams out of the view at 50-70 px
        a frame, and an object last seen 100 px inside the border has left two frames later (its coasting
        track took the next object reaching the border).

    Association
    -----------
    gate_chi2, max_gate_m : float
        Mahalanobis gate (squared; 9.21 = 99 % for 2 dof) and hard cap (metres) of track-detection
        pairs.
    score_weight : float
        Weight of -ln(raw score) in the pair cost (the negative log-likelihood of the ground
        distance): among detections near a track, the detector's best box wins, not a leftover.
    pair_max_cost : float or None
        A pair costing more (d2 + ln(|S| / |R|) + score and image terms) is not worth making: a track
        and a detection may both stay unassigned, so the assignment does not trade one good pair for
        two poor ones (None: as many pairs as the gate allows, like plain linear_sum_assignment).
    image_weight, image_max_age_s, image_max_turn_deg : float
        Image cue: a track matched within image_max_age_s (s) while the gimbal turned by at most
        image_max_turn_deg (deg) adds image_weight * (1 - overlap with its expected box) to each pair cost
        (0.5 * image_weight for other tracks): with a steady camera, pixels separate close objects better
        than ground points carrying the pose noise.
    image_overlap : str
        The overlap of that cue: "giou" (default since 27 Nov 2026; generalised IoU, Rezatofighi et al.
        2019: IoU minus the share of the boxes' enclosing box they leave empty, so the cost keeps growing
        past IoU 0 and a box far from the track costs more than one beside it) or "iou" (cost at most
        image_weight: a track could give its own object's box to a neighbour and take a far box instead,
        two middling pairs beating one good one).
    iou_threshold : float
        Minimum image IoU with a track's last box for detections without ground position (frames
        without pose, boxes beyond the georeferencing range).

    Ground error of a detection (1 sigma)
    -------------------------------------
    position_sigma_m : float
        Isotropic (GPS jitter, box anchor), metres.
    heading_sigma_deg, pitch_sigma_deg, height_sigma_m, pixel_sigma_px : float
        Frame-to-frame telemetry errors and the anchor pixel's error: sideways range * d_theta, along
        the ray slant^2 / h * d_beta and range / h * dh, a pixel slant / f (times slant / h along).
    max_measurement_sigma_m : float
        Cap of the sideways and along-ray errors (far pixels near the horizon), metres.
    far_reach_sigma_m, far_anchor : float, str
        Boxes the pipeline left without a ground point (beyond its range) get one from the tracker where the
        along-ray error of a pitch error of pitch_sigma_deg (slant^2 / h * d_beta) is at most this many metres (60:
        ~430 m at 27 m up), on flat ground, anchored as PipelineConfig.anchor ("auto"; set both alike); 0: off, as
        before 30 Nov 2026 (agent.tracking.far_points).
    far_loose_gate : float
        Boxes beyond that reach (up to the horizon) get a loose ground point as well: they may start tracks and
        follow them in the image only (a box centre within this many box sizes of the track's last box moved by the
        image's common motion since, `far_shift_radius`; `association.associate_centres`), the loose point updating
        the track's position where it agrees (0: off: such boxes follow tracks by IoU and start none, as before 30
        Nov 2026). Boxes without any point (at or above the horizon, over a DEM beyond the pipeline's range) follow
        tracks by IoU either way.
    far_image_sigma_m : float
        With a value below far_reach_sigma_m: points beyond the shorter reach where the along-ray error is this many
        metres are followed in the image as well, as loose points are, though their tracks keep their positions
        within far_reach_sigma_m and their ground points still re-identify and keep births away from a track
        (`far_points.placed_rows`; 0, the default: off; docs/tracking.md "Far views in the image").
    far_shift_radius, far_shift_min_tracks, far_shift_rate_gain : float, int, float
        Boxes followed in the image are expected where the image's common motion took them since their track's last
        match (`agent.tracking.image_motion`; a tele camera's sweep or sway moves every far box alike, 2-3 box sizes
        a frame). A frame with such boxes measures it first: the shift from the expected box centres of the tracks
        matched within image_max_age_s to the frame's boxes within far_shift_radius box sizes (the smaller box's)
        that at least far_shift_min_tracks tracks agree on within far_loose_gate sizes; between such frames the
        offset moves at a rate that each measured shift moves by far_shift_rate_gain times it per second, for up
        to image_max_age_s after the last one. far_shift_radius 0: off (the last box centre, as before 30 Nov 2026).
    telemetry_latency_s, max_heading_correction_deg : float
        How much older the telemetry is than its stamp (s): while the gimbal turns, ground points are
        turned about the UAV by rate * (frame time - pose time + latency), at most this many degrees.
        Not for poses re-timed by the clock-offset estimate (`GpsTracker.update(pose_retimed=True)`):
        their heading is already interpolated at the frame's time.
    timing_sigma_s : float
        Timing error left after that (s): the heading and pitch errors grow by turn rate * it.

    Duplicates (boosting lifts the whole cluster of boxes around a remembered object)
    --------------------------------------------------------------------------------
    duplicate_iou, duplicate_ioa : float
        A box overlapping a stronger one of its class by this IoU, or covering this fraction of the
        smaller box, is not used.
    duplicate_raw_ratio, duplicate_chi2 : float
        Nor is one within duplicate_chi2 (squared Mahalanobis, both ground errors) of another with
        a raw score below duplicate_raw_ratio times the other's (part boxes, shifted boxes).
    birth_suppress_iou, birth_suppress_chi2 : float
        A free detection overlapping a box taken in this frame by this IoU, or within this squared
        Mahalanobis distance of any active track of its class, starts no track.
    merge_chi2, merge_max_m, merge_after_s : float
        Two confirmed tracks of a class within merge_chi2 (track and measurement errors) and
        merge_max_m metres for merge_after_s seconds, never both taking a convincing detection in one
        frame, follow one object: the one with fewer hits is dropped.
    merge_keep_idle : bool
        A frame where neither of two such tracks took a detection (the detector missed the object) keeps
        the time they have been found taking turns instead of starting it again.
    merge_velocity_chi2 : float
        Two such tracks whose velocities differ by more than this squared Mahalanobis distance (their
        velocity covariances) are not merged: two objects passing each other, not one followed twice (two
        tracks on one object share its detections, and a young duplicate's velocity is still uncertain).
        0: off (position alone, as before 29 Nov 2026).
    merge_edge_twins : int
        Two confirmed tracks of a class are one object, whatever their distance, once detections in this many
        frames had their first ground point in one's gate and their alternative past a terrain edge
        (FrameResult.alt_latlon) in the other's, and in none of those frames both tracks took a detection (two
        objects); the one with fewer hits is dropped (0: off).

    Re-identification
    -----------------
    reid_horizon_s : float
        How long a lost track is remembered, s.
    reid_gate_chi2 : float
        Mahalanobis gate of lost track-detection pairs; the lost track is predicted with its class's
        damped velocity (`ClassMotion`) and its uncertainty grows by reid_spread_mps per second.
    reid_delay_s : float
        0: a free detection is matched against the lost tracks at once. > 0: a new track is followed
        this long first, then all such tracks are matched in one assignment on filtered positions
        (and reported only after that).
    reid_min_evidence : float
        With an evidence function (`GpsTracker(evidence_at=...)`), a lost track is revived only
        where the memory map holds at least this much (0 = do not ask).
    reid_unreported_s : float
        A track born less than this many seconds ago whose id is not being reported (never yet, see
        `GpsTracker.report`, or no longer: its quality fell below report_quality) still competes
        for the lost tracks' ids whenever it takes a detection good enough to revive one: a
        returning object's first boxes, partly out of view or a false positive next to it, start a
        new track that then takes the object's good detections before they can revive its old
        track. It takes the old id on probation, like a revival; a track whose id was reported only
        for a lost track its detection looks more like than like the track itself (0: off).

    reid_offset_min_inliers, reid_offset_max_m, reid_offset_inlier_m : int, float, float
        A view that comes back brings its objects back together, and the telemetry's error has changed since
        they left: before matching them, the returning points are shifted by the common offset (at most
        reid_offset_max_m metres) that lays the most of them within reid_offset_inlier_m of a lost track's
        prediction, when that is at least reid_offset_min_inliers and two more than no shift
        (`agent.tracking.reid.return_offset`; 0: off).

    View jumps
    ----------
    jump_rate_deg_s, jump_window_s : float
        A frame whose pose turns faster than this (heading or pitch, deg/s: the change over the last
        jump_window_s seconds divided by at least that window, so jitter does not count) is in a
        view jump, and so is every frame for jump_settle_s seconds after the last such frame: its boxes are
        not used (the tracks coast; nothing is matched, born or revived; 0: off). A gimbal that jumps between
        two frames shows in the telemetry smeared over several frames, tens of degrees off the image; matching
        such frames in the image alone (IoU >= 0.5 with the tracks' last boxes) measured the same on the tuning
        domains and gives an old track to a new object that happens to sit where it sat in the image.
    jump_settle_s : float
        See jump_rate_deg_s, seconds.
    jump_agree_min, jump_agree_frac, jump_agree_age_s, jump_agree_lost_s : int, float, float, float
        A frame in a view jump is used after all when its pose demonstrably places the view
        (`ViewJumpGuard.agrees`): of the tracks its pose (turned as the frame's points are, telemetry_latency_s)
        puts in the image (those seen within jump_agree_age_s, and the re-ID memory's lost within
        jump_agree_lost_s, moved on with their last velocity), one lies on (in the box widened by half its larger
        side) at least jump_agree_min of its confident boxes and jump_agree_frac of the fewer of boxes and
        tracks. A turn over several frames that the log follows keeps its objects, the new view's returning ones
        included; a jump the telemetry smears (tens of degrees off: no box where a track projects) stays guarded,
        and so does a frame with fewer boxes or tracks than jump_agree_min (no evidence). jump_agree_min 0 (the
        default): off; 3 with the other defaults is the measured setting (docs/tracking.md, step 5b: +0.65 HOTA
        on the tuning jump domains, +0.17 held out, where it gained 2.7 on the slow turns of a 10 Hz log and lost
        0.5-1.4 on two others).
    jump_motion_min, jump_motion_tol : int, float
        A frame in a view jump is used after all when the image moved as its pose did (`ViewJumpGuard.follows`):
        the confident boxes of the last frame with that many (at most jump_agree_age_s before), put on the ground
        with that frame's pose and projected with this one's, lie (centres within jump_motion_tol of the two boxes'
        mean diagonal) on at least jump_motion_min of its confident boxes and jump_agree_frac of the fewer, and on
        no fewer than the boxes where they were do. Differential, so a log lagging by a steady delay passes through a
        turn it follows. With jump_agree_min too, either check may use a frame. jump_motion_min 0 (the default):
        off (docs/tracking.md, step 5b).

    Appearance (optional: used when the detections carry descriptors, `FrameResult.embeddings`)
    ----------
    use_appearance : bool
        Use the descriptors at all (False: motion only, as without them).
    appearance_ema : float
        A track's descriptor is an exponential moving average of its detections' unit descriptors
        (weight of the past, per matched detection; FairMOT/BoT-SORT use 0.9).
    reid_appearance_weight, reid_appearance_gate : float
        Re-ID pair cost += weight * cosine distance (0 = same look, 1 = unrelated); a pair farther
        than the gate in cosine distance is not made (pairs where either side has no descriptor are
        judged on motion alone).
    appearance_weight : float
        Frame-to-frame association pair cost += weight * cosine distance (a secondary cue; ground
        distance leads).

    Reporting
    ---------
    quality_rate, report_quality : float
        A track's quality is a running mean of the raw scores of its detections, with zeros for
        frames where it is in view and not detected (weight quality_rate per frame); it is reported
        (`GpsTracker.report`) only while quality >= report_quality: persistent clutter and objects
        behind foliage are followed but not reported.
    report_level_ref, report_level_top_k : float, int
        The detector's score level is the mean of each frame's report_level_top_k highest raw scores,
        averaged over frames at quality_rate (as a track's quality). While it is below report_level_ref,
        report_quality is scaled by level / report_level_ref: motion blur in a sweep, or an under-confident
        detector, lowers the scores of objects and clutter alike, and the objects stay reported (0: off).
    unseen_margin : float
        "In view" for that: the track's ground point projects inside the image by at least this fraction
        of the width (left and right) and of the height (top and bottom).

    Telemetry error (common mode)
    ---------
    register_tracks : bool
        Before gating, move the frame's ground points by the common offset between its confident
        detections and the confirmed tracks they lie next to (agent.tracking.registration): what
        per-frame GPS or gimbal jitter puts on every detection of a frame. Off by default: on the tuning
        data it removed id switches on `sea-jitter` (23 -> 13 over seeds 0-2) but added them on the base
        `sea`/`grass` scenarios (50 -> 100 on three sequences), also when gated by the turn rate.
    register_gate_m, register_min_pairs : float, int
        A detection pairs with a predicted track within this distance (mutual nearest neighbours); a
        frame needs this many pairs for an offset.
    register_max_turn_deg_s : float
        No registration while the low-pass heading (heading_smoothing_s) turns faster than this: the
        error of a turn rotates the ground points about the UAV, it does not shift them.
    heading_smoothing_s : float
        Time constant of the low-pass heading the image cue compares (image_max_turn_deg): the reported
        gimbal heading jitters from frame to frame while the camera holds still (0: raw heading).
    image_register : bool
        Before gating, move the frame's ground points by the pose correction that lays its confident
        detections onto the tracks they overlap in the image (agent.tracking.registration):
        pairs made in pixels do not depend on the telemetry, so a GPS step (4-decimal GPS: 7-11 m) or a
        gimbal angle that jitters from frame to frame no longer breaks every track of the frame at once.
    image_register_iou, image_register_min_pairs : float, int
        A pair is a confirmed track's expected box and a confident detection that are each other's best
        overlap with at least this IoU; a frame needs this many pairs whose ground differences one pose
        correction (east, north, heading, pitch; agent.tracking.registration.fit_pose_correction)
        explains within gate_chi2.
    track_follow_s : float
        After a registered frame the tracks (and the re-ID memory) move toward the telemetry's frame by
        the offset, with this time constant (0: at once): a GPS step is followed in about this time, while
        white jitter is smoothed out of the tracks' positions.
    carry_correction : bool
        A frame the image cannot register (fewer than image_register_min_pairs pairs: the one confident
        object of two, a detector that faded for a frame) keeps the part of the last registered correction
        the tracks have not yet followed, and the tracks keep following it: the raw telemetry would put its
        points as far from the tracks as that part (a 4-decimal GPS error of 7 m stays until the next GPS
        step), where a neighbour's detection may be the nearer one. Not while the gimbal turns faster than
        register_max_turn_deg_s.
    use_pipeline_correction : bool
        Track on the ground points as the pipeline corrected them by the memory map
        (FrameResult.correction, PipelineConfig.correct_telemetry); False (default since 26 Nov 2026): take
        that offset back off and work from the telemetry's own points, registered in the image only. The
        map's correction jumps when two objects alias (one laid onto the other's evidence), and tracks that
        follow the corrected frame (track_follow_s) and carry its corrections followed those jumps; the
        telemetry's own frame jumps only at GPS steps.
    image_register_alone : bool
        When the image shows a single confirmed track, its one pair registers the frame (the object
        cannot tell its own motion from the telemetry's error; the image says it stayed).
    registered_floor_m : float
        In a registered frame a detection's ground error is its pixel error, the correction's own
        uncertainty at its place and this isotropic floor (metres, 1 sigma).
    registered_error_scale : float
        ... plus this share of the unregistered error model's telemetry part (0: none).
    registered_scale_s : float
        The pixel error and the floor are scaled by how much noisier than that the registration's pairs
        were (the median of their squared Mahalanobis residuals against its chi-square value), smoothed
        over frames with this time constant, seconds (0: no scaling).
    register_position_sd_m, register_angle_scale : float
        Prior of the correction: its position part is expected within this many metres (a GPS step of old
        SRT files is 11 m), its heading and pitch parts within register_angle_scale times the frame's
        heading and pitch errors (heading_sigma_deg, pitch_sigma_deg with the turn terms). A cluster of
        pairs far away is explained as a shift, pairs spread in range and bearing as a turn.
    image_gate : float
        In a frame whose image the registration paired with the tracks (the camera did what the telemetry
        said), a track matched within image_gate_age_s seconds (and the heading turned by at most
        image_max_turn_deg since) takes only detections whose box centre lies within image_gate +
        image_gate_growth_per_s * (seconds since) box sizes (square root of the area) of its expected box
        (0: off).
    image_first_iou : float
        First association round in the image (agent.tracking.association.associate_image): a confirmed
        track the image still shows takes the confident detection overlapping its expected box by at
        least this IoU, before the ground rounds; its filter is updated only when the ground agrees
        (0: off).
    image_velocity : bool
        The image cue and the registration expect a track's box where its last box moves with its image
        velocity (an exponential average of its box centres' motion, image_velocity_ema of the past per
        matched detection), not at its last place: a camera flying an orbit moves every box steadily.

    Other
    -----
    reanchor_m : float
        Move the local origin to the UAV when it is farther than this from it, metres.
    class_motion : tuple of (class name, ClassMotion)
        Motion per class name; default_motion for other classes.
    default_motion : ClassMotion
    """

    match_score: float = 0.4
    low_score: float = 0.15
    birth_score: float = 0.5
    reid_score: float = 0.5
    birth_on_raw: bool = True
    confirm_hits: int = 3
    confirm_score: float = 0.2
    confirm_window_s: float = 0.5
    tentative_coast_s: float = 0.25
    max_coast_s: float = 1.0
    exit_margin_px: float = 4.0
    exit_coast_s: float = 0.0
    exit_expected: bool = True
    gate_chi2: float = 9.21
    max_gate_m: float = 40.0
    score_weight: float = 1.0
    pair_max_cost: float | None = 17.0
    image_weight: float = 8.0
    image_overlap: str = "giou"
    image_max_age_s: float = 0.3
    image_max_turn_deg: float = 1.0
    iou_threshold: float = 0.2
    position_sigma_m: float = 0.5
    heading_sigma_deg: float = 1.0
    pitch_sigma_deg: float = 0.5
    height_sigma_m: float = 0.3
    pixel_sigma_px: float = 4.0
    max_measurement_sigma_m: float = 30.0
    far_reach_sigma_m: float = 60.0
    far_anchor: str = "auto"
    far_loose_gate: float = 2.0
    far_image_sigma_m: float = 0.0
    far_shift_radius: float = 8.0
    far_shift_min_tracks: int = 3
    far_shift_rate_gain: float = 0.5
    telemetry_latency_s: float = 0.05
    max_heading_correction_deg: float = 30.0
    timing_sigma_s: float = 0.05
    duplicate_iou: float = 0.25
    duplicate_ioa: float = 0.5
    duplicate_raw_ratio: float = 0.5
    duplicate_chi2: float = 4.0
    birth_suppress_iou: float = 0.1
    birth_suppress_chi2: float = 4.0
    merge_chi2: float = 9.21
    merge_max_m: float = 10.0
    merge_after_s: float = 0.5
    merge_keep_idle: bool = True
    merge_velocity_chi2: float = 9.21
    merge_edge_twins: int = 3
    reid_horizon_s: float = 30.0
    reid_gate_chi2: float = 9.21
    reid_delay_s: float = 0.0
    reid_min_evidence: float = 0.0
    reid_unreported_s: float = 3.0
    reid_offset_min_inliers: int = 3
    reid_offset_max_m: float = 10.0
    reid_offset_inlier_m: float = 1.5
    jump_rate_deg_s: float = 150.0
    jump_window_s: float = 0.05
    jump_settle_s: float = 0.1
    jump_agree_min: int = 0
    jump_agree_frac: float = 0.5
    jump_agree_age_s: float = 0.5
    jump_agree_lost_s: float = 6.0
    jump_motion_min: int = 0
    jump_motion_tol: float = 0.5
    use_appearance: bool = True
    appearance_ema: float = 0.9
    reid_appearance_weight: float = 10.0
    reid_appearance_gate: float = 0.5
    appearance_weight: float = 2.0
    quality_rate: float = 0.1
    unseen_margin: float = 0.02
    report_quality: float = 0.4
    report_level_ref: float = 0.0
    report_level_top_k: int = 5
    reanchor_m: float = 2000.0
    register_tracks: bool = False
    register_gate_m: float = 4.0
    register_min_pairs: int = 3
    register_max_turn_deg_s: float = 10.0
    heading_smoothing_s: float = 0.15
    image_register: bool = True
    image_register_iou: float = 0.5
    image_register_min_pairs: int = 2
    image_register_alone: bool = True
    track_follow_s: float = 0.5
    carry_correction: bool = True
    use_pipeline_correction: bool = False
    registered_floor_m: float = 0.2
    registered_error_scale: float = 0.3
    registered_scale_s: float = 1.0
    register_position_sd_m: float = 10.0
    register_angle_scale: float = 1.0
    image_velocity: bool = True
    image_gate: float = 2.0
    image_first_iou: float = 0.0
    image_gate_age_s: float = 1.0
    image_gate_growth_per_s: float = 4.0
    image_velocity_ema: float = 0.5
    class_motion: tuple[tuple[str, ClassMotion], ...] = DEFAULT_CLASS_MOTION
    default_motion: ClassMotion = field(default_factory=lambda: ClassMotion(2.0, 10.0, 1.0))

    def __post_init__(self) -> None:
        positive = {"confirm_window_s", "tentative_coast_s", "max_coast_s", "gate_chi2", "max_gate_m",
                    "position_sigma_m", "max_measurement_sigma_m", "merge_chi2", "merge_max_m", "reid_gate_chi2",
                    "reanchor_m", "jump_motion_tol"}
        unit = {"duplicate_iou", "duplicate_ioa", "birth_suppress_iou", "iou_threshold", "quality_rate",
                "image_register_iou"}
        if self.image_first_iou and not 0.0 < self.image_first_iou <= 1.0:
            raise ValueError(f"TrackerConfig.image_first_iou={self.image_first_iou!r} must be 0 (off) or in (0, 1]")
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name in ("birth_on_raw", "use_appearance", "confirm_hits", "register_tracks", "register_min_pairs",
                          "image_register", "image_register_min_pairs", "image_velocity", "image_register_alone",
                          "report_level_top_k", "exit_expected",
                          "carry_correction", "use_pipeline_correction",
                          "merge_keep_idle", "merge_edge_twins",
                          "class_motion", "default_motion",
                          "pair_max_cost", "exit_margin_px", "image_overlap", "far_anchor"):
                continue
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"TrackerConfig.{f.name} must be a finite number, got {value!r}")
            if f.name in unit and not 0.0 < value <= 1.0:
                raise ValueError(f"TrackerConfig.{f.name}={value!r} must be in (0, 1]")
            if f.name in positive and value <= 0:
                raise ValueError(f"TrackerConfig.{f.name}={value!r} must be > 0")
            if value < 0:
                raise ValueError(f"TrackerConfig.{f.name}={value!r} must be >= 0")
        if self.pair_max_cost is not None and not (isinstance(self.pair_max_cost, (int, float))
                                                   and math.isfinite(self.pair_max_cost) and self.pair_max_cost > 0):
            raise ValueError(f"TrackerConfig.pair_max_cost={self.pair_max_cost!r} must be None or a number > 0")
        if not isinstance(self.exit_margin_px, (int, float)) or not math.isfinite(self.exit_margin_px):
            raise ValueError(f"TrackerConfig.exit_margin_px must be a finite number (< 0: off), "
                             f"got {self.exit_margin_px!r}")
        if isinstance(self.merge_edge_twins, bool) or not isinstance(self.merge_edge_twins, int) \
                or self.merge_edge_twins < 0:
            raise ValueError(f"TrackerConfig.merge_edge_twins must be an int >= 0 (0: off), "
                             f"got {self.merge_edge_twins!r}")
        if self.far_anchor not in ("auto", "center", "bottom"):
            raise ValueError(f"TrackerConfig.far_anchor must be one of auto, center, bottom, got {self.far_anchor!r}")
        if self.image_overlap not in IMAGE_OVERLAPS:
            raise ValueError(f"TrackerConfig.image_overlap must be one of {IMAGE_OVERLAPS}, got {self.image_overlap!r}")
        for name in ("jump_agree_min", "jump_motion_min"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int):
                raise ValueError(f"TrackerConfig.{name}={value!r} must be an integer >= 0")
        if self.jump_agree_frac > 1.0:
            raise ValueError(f"TrackerConfig.jump_agree_frac={self.jump_agree_frac!r} must be in [0, 1]")
        for name in ("register_min_pairs", "image_register_min_pairs", "report_level_top_k", "far_shift_min_tracks"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"TrackerConfig.{name}={value!r} must be an integer >= 1")
        for name in ("birth_on_raw", "use_appearance", "register_tracks", "image_register", "image_velocity",
                     "image_register_alone", "merge_keep_idle", "carry_correction",
                     "use_pipeline_correction", "exit_expected"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"TrackerConfig.{name} must be a bool, got {getattr(self, name)!r}")
        for name in ("appearance_ema", "image_velocity_ema"):
            if not getattr(self, name) < 1.0:
                raise ValueError(f"TrackerConfig.{name}={getattr(self, name)!r} must be in [0, 1)")
        if isinstance(self.confirm_hits, bool) or not isinstance(self.confirm_hits, int) or self.confirm_hits < 1:
            raise ValueError(f"TrackerConfig.confirm_hits={self.confirm_hits!r} must be an integer >= 1")
        if self.low_score > self.match_score:
            raise ValueError(f"TrackerConfig.low_score={self.low_score!r} must be <= match_score={self.match_score!r}")
        for entry in self.class_motion:
            if (not isinstance(entry, tuple) or len(entry) != 2 or not isinstance(entry[0], str)
                    or not isinstance(entry[1], ClassMotion)):
                raise ValueError(f"TrackerConfig.class_motion entries must be (name, ClassMotion), got {entry!r}")
        if not isinstance(self.default_motion, ClassMotion):
            raise ValueError(f"TrackerConfig.default_motion must be a ClassMotion, got {self.default_motion!r}")

    def at_frame_interval(self, dt_s: float) -> TrackerConfig:
        """These settings for frames dt_s seconds apart: the windows in seconds floored to what such frames
        allow (FRAME_FLOORS: a tentative track survives until the next frame, can be confirmed by
        confirm_hits frames, a confirmed one coasts over two missed frames, the image cue reaches the last
        frame). At 24 fps and faster no floor binds and the same object is returned; a detector's output
        every 15th frame (2 fps, SeaDronesSee) otherwise deleted every tentative track before its second frame.
        """
        if not (math.isfinite(dt_s) and dt_s > 0):
            return self
        floors = {name: k * dt_s for name, k in FRAME_FLOORS.items()}
        floors["confirm_window_s"] = (self.confirm_hits - 0.5) * dt_s
        changes: dict[str, Any] = {name: value for name, value in floors.items() if getattr(self, name) < value}
        return dataclasses.replace(self, **changes) if changes else self

    def motion_for(self, class_name: str | None) -> ClassMotion:
        """The motion model of a class name (`default_motion` when it has none)."""
        for name, motion in self.class_motion:
            if name == class_name:
                return motion
        return self.default_motion
