"""Configuration: one pydantic section per pipeline component.

``slam2d dump-config`` prints every option with its default and description; the shipped
``configs/default.yaml`` is exactly that output. Sensor facts (beam count, angles, range
limits, no-return value) are never configured: they come from the data.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from slam2d.errors import ConfigError


class _Section(BaseModel):
    """A config section. Changed in code (``cfg.grid.resolution = x``), a bad value is a ConfigError
    naming the key, as from a YAML file. (Built in code, ``SlamConfig(grid={...})`` raises pydantic's
    ValidationError: overriding ``__init__`` would take over the validation of nested sections and
    lose the key path and file name that ``config_from_dict`` reports.)"""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    def __setattr__(self, name, value):
        try:
            super().__setattr__(name, value)
        except ValidationError as e:
            raise _config_error(type(self).__name__, e) from None

    @field_validator("*", mode="before")
    @classmethod
    def _no_bool_for_a_number(cls, value, info):
        """YAML's true/false is no number: pydantic would read ``max_range: true`` as 1.0."""
        kind = cls.model_fields[info.field_name].annotation
        if isinstance(value, bool) and kind in (int, float):
            raise ValueError(f"needs a number, not {str(value).lower()}")
        return value


class RangeFilterConfig(_Section):
    """Which readings local SLAM uses (a processing choice, not a sensor fact)."""

    min_range: float = Field(0.0, ge=0.0, description="Readings closer than this [m] are dropped (the sensor's own range_min always applies).")
    max_range: float = Field(30.0, gt=0.0, description="Hits farther than this [m] are not matched or inserted as hits; the ray up to it is inserted as free space.")
    missing_data_ray_length: float = Field(5.0, ge=0.0, description="No-return beams insert free space up to this length [m] (0 disables), or only up to the nearer of the two returns beside them where those lie on one surface (a dark or glossy patch of a wall returns no echo either); they never insert a hit.")
    voxel_filter_size: float = Field(0.025, ge=0.0, description="Points are thinned to one per square cell of this size [m] before matching (0 disables).")


class GridConfig(_Section):
    """Log-odds probability grid (Cartographer's probability_grid_range_data_inserter)."""

    resolution: float = Field(0.05, ge=0.01, le=1.0, description="Cell size of submaps [m] (at least 1 cm: a laser's noise is about that, and finer cells multiply memory by the square).")
    hit_probability: float = Field(0.55, gt=0.5, lt=1.0, description="Probability that a cell holding a scan endpoint is occupied.")
    miss_probability: float = Field(0.49, gt=0.0, lt=0.5, description="Probability that a cell crossed by a ray is occupied.")
    min_probability: float = Field(0.12, gt=0.0, lt=0.5, description="Lower clamp of cell probabilities.")
    max_probability: float = Field(0.97, gt=0.5, lt=1.0, description="Upper clamp of cell probabilities.")


class SubmapConfig(_Section):
    """Two overlapping active submaps, as in Cartographer."""

    num_range_data: int = Field(90, ge=1, description="Scans inserted into a submap before the next one starts; a submap is finished after twice this many.")
    num_range_data_without_loop_closure: int = Field(
        400, ge=1, description="num_range_data when local SLAM runs alone (--no-loop-closure, loop_closure.enabled false): with no "
        "pose graph to correct drift between submaps, bigger submaps tie revisits to one map; with loop closure, small rigid "
        "submaps let the graph bend.")
    max_travel: float = Field(
        20.0, gt=0.0, description="A submap is also full once the robot travelled this far [m] since it started, so its extent "
        "follows the path, not the scan rate (about num_range_data × motion_filter.max_distance: dense logs fill a submap by "
        "count first, a sparse log with scans a metre apart by distance). Without loop closure it scales like the count "
        "(× num_range_data_without_loop_closure / num_range_data).")


