"""Settings of the per-frame detection pipeline: memory map, boosting, size filter, NMS, and the joint map's
part (boosting with it and the detections it adds).
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import sys
from dataclasses import dataclass, field

from agent.boxes import ANCHORS
from agent.clock_offset import ClockOffsetSettings
from agent.memory_map import MemoryMapConfig
from agent.score_calibration import CalibrationSettings
from agent.size_filter_check import SizeCheckSettings
from agent.telemetry_correction import CorrectionSettings
from shared.terrain import Terrain

__all__ = ["BOOST_MODES", "JOINT_MODES", "PipelineConfig", "refuse_huge_int"]

JOINT_MODES = ("max", "local", "joint", "mean")
BOOST_MODES = ("add", "logodds")
#: Allowed values of the joint detections' tuning settings: (field, low, high, low excluded).
_CORRECTION = CorrectionSettings()

_JOINT_TUNING_RANGES = (
    ("joint_peak_smoothing_m", 0.0, math.inf, True),
    ("joint_peak_gate_across_rad", 0.0, math.inf, False),
    ("joint_peak_gate_down_rad", 0.0, math.inf, False),
    ("joint_register_score", 0.0, math.inf, False),
    ("joint_register_radius_m", 0.0, math.inf, True),
    ("joint_register_window_s", 0.0, math.inf, True),
    ("joint_register_min_pairs", 1.0, math.inf, False),
    ("joint_register_bin_rad", 0.0, math.inf, True),
    ("joint_register_match_rad", 0.0, math.inf, True),
    ("joint_register_candidates", 1.0, math.inf, False),
    ("joint_register_max_rad", 0.0, math.inf, True),
    ("joint_carry_gate", 0.0, math.inf, False),
    ("joint_carry_min_sightings", 1.0, math.inf, False),
    ("joint_carry_match_iou", 0.0, 1.0, False),
    ("joint_carry_blend", 0.0, 1.0, False),
    ("joint_carry_velocity_gain", 0.0, 1.0, False),
    ("joint_absent_value", 0.0, 1.0, False),
    ("joint_absent_logit", 0.0, math.inf, False),
    ("track_lending", 0.0, 1.0, False),
)


@dataclass(frozen=True, slots=True)
class PipelineConfig:
    """Pipeline parameters (defaults: the best measured on the simulator; see docs/memory-map.md).

    boost_weight: c_hat = c + boost_weight * p (paper: 1).
    boost_mode: "add" (the paper: c + w p) or "logodds" (logit(c_hat) = logit(c) + w * logodds_scale * p:
        a Bayesian update that moves mid-confidence boxes most and keeps c_hat in (0, 1); logodds_scale 6
        with the map's half-life 0.5 s was chosen on the tuning domains (issue 15, third round: +7.4 /
        +7.0 AP50 over no memory at noise x1 / x2 against +6.3 / +6.1 with 4 and 1 s, and the paper's rule
        +6.6 / +6.6)).
    use_memory: False gives the single-frame baseline (same filter and NMS, no boosting).
    use_size_filter: apply the distance-size filter, per class only where its prior agrees with the data:
        size_check_min_score, size_check_min_boxes, size_check_max_shift, size_check_widen
        (agent.size_filter_check: the confident boxes that stand for real objects, how many a class needs,
        how far (std) their median may lie from the prior's mean, and whether the band is widened to it;
        the built-in priors would have removed a fifth of the real swimmers of SeaDronesSee).
    anchor: where on a box its ground point is: "center" (the paper), "bottom" (feet of an upright
        object) or "auto" (from the bottom at grazing views to the centre at nadir).
    joint_mode: how a joint map from the fusion server combines with the local one for boosting:
        "max" (default), "local" (ignore it), "joint" (only it where fresh), "mean".
    max_range_m: boxes whose ground point is farther from the UAV are not georeferenced (default:
        half the memory window).
    fragment_iou: of the boxes NMS keeps, one that a kept box of its class with a higher boosted score overlaps
        by an IoU of at least fragment_iou (kept boxes overlap by at most nms_iou) keeps the detector's score,
        not the boosted one: the map's evidence at its cell is that box's object's, of which it is a part or a
        displaced copy, and boosting it makes a false positive next to every object the map remembers (0: off,
        every box is boosted, as in the paper; at or above nms_iou it never acts). Measured in
        docs/memory-map.md, "Fragments".
    nms_iou: IoU threshold of class-wise NMS; score_threshold: minimum output score;
    max_detections: per frame, highest scores first (COCO evaluates 100).
    joint_detections: with a joint layer, use_memory and joint_mode other than "local", add detections for the
        other UAVs' evidence in this view that no detection of the frame explains (agent.joint_detections;
        flagged in FrameResult.from_joint). joint_min_value: the others' evidence a peak needs;
        joint_gate_m: ground distance within which a kept box explains (or is promoted by) a peak (an
        angular gate around the peak's pixel applies too, joint_peak_gate_across_rad / _down_rad);
        joint_cover_uavs: UAVs assumed to cover a joint cell when this UAV's own evidence is taken out
        of the joint mean (1: use the joint value as is); joint_prior_score: the confidence a joint
        detection is credited with before the boost by the others' evidence (see joint_score; 0.5: a
        promoted weak box ranks with confident detections, as it was right in ~88 % of cases on `coop`);
        joint_logodds_scale: the log-odds scale of that score (with boost_mode "logodds"; None, the
        default: the boost's own logodds_scale, so a promoted box ranks on the same scale as the boosted
        detections it competes with: after logodds_scale moved from 4 to 6, keeping 4 here cost uav1 2.0
        AP50 on `coop` seeds 0-2);
        joint_synth_factor: multiplies the score of boxes synthesised where no real candidate exists
        (their pixel position carries the cross-UAV georeferencing error: on `coop` at 80 m they overlapped
        the object in 4 of ~1,200 cases; default 0 = only promote and carry real candidates).
        joint_carry_s: for this long after this UAV last saw an object the others' evidence points at (a
        promoted or confident box), a frame with no box for it reports the last one moved on by its image
        velocity (agent.joint_detections.JointCarry; 0 = off), scored the peak's times joint_carry_factor.
    joint_register_boost: once the joint detections' registration has an offset (JointRegistration), each
        candidate is boosted with the others' evidence read where the registration puts it (its anchor moved by
        the offset) beside this UAV's own evidence at the candidate, averaged over the UAVs covering the spot,
        instead of the joint map read at the candidate (agent.joint_boost; the two UAVs' maps lie metres apart,
        4.6 m on `coop-glare` seed 0). joint_absent_value, joint_absent_logit: where a partner's footprint
        covers the registered spot and the others' evidence there is below joint_absent_value, the candidate's
        log-odds are lowered by joint_absent_logit (boost_mode "logodds" only; 0 = never). It needs the joint
        detections (the registration is theirs: with joint_detections off, or joint_mode "local", it does
        nothing, and a pipeline with a joint layer says so in a warning). Off by default: chosen
        on the coop tuning domains (the weaker UAV's joint AP50 +0.38, the others +0.31), it held out at +0.12 /
        +0.05 with `coop-high-low` -0.4 / -0.2 and fewer hidden objects found by the stronger UAVs, where the
        registration leaves most (docs/simulator.md, "Fourth measurement"; 28 Nov 2026).
    track_lending: with another UAV on the same global track (the fusion server's ``joint/tracks``), a detection
        of that track moves this share of the way, in log-odds, to the confidence the other UAV reports for it
        (the highest over the last agent.track_lending.MEMORY_S, 2 s), where that is higher (agent.track_lending;
        the output only: the detections the agent writes; 0 = off). 0.5 since 1 Dec 2026, chosen on the coop tuning
        domains among 0.5, 0.75 and 1.0 (docs/simulator.md, "Eighth measurement").

    correct_telemetry: before boosting and stamping, register the frame's confident boxes to the memory
        map and move all its ground points by the common offset found (agent.telemetry_correction; needs
        use_memory). correction_min_score, correction_search_m, correction_min_points,
        correction_min_support, correction_smoothing_s, correction_hold_s, correction_local_m: its settings
        (CorrectionSettings: the detector score that registers, the largest offset searched around the
        last correction, the boxes and mean evidence a measurement needs, the smoothing time constant,
        how long a correction is held without measurements, and the radius around the current correction
        searched first). correction_anchor_s: the time over which the correction is anchored to the
        telemetry (CorrectionSettings.anchor_s: the applied corrections averaged over it are taken off each
        measurement, so the map stays where the telemetry puts the objects on average instead of drifting
        with the correction's own errors; 0: not anchored). 10 s by default (29 Nov 2026): unanchored, the
        maps walked away from exact telemetry (the joint map's peaks on `coop-slope` a median 1.28 m off
        after 15 s, 0.50 m anchored at 10 s) while the mean AP50 of each domain grid moved by at most 0.3
        (docs/memory-map.md, "Anchoring").

    estimate_clock_offset: the frame drivers of files (`uavmm boost`, `uavmm track`, `uavmm tune`, the
        evaluations) estimate the video/telemetry clock offset online from the confident detections and
        give the pipeline and the tracker poses with the telemetry interpolated at frame time + offset
        (agent.clock_offset); the live agent does not (it would have to hold frames back by the search
        window). In `uavmm boost` since issue 15's fifth round: +0.44 / +0.41 mean AP50 on the tuning
        domains at noise x1 / x2 (two passes; docs/memory-map.md). clock_offset_fallback_s: the offset used
        until a window of frames turned enough to measure it (the configured telemetry latency);
        clock_offset_search_s: the estimate stays within +- this. clock_offset_two_pass: files are searched
        twice and each frame gets the estimate from the whole video's informative windows weighted by their
        distance in time (ClockOffsetSettings.two_pass; False: the online estimate alone). The estimate is on
        by default since the tracker registers its frames in the image (issue 15, third round): with it the
        sweeps of the tuning domains lost most of their id switches (grass-sweeps-wide 34 -> 15,
        sea-sweeps-60 47 -> 7, reid 26 -> 18 over seeds 0-2) while the base `sea`/`grass` scenarios stayed
        within one switch per seed (docs/tracking.md).

    dequantize_telemetry: the frame drivers of files make GPS written with 3 to 5 decimals (and altitude in
        whole or half metres) continuous again before anything else (agent.telemetry_dequantize: ramps from the
        middles of the steps to the levels written, inside the rounding interval); detected per video from the
        values themselves, a no-op on other telemetry. So do `uavmm detect` and `uavmm agent --video` with the
        telemetry file they read whole (VideoSource); a live MAVLink stream is not.

    terrain: the DEM boxes are georeferenced on (`uavmm ... --dem FILE`, agent.dem; shared.terrain.Terrain: ray
        and terrain intersected instead of ray and flat ground, and the size filter's range and depression taken
        to the terrain point); None (the default) is flat ground at the UAV's height reference. A terrain
        without takeoff_elevation_m gets, per video, the DEM's height under the video's first pose
        (DetectionPipeline.terrain_for). Not a setting of config files: it comes from --dem.
    edge_probe: over a terrain, the anchors of the kept boxes are probed this fraction of their box's height above
        and below; where one probe's ray passes an edge of the terrain (a bank's lip, a crest) that the other does
        not, its ground point is the box's alternative (FrameResult.alt_latlon, shared.terrain.edge_alternatives),
        which the tracker may match instead (0: off).

    telemetry_at_frame_time: the frame drivers of files give each frame the telemetry interpolated at its own
        time between the telemetry's samples, put on the frame clock first (agent.telemetry_clock: a time-zone
        offset removed, sample-and-hold repeats recognised); False: each frame keeps the sample it carries, as
        the paper's rule does.

    view_cuts: the frame drivers of files put a view jump hidden between two telemetry samples (a log at 1 Hz
        interpolated at the frames' times shows a 60 deg jump as a second-long turn) at the frame where the
        confident detections stop continuing the previous frame's, stepping heading and pitch there
        (agent.view_cuts); an interval without a clear cut keeps its interpolated poses. The live agent does not.

    calibrate_scores: with use_memory, scale the detector's logits to the reference temperature from the
        spread of each frame's strongest detections, estimated online (agent.score_calibration), before
        boosting, stamping and the tracker (FrameResult.raw_scores are then the calibrated scores);
        calibration_tau_s: time constant of that estimate, seconds; calibration_ref_sd: the reference
        spread (the simulator's default detector on the tuning domains); calibration_max_floor: the
        calibration stands down on input thresholded above this score (a detector's final output: fewer than
        1 % of its scores lie below it), whose strongest detections' spread the threshold truncates.

    Tuning of the joint detections (agent.joint_detections; measured on the simulator's `coop`):
    joint_peak_smoothing_m: standard deviation (m) of the Gaussian that smooths the others' evidence
        before looking for its maxima (maps clip at 1: a steadily seen object is a plateau). 0.25 since 28 Nov
        2026, chosen on the coop tuning domains (the weaker UAV's joint AP50 +0.78 over 1.0, seeds 0-2; 0.1-1.5
        measured) and held out (+0.42 on average, `coop-glare-east` +0.76, `coop-sea-glare` -0.67). A plateau's
        inner cells then tie as maxima: the 3 m suppression keeps one peak per 3 m of a wide one (a group, a
        walker's trail), the middle first (docs/simulator.md, "Second measurement").
    joint_peak_gate_across_rad, joint_peak_gate_down_rad: angular gate around a peak's (registered) pixel,
        half-axes across and down the image in focal lengths (radians): a kept box whose anchor lies inside
        this ellipse is near the peak, as is one within joint_gate_m on the ground. What is left of the
        cross-UAV error after registration is angular (both UAVs' heading and pitch jitter, the
        telemetry's sample-and-hold during sweeps): at 80 m and 20 deg a ground gate of 3 m spans ~105 px
        across but only ~33 px down the image, less than the peaks' scatter (inter-quartile ~35-70 px
        down, ~80 px across on `coop`). 0.035 / 0.02 rad are 2.0 / 1.15 deg (~105 / 60 px at focal 2985 px).
    joint_register_score: kept detections scoring at least this update the registration (JointRegistration)
        of the others' evidence in this UAV's image; joint_register_radius_m, joint_register_window_s,
        joint_register_min_pairs, joint_register_bin_rad, joint_register_match_rad,
        joint_register_candidates, joint_register_max_rad: its pairing radius (m), memory (s), pairs
        needed, histogram bin (focal lengths), match radius, maxima tried and largest offset (see
        JointRegistration).
    joint_carry_gate: a remembered sighting (JointCarry) stands for a peak up to this many joint_gate_m away
        (this UAV's own ground point of a person at 80 m grazing errs by metres along the line of sight
        from frame to frame).
    joint_carry_min_sightings: a remembered sighting stands for a peak no box explains only once this UAV
        has seen the object there in at least this many frames (overlapping sightings, see
        JointCarry.observe). On `coop` (seeds 3 and 4) carried boxes from a single sighting were right in
        6-9 % of frames (mostly a background false positive or a neighbour's box that happened to lie
        near the peak), from four or more in 88 %.
    joint_carry_match_iou: a kept box is the object a remembered sighting stands for when their IoU
        reaches this.
    joint_carry_blend: weight of a new sighting against the remembered one it overlaps (1 = keep the new
        box only); joint_carry_velocity_gain: gain of a remembered sighting's image velocity on each new
        sighting (the beta of an alpha-beta filter whose alpha is joint_carry_blend): the box's pixel
        velocity (camera sweep and object motion together) settles over ~10 sightings, so one jittery box
        moves it little.
    """

    memory: MemoryMapConfig = field(default_factory=MemoryMapConfig)
    boost_weight: float = 1.0
    boost_mode: str = "logodds"
    logodds_scale: float = 6.0
    use_memory: bool = True
    use_size_filter: bool = True
    anchor: str = "auto"
    joint_mode: str = "max"
    max_range_m: float | None = None
    fragment_iou: float = 0.1
    nms_iou: float = 0.5
    score_threshold: float = 0.001
    max_detections: int = 100
    joint_detections: bool = True
    joint_min_value: float = 0.3
    joint_gate_m: float = 3.0
    joint_cover_uavs: int = 2
    joint_prior_score: float = 0.5
    joint_logodds_scale: float | None = None
    joint_synth_factor: float = 0.0
    joint_carry_s: float = 0.5
    joint_carry_factor: float = 0.8
    joint_peak_smoothing_m: float = 0.25
    joint_peak_gate_across_rad: float = 0.035
    joint_peak_gate_down_rad: float = 0.02
    joint_register_score: float = 0.5
    joint_register_radius_m: float = 8.0
    joint_register_window_s: float = 10.0
    joint_register_min_pairs: int = 5
    joint_register_bin_rad: float = 0.0017
    joint_register_match_rad: float = 0.0134
    joint_register_candidates: int = 8
    joint_register_max_rad: float = 0.15
    joint_carry_gate: float = 2.0
    joint_carry_min_sightings: int = 2
    joint_carry_match_iou: float = 0.3
    joint_carry_blend: float = 0.5
    joint_carry_velocity_gain: float = 0.1
    joint_register_boost: bool = False
    joint_absent_value: float = 0.05
    joint_absent_logit: float = 2.0
    track_lending: float = 0.5
    size_check_min_score: float = 0.5
    size_check_min_boxes: int = 15
    size_check_max_shift: float = 3.0
    size_check_widen: bool = True
    calibrate_scores: bool = True
    calibration_max_floor: float = 0.05
    calibration_tau_s: float = 30.0
    calibration_ref_sd: float = 1.35
    correct_telemetry: bool = True
    # the correction's defaults are CorrectionSettings' (one place to change them)
    correction_min_score: float = _CORRECTION.min_score
    correction_search_m: float = _CORRECTION.search_m
    correction_min_points: int = _CORRECTION.min_points
    correction_min_support: float = _CORRECTION.min_support
    correction_smoothing_s: float = _CORRECTION.smoothing_s
    correction_hold_s: float = _CORRECTION.hold_s
    correction_local_m: float = _CORRECTION.local_m
    correction_anchor_s: float = _CORRECTION.anchor_s
    estimate_clock_offset: bool = True
    clock_offset_fallback_s: float = 0.0
    clock_offset_search_s: float = 1.0
    clock_offset_two_pass: bool = True
    dequantize_telemetry: bool = True
    telemetry_at_frame_time: bool = True
    view_cuts: bool = True
    terrain: Terrain | None = None
    edge_probe: float = 0.3

    def __post_init__(self) -> None:
        if self.terrain is not None and not isinstance(self.terrain, Terrain):
            raise ValueError(f"terrain must be a shared.terrain.Terrain (from --dem FILE), got "
                             f"{type(self.terrain).__name__}")
        self.correction_settings()  # validates the correction_* fields
        self.clock_offset_settings()  # and the clock_offset_* ones
        self.calibration_settings()  # and the calibration_* ones
        self.size_check_settings()  # and the size_check_* ones
        if self.anchor not in ANCHORS:
            raise ValueError(f"anchor must be one of {', '.join(ANCHORS)}, got {self.anchor!r}")
        if self.boost_mode not in BOOST_MODES:
            raise ValueError(f"boost_mode must be one of {', '.join(BOOST_MODES)}, got {self.boost_mode!r}")
        if self.joint_mode not in JOINT_MODES:
            raise ValueError(f"joint_mode must be one of {', '.join(JOINT_MODES)}, got {self.joint_mode!r}")
        if isinstance(self.edge_probe, bool) or not isinstance(self.edge_probe, numbers.Real) \
                or not (math.isfinite(self.edge_probe) and 0.0 <= self.edge_probe <= 1.0):
            raise ValueError(f"edge_probe must be in [0, 1] (a fraction of the box's height; 0: off), got "
                             f"{self.edge_probe!r}")
        if not (0.0 < self.nms_iou <= 1.0):
            raise ValueError(f"nms_iou must be in (0, 1], got {self.nms_iou!r}")
        if isinstance(self.fragment_iou, bool) or not isinstance(self.fragment_iou, numbers.Real) \
                or not (0.0 <= self.fragment_iou < 1.0):
            raise ValueError(f"fragment_iou must be a number in [0, 1) (0: off), got {self.fragment_iou!r}")
        if not math.isfinite(self.boost_weight) or self.boost_weight < 0:
            raise ValueError(f"boost_weight must be >= 0, got {self.boost_weight!r}")
        if self.max_detections < 1:
            raise ValueError(f"max_detections must be >= 1, got {self.max_detections!r}")
        if not (0.0 < self.joint_min_value <= 1.0):
            raise ValueError(f"joint_min_value must be in (0, 1], got {self.joint_min_value!r}")
        if not (math.isfinite(self.joint_gate_m) and self.joint_gate_m >= 0):
            raise ValueError(f"joint_gate_m must be >= 0, got {self.joint_gate_m!r}")
        if self.joint_cover_uavs < 1:
            raise ValueError(f"joint_cover_uavs must be >= 1, got {self.joint_cover_uavs!r}")
        if self.joint_logodds_scale is not None and not (
                math.isfinite(self.joint_logodds_scale) and self.joint_logodds_scale > 0):
            raise ValueError(f"joint_logodds_scale must be > 0, got {self.joint_logodds_scale!r}")
        if not (0.0 < self.joint_prior_score < 1.0):
            raise ValueError(f"joint_prior_score must be in (0, 1), got {self.joint_prior_score!r}")
        if not (0.0 <= self.joint_synth_factor <= 1.0):
            raise ValueError(f"joint_synth_factor must be in [0, 1], got {self.joint_synth_factor!r}")
        if not (math.isfinite(self.joint_carry_s) and self.joint_carry_s >= 0):
            raise ValueError(f"joint_carry_s must be >= 0, got {self.joint_carry_s!r}")
        if not (0.0 <= self.joint_carry_factor <= 1.0):
            raise ValueError(f"joint_carry_factor must be in [0, 1], got {self.joint_carry_factor!r}")
        for name, low, high, low_open in _JOINT_TUNING_RANGES:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
                    or value < low or (low_open and value == low) or value > high:
                allowed = (f"in {'(' if low_open else '['}{low:g}, {high:g}]" if math.isfinite(high)
                           else f"{'>' if low_open else '>='} {low:g}")
                raise ValueError(f"{name} must be a number {allowed}, got {value!r}")
        for f in dataclasses.fields(self):  # every switch: a JSON "false" (a string) would be truthy, so on
            value = getattr(self, f.name)
            if f.type == "bool" and not isinstance(value, bool):
                raise ValueError(f"{f.name} must be true or false, got {value!r}")
        for name in ("joint_register_min_pairs", "joint_register_candidates", "joint_carry_min_sightings"):
            if not isinstance(getattr(self, name), int):
                raise ValueError(f"{name} must be an integer, got {getattr(self, name)!r}")

    def correction_settings(self) -> CorrectionSettings:
        """The telemetry correction's settings (agent.telemetry_correction)."""
        return CorrectionSettings(min_score=self.correction_min_score, search_m=self.correction_search_m,
                                  min_points=self.correction_min_points, min_support=self.correction_min_support,
                                  smoothing_s=self.correction_smoothing_s, hold_s=self.correction_hold_s,
                                  local_m=self.correction_local_m, anchor_s=self.correction_anchor_s)

    @property
    def joint_scale(self) -> float:
        """The log-odds scale joint detections score with (joint_logodds_scale, else logodds_scale)."""
        return self.logodds_scale if self.joint_logodds_scale is None else self.joint_logodds_scale

    def clock_offset_settings(self) -> ClockOffsetSettings | None:
        """The clock-offset estimate's settings (agent.clock_offset), None when it is off."""
        settings = ClockOffsetSettings(fallback_s=self.clock_offset_fallback_s, search_s=self.clock_offset_search_s,
                                       two_pass=self.clock_offset_two_pass)
        return settings if self.estimate_clock_offset else None

    def calibration_settings(self) -> CalibrationSettings:
        """The score calibration's settings (agent.score_calibration)."""
        return CalibrationSettings(tau_s=self.calibration_tau_s, ref_sd_logit=self.calibration_ref_sd,
                                   max_floor=self.calibration_max_floor)

    def size_check_settings(self) -> SizeCheckSettings:
        """The size filter's check of its priors against the data (agent.size_filter_check)."""
        return SizeCheckSettings(min_score=self.size_check_min_score, min_boxes=self.size_check_min_boxes,
                                 max_shift=self.size_check_max_shift, widen=self.size_check_widen)

    @property
    def range_limit_m(self) -> float:
        return self.memory.window_m / 2.0 if self.max_range_m is None else self.max_range_m


def refuse_huge_int(key: str, value: object) -> None:
    """ValueError naming the setting `key` of a JSON settings file when `value` is an integer beyond float's range
    (json reads any number of digits; the settings' own checks raised OverflowError converting it)."""
    if isinstance(value, int) and not isinstance(value, bool) and abs(value) > sys.float_info.max:
        raise ValueError(f"setting {key!r} is a number of {len(str(abs(value)))} digits, beyond any float")
