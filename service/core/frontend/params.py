"""Parameters of the Manhattan estimator.

The first block is the paper's method with its published values (Sawamura-style projection
histograms, IROS 2010, see `docs/estimator.md`); the second block is what we added because real
data needs it. Every addition can be switched off, which is how `docs/estimator.md` measures
each step's effect.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from service.core.frontend.dynamic import SeenThroughParams
from service.core.frontend.frames import FrameParams
from service.core.types import fields_by_name, restore_fields

ReferenceMode = Literal["previous", "keyframe", "local_map"]
HeadingScore = Literal["max", "energy"]


@dataclass(frozen=True, slots=True)
class EstimatorParams:
    # --- the paper (§II, §III) -------------------------------------------------------------
    thinning_m: float = 0.05  # keep points roughly this far apart along the scan
    heading_step_deg: float = 0.1  # rotation step of the projection-histogram search
    heading_bin_m: float = 0.02  # histogram bin of the heading search
    heading_switch_deg: float = 45.0  # a jump beyond this means the major wall changed
    translation_bin_m: float = 0.03  # histogram bin of the translation correlation
    translation_step_m: float = 0.005  # shift step of the correlation
    translation_window_m: float = 0.8  # ± search window of the correlation (no prediction)

    # --- beyond the paper -----------------------------------------------------------------
    use_odometry: bool = True  # odometry (when the scan carries it) is the motion prior
    use_prediction: bool = True  # centre the searches on a motion prediction
    heading_score: HeadingScore = "energy"  # "max" = the paper's hmax(θ); "energy" = Σ h²
    heading_prior_sigma_deg: float = 10.0  # trust in a constant-velocity heading prediction
    heading_prior_sigma_odom_deg: float = 4.0  # trust in an odometry heading prediction ...
    odometry_consistency: bool = True  # ... growing while the heading follows it (`odometry`)
    heading_max_offset_sigmas: float = 3.0  # farther from the prediction: NON_MANHATTAN
    heading_coarse_step_deg: float = 1.0  # coarse 90° search step (then the paper's 0.1°)
    heading_coarse_bin_m: float = 0.05
    heading_coarse_window_sigmas: float = 6.0  # coarse search ± this × prior σ (0: all 90°)
    heading_max_range_m: float = 12.0  # heading uses the points within this range
    heading_tracking_max_turn_deg: float = 2.0  # predicted turn per scan below this, on a
    # measured heading: the fine search alone around the prediction (0: always search) ...
    heading_tracking_max_period_s: float = 0.1  # ... when scans come at least this often
    profile_turn: bool = True  # without odometry: the turn predicted from the range profiles
    profile_turn_min_score: float = 0.5  # share of beams that must agree at that turn
    profile_turn_max_deg: float = 90.0  # ± search of that turn (less between frequent scans)
    profile_turn_min_period_s: float = 0.05  # scans steadily closer than this: not needed
    max_speed_m_s: float = 2.0  # clamp of the constant-velocity model
    max_turn_rate_deg_s: float = 120.0
    max_accel_m_s2: float = 0.5  # bound on the constant-velocity model's change (0: none)
    scan_period_s: float = 0.2  # > 0: constant motion per scan (this nominal period), not time
    period_clip_ratio: float = 2.0  # scan period clipped to [1/r, r] × the recent median
    turn_rate_decay: float = 0.5  # per scan, while the heading is a fallback (not measured)
    translation_window_pred_m: float = 0.4  # ± translation search around the prediction
    translation_window_odom_m: float = 0.25  # ± around an odometry prediction
    bounded_search: bool = True  # windows no wider than 2 × max speed × the scan period
    translation_window_min_m: float = 0.2  # ... but at least this (0.1: 40 Hz drift, 1.9 m)
    translation_prior_sigma_m: float = 0.1  # trust in a constant-velocity prediction (0: none)
    translation_prior_sigma_odom_m: float = 0.06  # trust in an odometry prediction
    translation_prior_carried: bool = True  # ... no narrower than the prediction's own σ
    subbin_refinement: bool = True  # parabolic peak refinement (heading and translation)
    orientation_weighting: bool = True  # wall points vote only on the axis they constrain
    reference: ReferenceMode = "local_map"
    keyframe_distance_m: float = 0.3  # the paper's scan spacing, reused for keyframes
    keyframe_angle_deg: float = 10.0
    keyframe_ambiguous_distance_m: float = 0.0  # > 0: ambiguous matches keyframe only this far
    local_map_keyframes: int = 12  # keyframes kept in the local map
    local_map_radius_m: float = 12.0  # reference points farther than this are ignored
    direction_prior: bool = True  # relative rotation from surface-direction histograms
    direction_window_deg: float = 20.0  # ± search of that rotation around the prediction
    direction_sigma_deg: float = 2.0  # trust in it as the Manhattan heading's prior
    direction_min_contrast: float = 0.1
    direction_line_deviation: float = 0.05  # sparse scans: far collinear points get a direction
    weak_directions: bool = True  # dense scans: ... which only stops them voting along it
    end_directions: bool = True  # dense scans: a wall's last return takes its wall's line
    coverage_cut: bool = True  # current points beyond the reference's coverage do not vote
    field_match: bool = True  # an axis left ambiguous is searched in 2-D (`field_match`)
    dynamic_rejection: bool = True  # points where the previous scan saw free space: moving
    seen_through: SeenThroughParams = field(default_factory=SeenThroughParams)  # (`dynamic`)
    wall_frames: bool = True  # several wall families ("Atlanta world", `frames`) ...
    frames: FrameParams = field(default_factory=FrameParams)  # ... and how they are found
    wall_reanchor_fraction: float = 0.25  # on a relative heading, prior-free walls this strong ...
    wall_reanchor_max_deg: float = 30.0  # ... within this of it make the heading absolute again
    translation_gate_m: float = 0.15  # > 0: correlate only pairs this close on the other axis
    translation_gate_min_points: int = 250  # thinned scan points needed to gate
    translation_gate_heading_deg: float = 0.5  # band widened by range × tan(this)
    translation_gate_min_weight: float = 0.05  # points voting less on an axis are skipped
    translation_gate_sides: bool = True  # pair only faces seen from the same side
    translation_gate_both: bool = False  # gate both axes (default: the less supported one)
    refine_2d: bool = True  # joint 2-D check of the 1-D peak candidates
    refine_2d_gated: bool = False  # run it also after a gated correlation
    previous_scan_fallback: bool = True  # an ambiguous axis tries the previous scan as reference
    previous_scan_min_support: float = 3.0  # ... where this many constraining points suffice
    heading_check: bool = True  # re-anchor the heading quadrant on the local map's geometry
    heading_check_min_turn_deg: float = 4.0  # run it when turning faster than this per scan
    heading_check_max_turn_deg: float = 20.0  # candidates within this of the prediction
    heading_check_window_m: float = 0.4  # ± translation grid of the check
    heading_check_step_m: float = 0.1
    heading_check_points: int = 120  # scan points scored (subsampled)
    heading_check_margin: float = 0.06  # hit-fraction gain needed to change the heading

    # --- degeneracy / ambiguity thresholds --------------------------------------------------
    min_points: int = 20  # fewer valid points than this: DEGENERATE
    min_axis_support: float = 8.0  # weighted points constraining an axis, else AMBIGUOUS
    ambiguity_ratio: float = 0.92  # a second peak this high (relative) means ambiguous
    min_heading_peak_fraction: float = 0.08  # share of points on the major lines
    max_range_used_m: float = 30.0  # the heading/translation ignore points beyond this

    # Pickled by name, not by position (the dataclass default): a checkpoint keeps its values
    # when a later version adds parameters, which take their defaults.
    def __getstate__(self) -> dict[str, object]:
        return fields_by_name(self)

    def __setstate__(self, state: object) -> None:
        if not isinstance(state, dict):
            raise TypeError("estimator parameters pickled by position (an older version)")
        restore_fields(self, state, EstimatorParams())