class MotionFilterConfig(_Section):
    """A scan is inserted only when the robot moved enough since the last inserted scan."""

    max_distance: float = Field(0.2, ge=0.0, description="Insert when translation since the last insertion exceeds this [m]: of the matched pose, or of the wheel odometry where the input has it (a match sliding back along a corridor cannot then keep the new ground out of the map).")
    max_angle_deg: float = Field(1.0, ge=0.0, description="Insert when rotation since the last insertion exceeds this [deg].")
    max_time: float = Field(5.0, ge=0.0, description="Insert when this much time [s] passed since the last insertion.")


class RealTimeMatcherConfig(_Section):
    """Olson 2009 real-time correlative scan matcher (local SLAM)."""

    score_grid: Literal["likelihood_field", "probability"] = Field("likelihood_field", description="What a scan is scored against: a likelihood field (Gaussian of the distance to the nearest occupied cell; Olson 2009) or the hit probabilities (Cartographer).")
    likelihood_field_sigma: float = Field(0.1, gt=0.0, le=1.0, description="Standard deviation of the likelihood field [m] (cut at 3 sigma).")
    linear_search_window: float = Field(0.3, gt=0.0, description="Largest half-width of the x/y search window around the predicted pose [m], unless recent trusted matches measured the prediction's error larger: then three times its RMS (scans a metre apart with noisy odometry need no other setting).")
    angular_search_window_deg: float = Field(10.0, gt=0.0, le=180.0, description="Largest half-width of the rotation search window [deg].")
    min_linear_search_window: float = Field(0.05, gt=0.0, description="Half-width of the x/y window when the robot did not move [m]; it grows with the motion since the last scan.")
    min_angular_search_window_deg: float = Field(1.0, gt=0.0, description="Half-width of the rotation window when the robot did not turn [deg].")
    window_motion_fraction: float = Field(0.7, ge=0.0, description="The windows grow by this fraction of the predicted motion since the last scan (odometry error grows with motion); a best pose on the window's edge repeats the search with the largest windows.")
    window_angle_per_metre_deg: float = Field(5.0, ge=0.0, description="The rotation window also grows by this much per metre travelled since the last scan [deg/m]: the heading error of wheel odometry grows with distance, so a log with scans a metre apart needs no other setting.")
    min_relative_score: float = Field(0.8, gt=0.0, le=1.0, description="A match is trusted when its score is at least this fraction of the median score of recent trusted matches and its best pose is not on the edge of the largest window; otherwise the recovery search runs.")
    recovery_linear_window: float = Field(2.0, gt=0.0, description="Recovery: half-width of the x/y window [m] searched by branch-and-bound around each prediction (odometry, constant velocity, no motion) when a match is not trusted.")
    recovery_angular_window_deg: float = Field(45.0, gt=0.0, le=180.0, description="Recovery: half-width of the rotation window [deg]; without odometry at least the fastest turn measured so far times the time since the last trusted match, up to 180 (a turn made while the data paused).")
    max_untrusted_in_a_row: int = Field(3, ge=0, description="A scan whose best pose still lies on the edge of every window searched carries the prediction and is not inserted into the submaps, unless this many scans in a row did (the robot then did move that way): it is then inserted into new submaps, the old ones finished as they were, and the pose graph ties the two by a step as loose as the recovery window. A clear peak that scores low (new ground) is inserted and reported as weak.")
    branch_depth: int = Field(0, ge=0, le=6, description="Levels of the coarse-to-fine search (0 = exhaustive); results equal the exhaustive search on the same lattice.")
    translation_delta_cost_weight: float = Field(0.1, ge=0.0, description="Scores are multiplied by exp(-(w_t·|Δt| + w_r·|Δθ|)²): prefers the predicted pose where the scan alone cannot decide (Cartographer's default 0.1).")
    rotation_delta_cost_weight: float = Field(0.1, ge=0.0, description="w_r of the same penalty [per rad].")
    window_sigmas: float = Field(3.0, ge=0.0, description="The wheel odometry as a prior on the match (Olson 2009's posterior): its translation error is taken as Gaussian, its motion window (min_linear_search_window + window_motion_fraction × the predicted motion, before the largest window's cap) at this many sigma, and each candidate's mean score is multiplied by exp(-d²/(2σ²N)), N the scan's points (the score read as a mean per-point likelihood). Where the scan cannot decide (a corridor seen by a scanner whose range ends inside it: its newest wall ends score higher slid back onto mapped ground) the odometry wins; a clearly better fit anywhere in the window still does. A prediction without odometry gets none, nor does an odometry reading identical to the last scan's (standing still, or a stalled odometry stream); 0 turns it off. Needs branch_depth 0.")
    use_odometry: bool = Field(True, description="Predict each scan's pose from the input's wheel odometry where it has one; false: from the velocity of the recent trusted matches, as for an input without odometry (slam2d run --no-odometry).")

    @model_validator(mode="after")
    def _prior_needs_exhaustive(self):
        if self.window_sigmas > 0 and self.branch_depth > 0:
            raise ValueError("window_sigmas (the odometry prior, on by default) needs branch_depth 0: set "
                             "window_sigmas: 0 for the coarse-to-fine search")
        return self


class RefineConfig(_Section):
    """Continuous refinement below cell size (Gauss-Newton on the interpolated grid, like Cartographer's Ceres matcher)."""

    enabled: bool = Field(True, description="Refine the correlative pose below cell size.")
    occupied_space_weight: float = Field(1.0, gt=0.0, description="Weight of the grid term.")
    translation_weight: float = Field(3.0, ge=0.0, description="Weight pulling x/y toward the correlative pose.")
    rotation_weight: float = Field(10.0, ge=0.0, description="Weight pulling theta toward the correlative pose.")
    max_iterations: int = Field(20, ge=1, description="Gauss-Newton iterations at most.")
    unobserved: Literal["min_probability", "mirrored"] = Field("min_probability", description="What a cell of the submap that no scan has observed reads as in the refinement. min_probability: the grid's lowest probability (Cartographer). A wall seen from one side then reads lower behind it than before it, the interpolated peak lies toward the side it was seen from, and scans are pulled that way: on logs whose cells are seen by a few scans each (scans a metre apart) whole maps come out slightly too small. mirrored: a never-observed cell just behind a surface reads as the surface's observed free side (mirrored across it); others stay at the lowest probability. It removes most of that pull but on the benchmark it helped some sparse logs and cost others (README), so it is not the default.")


class LoopClosureConfig(_Section):
    """Global SLAM: branch-and-bound loop closure (Hess et al. 2016, Sec. V) and the GTSAM pose graph."""

    enabled: bool = Field(True, description="Search loop closures and optimize the pose graph (off = local SLAM only, like --no-loop-closure).")
    background: bool = Field(True, description="Run global SLAM beside local SLAM: loop search on a worker thread, the pose graph solved in a child process, so add_scan returns once local SLAM is done and a run uses a second core. Outputs are the same either way; off = everything on the caller's thread (and gtsam in its process).")
    min_score: float = Field(0.55, gt=0.0, lt=1.0, description="Smallest mean value under the scan's points (of the submap's probabilities or its likelihood field: score_grid) that makes a match a constraint (Cartographer: 0.55, on probabilities), unless min_relative_score lowers it for a submap.")
    min_relative_score: float = Field(0.7, gt=0.0, le=1.0, description="A submap's own nodes, at their own poses, score a mean value that depends on how often its cells were seen (on the probabilities: a log filtered to a scan every 20 cm, or sparse, sees each wall a few times: about 0.6; a dense log about 0.85). A match against it is accepted from this share of that self-score (on the grid it is scored on) when that is below min_score.")
    linear_search_window: float = Field(3.0, gt=0.0, description="Largest half-width of the x/y window around the estimated pose [m]. Each search covers the drift bound between the node and the submap (consistency_drift per metre of local SLAM linking them through the optimized graph, plus the doubt of every step local SLAM could not vouch for on the way: a recovered pose the distance to the pose it replaced, a forced one the recovery window, a weak match the standard deviations of its score surface), at least margin_window; where the bound exceeds this window, the wide search takes over.")
    angular_search_window_deg: float = Field(15.0, gt=0.0, le=180.0, description="Largest half-width of the rotation window [deg] (the drift bound's rotation, at least margin_window_deg).")
    score_grid: Literal["auto", "probability", "likelihood_field"] = Field("auto", description="What a loop match is scored against: a finished submap's hit probabilities (Cartographer), or its likelihood field (a Gaussian of the distance to its nearest surface, σ = real_time_matcher.likelihood_field_sigma), which reads as sharp on a wall seen by two scans as on one seen by a hundred. On a submap whose cells were each seen a few times, the probabilities score a scan nearly the same at its true pose and a metre off, and verification rejects the match as ambiguous. auto: the field for a submap whose own nodes score low enough on its probabilities that min_relative_score lowers its threshold, the probabilities otherwise. The refinement below cell size and the covariance of an accepted match use the probabilities either way.")
    branch_depth: int = Field(6, ge=1, le=8, description="Precomputation grids of widths 1 … 2^depth cells.")
    voxel_filter_size: float = Field(0.05, ge=0.0, description="Scan points are thinned to one per cell of this size for loop-closure matching [m].")
    adaptive_voxel_min_points: int = Field(100, ge=0, description="Then the coarsest voxel filter (up to adaptive_voxel_max_length) that keeps this many points thins them further (Cartographer's loop-closure adaptive voxel filter; 0 disables): a search costs time in proportion to the points. The wide search thins a finished submap's content the same way.")
    adaptive_voxel_max_length: float = Field(0.9, gt=0.0, description="Largest cell of the adaptive voxel filter for loop-closure points and the wide search's submap content [m].")
    sample_every_n_nodes: int = Field(5, ge=1, description="Every n-th node is matched against nearby finished submaps (or sooner, once the robot travelled n × motion_filter.max_distance since the last sampled node, so sparse logs are sampled as densely per metre as dense ones).")
    max_submaps_per_node: int = Field(3, ge=1, description="A sampled node is matched against at most this many nearest finished submaps.")
    max_searches_per_submap: int = Field(8, ge=0, description="A newly finished submap is matched against at most this many earlier nearby nodes.")
    exclude_recent_submaps: int = Field(2, ge=0, description="The newest finished submaps are left to local SLAM.")
    max_constraint_distance: float = Field(10.0, gt=0.0, description="A sampled node is matched against the finished submaps whose content centre lies this close to its estimate [m], nearest first; where there is none, against those built from a pose this close (a submap seeing far down a corridor has its centre far from where the robot stood).")
    min_margin: float = Field(0.02, ge=0.0, description="A match is ambiguous, and rejected, unless its score beats the best separated local maximum around it (exhaustive search in the margin window) by this much.")
    margin_window: float = Field(0.6, gt=0.0, description="Half-width of the x/y window searched exhaustively around a refined loop match, for its margin and covariance [m].")
    margin_window_deg: float = Field(2.0, gt=0.0, description="Half-width of that window's rotation [deg].")
    margin_exclusion: float = Field(0.2, gt=0.0, description="Local maxima closer than this to the peak [m] (and closer than margin_exclusion_deg) are the peak itself.")
    margin_exclusion_deg: float = Field(1.0, gt=0.0, description="... [deg].")
    estimate_check: bool = Field(True, description="A match that moves a node at least margin_exclusion from where the pose graph places it must also score higher than that estimate on the scan points both poses put on cells the submap observed. A scan that sees past the mapped part of a submap scores higher slid back onto mapped ground (its far end then lands on walls already mapped, at the true pose on unobserved cells), so the plain score can prefer a wrong pose with a clear margin. Not applied to the wide search's node matches, which start from a coarse match rather than the estimate.")
    loop_sigma_translation: float = Field(0.02, gt=0.0, description="Floor on the standard deviation of a loop constraint's translation (its covariance comes from the match's score surface) [m].")
    loop_sigma_rotation_deg: float = Field(0.3, gt=0.0, description="Floor on the standard deviation of a loop constraint's rotation [deg].")
    consistency_check: bool = Field(True, description="Before each optimization, remove loops that contradict other loops through the local chain (pairwise cycle consistency; independent of the solution).")
    consistency_max_chain: float = Field(30.0, gt=0.0, description="Two loops are compared when the local path between their anchors plus between their nodes is at most this long [m].")
    consistency_translation: float = Field(0.3, gt=0.0, description="Allowed translation error of a two-loop cycle [m], plus consistency_drift times the chain length and the doubt of every step on it that local SLAM could not vouch for (a recovered or forced pose, a weak match).")
    consistency_rotation_deg: float = Field(2.0, gt=0.0, description="Allowed rotation error of a two-loop cycle [deg], plus consistency_drift_deg per metre of chain and the rotation doubt of its steps.")
    consistency_drift: float = Field(0.03, ge=0.0, description="Local SLAM translation drift allowed per metre of chain (three times local_drift: a 3-sigma bound of the drift model the pose graph uses); it also sizes the loop search windows.")
    consistency_drift_deg: float = Field(0.3, ge=0.0, description="Local SLAM rotation drift allowed per metre of chain [deg] (three times local_drift_deg).")
    consistency_min_support: int = Field(0, ge=0, description="A loop needs at least this many consistent partner loops to stay (0: an unconfirmed loop is left to the residual check).")
    min_local_sigma_translation: float = Field(0.01, gt=0.0, description="Floor on the translation sigma of node-in-submap constraints from the local matcher's covariance [m].")
    min_local_sigma_rotation_deg: float = Field(0.1, gt=0.0, description="Floor on their rotation sigma [deg].")
    local_drift: float = Field(0.01, ge=0.0, description="A node-in-submap constraint's translation sigma grows by this much per metre the robot travelled between the submap's first node and the node [m/m]: the submap itself was built by local SLAM along that path and drifted with it, which the match's score surface does not see.")
    local_drift_deg: float = Field(0.1, ge=0.0, description="... and its rotation sigma by this much per metre the view moved [deg/m]: the metres travelled plus the radians turned times the mean range of a hit (a turn on the spot sweeps the scan's content past as a drive of that length does, and there local SLAM's heading drifts while it covers no path).")
    wide_search: bool = Field(True, description="When a submap is finished, match its content against older submaps nearby that the drift bound (consistency_drift, consistency_drift_deg times the shortest local-SLAM path between them, loops as shortcuts) may have carried beyond the regular window; at most max_constraint_distance and 180°. Two of its nodes must then pass verification and agree.")
    wide_heading_constraints: bool = Field(True, description="A node match of the wide search that verification rejects as ambiguous in position only (a corridor: poses along it score alike) but whose heading it fixes (every other heading in the verification window scores at least min_margin less) adds its heading alone to the pose graph: a loop constraint whose translation carries no information, checked on its rotation residual. The wide search runs where local SLAM may have drifted beyond the regular window, and there a turn local SLAM got a few degrees wrong carries the map away; a corridor still measures the heading. constraints.jsonl shows it under the record's heading_constraint.")
    final_search: bool = Field(True, description="Before the final optimization, search again every sampled node whose estimate has since left the window it was searched in (a loop closed later can move a stretch of the trajectory by more than that window), against the finished submaps now near it whose earlier search did not cover its estimate; repeated while a round closes loops (at most three rounds), with at most as many searches as the run made before it, the nodes that moved farthest first.")
    gnc_final: bool = Field(True, description="Before the final optimization, remove loops that graduated non-convexity (gtsam GncLMOptimizer, every local constraint a known inlier) weighs as outliers.")
    huber_scale: float = Field(5.0, gt=0.0, description="Huber threshold (in standard deviations) of the robust loop-constraint noise.")
    max_residual_translation: float = Field(0.2, gt=0.0, description="A loop constraint whose residual after optimization exceeds this [m] is removed.")
    max_residual_rotation_deg: float = Field(1.0, gt=0.0, description="... or this [deg].")
    residual_exempt_support: int = Field(2, ge=0, description="... unless it closes consistent cycles with at least this many other loops through the local chain and contradicts none (consistency_check): its residual then shows local SLAM's chain bending less than it drifted, not a false loop. 0: every loop is judged by its residual.")
    optimize_every_n_nodes: int = Field(90, ge=1, description="Optimize the pose graph after this many new nodes (and once at the end).")
    incremental: bool = Field(True, description="Optimize with iSAM2 (Kaess et al. 2012: only the part of the graph that changed since the last solve) instead of batch Levenberg-Marquardt over the whole graph.")
    final_batch: bool = Field(False, description="With incremental, solve the final graph by batch Levenberg-Marquardt instead (slower; it did not change accuracy where measured).")
    refine_occupied_weight: float = Field(20.0, gt=0.0, description="Refinement of loop matches: grid weight (Cartographer: 20).")
    refine_translation_weight: float = Field(10.0, ge=0.0, description="Refinement of loop matches: translation weight (Cartographer: 10).")
    refine_rotation_weight: float = Field(1.0, ge=0.0, description="Refinement of loop matches: rotation weight (Cartographer: 1).")


class FinalRefinementConfig(_Section):
    """Global SLAM's last step: every scan is refined once more against the map of the optimized pose graph."""

    enabled: bool = Field(True, description="After the final optimization, refine every scan's pose (continuous refinement only) against the map built from the optimized nodes.")
    translation_weight: float = Field(3.0, ge=0.0, description="Weight pulling x/y toward the optimized pose.")
    rotation_weight: float = Field(10.0, ge=0.0, description="Weight pulling theta toward the optimized pose.")


class MapConfig(_Section):
    """The exported occupancy map (ROS map_server PGM + YAML, and PNG)."""

    resolution: float = Field(0.05, ge=0.01, le=1.0, description="Cell size of the exported map [m] (at least 1 cm).")
    occupied_thresh: float = Field(0.65, gt=0.0, lt=1.0, description="map.yaml occupied_thresh (how map_server reads the image's pixels).")
    free_thresh: float = Field(0.196, gt=0.0, lt=1.0, description="map.yaml free_thresh.")
    cells: Literal["evidence", "thresholds"] = Field(
        "evidence", description="How a cell becomes occupied or free in the image. evidence: by the balance of what the scans saw there: occupied once its hits outweigh its misses by at least about one hit of the sensor model (its probability beyond halfway from 0.5 to grid.hit_probability), free once its misses outweigh its hits by about one miss (beyond halfway to grid.miss_probability), as occupancy maps by hit counts (GMapping, Karto) decide; a log with scans a metre apart then shows the free space it saw. thresholds: by occupied_thresh / free_thresh on the cell's probability, as map_saver does on a probability map (with Cartographer's update rates a cell turns free only after dozens of misses: dense logs only).")

    @model_validator(mode="after")
    def _thresholds(self):
        if self.free_thresh >= self.occupied_thresh:
            raise ValueError("free_thresh must be below occupied_thresh")
        return self

    def cell_thresholds(self, grid: GridConfig) -> tuple[float, float]:
        """(occupied above, free below): the probabilities that classify a cell of the image (``cells``)."""
        if self.cells == "thresholds":
            return self.occupied_thresh, self.free_thresh
        return 0.5 * (0.5 + grid.hit_probability), 0.5 * (0.5 + grid.miss_probability)


class SlamConfig(_Section):
    range_filter: RangeFilterConfig = Field(default_factory=RangeFilterConfig, description="Range filtering of each scan.")
    grid: GridConfig = Field(default_factory=GridConfig, description="Submap grids.")
    submaps: SubmapConfig = Field(default_factory=SubmapConfig, description="Submap life cycle.")
    motion_filter: MotionFilterConfig = Field(default_factory=MotionFilterConfig, description="Insertion gate.")
    real_time_matcher: RealTimeMatcherConfig = Field(default_factory=RealTimeMatcherConfig, description="Local scan matching.")
    refine: RefineConfig = Field(default_factory=RefineConfig, description="Sub-cell refinement.")
    loop_closure: LoopClosureConfig = Field(default_factory=LoopClosureConfig, description="Global SLAM.")
    final_refinement: FinalRefinementConfig = Field(default_factory=FinalRefinementConfig, description="Final trajectory refinement (global SLAM).")
    map: MapConfig = Field(default_factory=MapConfig, description="Exported map.")

    @field_validator("grid")
    @classmethod
    def _grid(cls, g: GridConfig):
        if not (g.min_probability < g.miss_probability < 0.5 < g.hit_probability < g.max_probability):
            raise ValueError("need min_probability < miss_probability < 0.5 < hit_probability < max_probability")
        return g

    @property
    def max_angle_rad(self) -> float:
        return math.radians(self.motion_filter.max_angle_deg)


def _format_error(err: dict) -> str:
    key = ".".join(str(p) for p in err.get("loc", ()))
    if err.get("type") == "extra_forbidden":
        return f"unknown key '{key}'"
    return f"key '{key}': {err.get('msg')}"


def _config_error(source: str, e: ValidationError) -> ConfigError:
    more = f" (and {e.error_count() - 1} more)" if e.error_count() > 1 else ""
    return ConfigError(f"{source}: {_format_error(e.errors()[0])}{more}")


def config_from_dict(data: dict[str, Any] | None, source: str = "config") -> SlamConfig:
    try:
        return SlamConfig.model_validate(data or {})
    except ValidationError as e:
        raise _config_error(source, e) from None


def load_config(path: str | Path | None) -> SlamConfig:
    """Load a YAML config; missing keys take defaults, unknown keys are an error."""
    if path is None:
        return SlamConfig()
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such config file") from None
    except OSError as e:
        raise ConfigError(f"{path}: cannot read: {e.strerror}") from None
    except UnicodeDecodeError as e:
        raise ConfigError(f"{path}: not a text file (byte {e.start} is not UTF-8)") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f":{mark.line + 1}" if mark is not None else ""
        raise ConfigError(f"{path}{where}: not valid YAML ({getattr(e, 'problem', e)})") from None
    if data is not None and not isinstance(data, dict):
        raise ConfigError(f"{path}: the top level must be a mapping of sections")
    return config_from_dict(data, str(path))


def dump_config(cfg: SlamConfig | None = None) -> str:
    """Every option with its value and description, as commented YAML."""
    cfg = cfg or SlamConfig()
    lines = ["# slam2d configuration: every option, its default and what it does.",
             "# Generated by `slam2d dump-config`; sensor facts come from the data, not from here.", ""]
    for name, finfo in SlamConfig.model_fields.items():
        section = getattr(cfg, name)
        lines.append(f"# {finfo.description}")
        lines.append(f"{name}:")
        for key, sinfo in type(section).model_fields.items():
            lines.append(f"  # {sinfo.description}")
            value = yaml.safe_dump({key: getattr(section, key)}, default_flow_style=True).strip()[1:-1]
            lines.append(f"  {value}")
        lines.append("")
    return "\n".join(lines)
