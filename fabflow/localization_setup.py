"""The project's localization sections: UWB, total station, LiDAR ICP and the integrity policy.

Each model is one method's setup as the project file gives it (validated with
pydantic, units in the field docs); :class:`fabflow.project.Localization`
chooses the method and holds them.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import (
    Field,
    model_validator,
)

from fabflow.schema import (
    Count,
    ExistingPath,
    Fraction,
    ModelPath,
    NonNegativeFloat,
    PoseSpec,
    PositiveFloat,
    Real,
    StrictModel,
    Switch,
    Vec3,
)
from fabflow.sensors.lidar_errors import LidarErrorModel
from fabflow.sensors.uwb import UwbErrorModel


class UwbSetup(StrictModel):
    """Ultra-wideband ranging: anchors in the UWB frame and the ranging model."""

    anchors: dict[str, Vec3] = {}
    """Anchor positions in the UWB frame (metres). Given: checked against every
    station; absent: planned (:mod:`fabflow.localize.anchors`)."""
    anchor_count: Annotated[int, Field(ge=3, le=40)] | None = None
    """How many anchors to plan (default: the fewest that reach ``target_sigma``)."""
    anchor_height: tuple[PositiveFloat, PositiveFloat] = (1.0, 3.2)
    """Range of the planned anchors' heights above the ground (metres)."""
    anchor_spacing: Annotated[float, Field(ge=0.25, le=10.0)] = 1.0
    """Grid spacing of the candidate anchor positions on the site (metres)."""
    target_sigma: PositiveFloat | None = None
    """Largest predicted XY sigma of the platform at any station (metres; the
    Cramer-Rao bound of one ranging epoch, :mod:`fabflow.localize.anchors`); default
    2 x the range sigma at 1 m, ``sigma`` and ``multipath_sigma`` together (a
    horizontal dilution of precision of 2)."""
    T_world_uwb: PoseSpec = PoseSpec()
    estimator: Literal["ls", "wls", "wls-t", "eskf"] = "wls-t"
    sigma: PositiveFloat = UwbErrorModel.sigma_1m
    """Range noise standard deviation at 1 m (metres): white, every range its own.
    0.033 (the default) is the DW1000 chip's stated precision (10 cm at three
    sigma; :class:`~fabflow.sensors.uwb.UwbErrorModel`); with the multipath below it
    reproduces paper 003's static tables and, unfitted, its moving ones
    (``benchmarks/sensor_models.py``)."""
    sigma_growth: Annotated[NonNegativeFloat, Field(le=1.0)] = UwbErrorModel.growth
    """Increase of ``sigma`` per metre of range (m/m; 0 by default, at most 1)."""
    multipath_sigma: NonNegativeFloat = 0.035
    """Standard deviation at 1 m (metres) of the range error multipath gives each
    tag-anchor link where the tag stands (:mod:`fabflow.sensors.uwb_multipath`): it
    stays while the platform stands, so the dwell does not average it out, and
    grows by a fifth of it per metre of range. Simulated, and in the covariance of
    every station fix. 0.035 (the default) reproduces paper 003's real-site tables:
    fitted on its static tables, checked on its moving ones
    (``benchmarks/sensor_models.py``); 0 simulates an open, clean site."""
    multipath_length: PositiveFloat = 0.5
    """How far (metres) a tag moves before its multipath error changes (the
    simulated field's correlation length; not fitted, see the benchmark)."""
    material_delay: Annotated[NonNegativeFloat, Field(le=3.0)] = 0.0
    """Excess range per metre of built material a tag-anchor line of sight passes
    through (``sqrt(eps_r) - 1``; 0.41 for wood of relative permittivity 2). Simulated
    on the links the structure blocks; the estimate subtracts the excess it predicts
    from the design and counts the spread below in the link's variance. 0: off."""
    material_delay_spread: Annotated[NonNegativeFloat, Field(le=1.0)] = 0.25
    """Relative standard deviation of ``material_delay`` at one site (moisture,
    species)."""
    rate_hz: PositiveFloat = 60.0
    imu_rate_hz: PositiveFloat = 100.0
    tags: Annotated[list[Vec3], Field(min_length=1)] = [(0.8, 0.0, 1.5), (-0.8, 0.0, 1.5)]
    """UWB tag lever arms in the platform frame (metres)."""
    dwell_s: PositiveFloat = 5.0
    """How long the platform stands still measuring at each station (seconds)."""
    calibration: dict[str, tuple[Real, PositiveFloat]] = {}
    """Ranging calibration per anchor id: (offset a in metres, scale b) of the fit
    measured = a + b * true; ranges are corrected as (measured - a) / b."""
    calibration_sigma: NonNegativeFloat = 0.01
    """Range error the calibration leaves per anchor (metres, shared by all its
    ranges); enters the covariance and the tests of measured ranges (a simulated
    calibration campaign knows its own)."""

    def error_model(self) -> UwbErrorModel:
        """The range error model of this setup (simulation and covariance alike)."""
        return UwbErrorModel(
            sigma_1m=self.sigma,
            growth=self.sigma_growth,
            multipath_field_sigma=self.multipath_sigma,
            multipath_field_length=self.multipath_length,
            material_delay=self.material_delay,
            material_delay_spread=self.material_delay_spread,
        )

    @model_validator(mode="after")
    def _calibrated_anchors_exist(self) -> UwbSetup:
        unknown = sorted(set(self.calibration) - set(self.anchors))
        if unknown:
            raise ValueError(f"'calibration' names unknown anchors {unknown}")
        if 0 < len(self.anchors) < 3:
            raise ValueError("'anchors' needs at least 3 anchors (or none, to have them planned)")
        if self.anchor_height[0] > self.anchor_height[1]:
            raise ValueError("'anchor_height' must be (lowest, highest)")
        return self


class TotalStationSetup(StrictModel):
    """A robotic total station measuring prisms on the robot."""

    instrument: Literal["leica_ms50", "hilti_pos150", "custom"] = "leica_ms50"
    distance_sigma_mm: PositiveFloat | None = None
    distance_ppm: NonNegativeFloat | None = None
    angle_sigma_arcsec: PositiveFloat | None = None
    prism_centring_mm: Annotated[NonNegativeFloat, Field(le=100.0)] = 0.0
    """Standard deviation per axis of a sighted prism's optical centre off its point
    (millimetres, per sighting): about 1 for a 360 deg prism seen from changing
    sides (manufacturers state about 2 mm for such prisms), 0.5 for a round prism facing the
    instrument. Simulated, and in every point's covariance. The default stays 0:
    with 1 mm a set-up rarely localizes the base to the planner's 0.1 of a 10 mm
    tolerance (docs/total_station.md)."""
    atmosphere_ppm: Annotated[NonNegativeFloat, Field(le=1000.0)] = 0.0
    """Standard deviation of the scale error the atmospheric correction leaves (ppm;
    about 1 per degree Celsius or 3 hPa entered wrongly; 10 or more when no
    temperature and pressure are entered). Simulated per set-up, and in the
    distances' variance."""
    T_world_instrument: PoseSpec | None = None
    """Where the instrument stands (world). Given: checked against every visit and used
    for all of them; absent: the set-ups are planned (:mod:`fabflow.localize.setups`)."""
    tripod_height: tuple[PositiveFloat, PositiveFloat] = (1.3, 1.8)
    """Range of trunnion heights above the ground of a planned set-up (metres)."""
    setup_spacing: Annotated[float, Field(ge=0.1, le=5.0)] = 0.5
    """Grid spacing of the candidate set-up positions on the site (metres)."""
    max_range: Annotated[float, Field(ge=5.0, le=1000.0)] | None = None
    """Farthest a sighted prism or control point may be from a set-up (metres): the
    instrument's tracking range with the prism used, or a site rule keeping sights short
    across traffic and stacked material. ``None``: no limit."""
    stationing: Literal["control_points", "robot_points"] = "control_points"
    """How each planned set-up is registered to the site: free stationing on the fixed
    ``control_points`` (paper 001, Procedure B), or on prisms the robot holds at its last
    visit, their world positions from its last localization (Procedure A: errors carry
    over from set-up to set-up). The first set-up always uses the control points."""
    control_points: dict[str, Vec3] = {}
    """Surveyed control points (world, metres) for free stationing; default: the four
    corners of the site, 0.3 m above the ground."""
    control_sigma_mm: NonNegativeFloat = 1.0
    """Standard deviation of the control points' survey, per axis (mm)."""
    procedure: Literal["three_point", "arbitrary"] = "arbitrary"
    n_points: Annotated[Count, Field(ge=3, le=50)] = 4
    observations: ExistingPath | None = None
    """Optional measured observations (CSV or Leica GSI); simulated when absent."""
    robot_points: ExistingPath | None = None
    """Prism positions in the base frame (CSV point_id,x_m,y_m,z_m) matching ``observations``."""
    instrument_height: Real = 0.0
    """Trunnion height above ``T_world_instrument`` (metres; 0 when the pose is the trunnion)."""
    three_point_step: PositiveFloat = 0.8
    """Distance d of the three-point procedure: P1, P1 + d x, P1 + d y (metres)."""
    z_min: Real = 0.1
    """Lowest allowed prism height above the arm base (metres)."""
    tool_half_extents: tuple[PositiveFloat, PositiveFloat, PositiveFloat] = (0.15, 0.15, 0.2)
    """Half sizes of the tool's bounding box around the prism, kept clear of the structure."""
    setup_sigma_mm: NonNegativeFloat = 0.0
    """Uncertainty of the instrument's set-up position, per axis (mm)."""
    setup_sigma_arcsec: NonNegativeFloat = 0.0
    """Uncertainty of the instrument's set-up orientation (Hz zero) about the vertical (")."""

    @model_validator(mode="after")
    def _custom_and_files(self) -> TotalStationSetup:
        if self.instrument == "custom" and None in (
            self.distance_sigma_mm,
            self.distance_ppm,
            self.angle_sigma_arcsec,
        ):
            raise ValueError(
                "instrument 'custom' needs distance_sigma_mm, distance_ppm and angle_sigma_arcsec"
            )
        if (self.observations is None) != (self.robot_points is None):
            raise ValueError("'observations' and 'robot_points' must be given together")
        if self.tripod_height[0] > self.tripod_height[1]:
            raise ValueError("'tripod_height' must be (lowest, highest)")
        if 0 < len(self.control_points) < 2:
            raise ValueError("'control_points' needs at least 2 points for free stationing")
        return self


class IcpSetup(StrictModel):
    """LiDAR scan-to-map localization."""

    map: ModelPath | None = None
    """A point-cloud map (PLY/XYZ) in the world frame; a simulated site scan when absent."""
    T_platform_lidar: PoseSpec = PoseSpec(xyz=(0.9, 0.0, 1.2))
    voxel_size: PositiveFloat = 0.05
    """Voxel grid of the scan for the fine ICP stage (metres)."""
    map_voxel_size: PositiveFloat = 0.03
    """Voxel grid the map is downsampled on (metres; paper 002, Table 3)."""
    max_correspondence_distance: PositiveFloat = 0.5
    """Last correspondence distance of the coarse ICP stage; the first is 4 times it."""
    min_fitness: Annotated[Fraction, Field(gt=0)] = 0.25
    """Required share of scan points matching the map. Low, because from inside the
    growing structure (not in the map) most of a scan is new; wrong poses are caught by
    ``min_structure_fitness``."""
    min_structure_fitness: Fraction = 0.5
    """Required fitness of scan points on walls and columns (not the ground)."""
    max_rmse: PositiveFloat = 0.03
    """Largest accepted inlier RMSE (metres)."""
    map_as_built: Switch = True
    """Add the blocks built so far (at their design poses) to the map before localizing."""
    as_built_sigma: Annotated[NonNegativeFloat, Field(le=0.1)] = 0.003
    """How far (metres per axis) the blocks added to the map may stand off their design
    poses: the localization of the visits that placed them and the arm's repeatability.
    Every fix's covariance counts it for the map points it matches on those blocks.
    3 mm: what the cabin's simulated ICP-localized runs place to (1.4 mm RMS in 3D),
    with room for a coarser localization of the visits before."""
    beam_divergence_mrad: Annotated[NonNegativeFloat, Field(le=50.0)] = 3.0
    """Full beam divergence of the LiDAR (milliradians): a surface seen obliquely
    spreads the return over the beam's footprint (:mod:`fabflow.sensors.lidar_errors`).
    Simulated."""
    max_incidence_deg: Annotated[PositiveFloat, Field(le=90.0)] = 85.0
    """Returns from surfaces seen more obliquely than this are too weak and dropped
    (degrees). Simulated."""
    channel_bias_sigma: Annotated[NonNegativeFloat, Field(le=0.2)] = 0.01
    """Standard deviation of the range offset each laser channel keeps over a run
    (metres): simulated, and in the covariance of every scan fix. 0.01 (the default)
    reproduces paper 000's moving end-effector (ICP RMSE 0.54 cm against its 0.58;
    fitted there, ``benchmarks/sensor_models.py``); its table I, a stationary
    sensor outdoors at other times of day, errs 2-5 times as much as this model
    gives."""
    map_drift: Switch = False
    """Build the simulated map as a mapping run builds it: its scans registered one
    after the other, so it drifts by what each registration errs (about a millimetre
    on the simulated site), and every fix's covariance counts the map's error
    (``ScanMap.map_covariance``). ``false`` (the default, and cheaper: no
    registrations): the scans at their true poses (their range errors stay in
    the map, not in the covariance). Simulated."""

    def lidar_errors(self) -> LidarErrorModel:
        """The range error model of this setup's LiDAR (simulation and covariance alike)."""
        return LidarErrorModel(
            channel_bias_sigma=self.channel_bias_sigma,
            beam_divergence=self.beam_divergence_mrad / 1000.0,
            max_incidence_deg=self.max_incidence_deg,
        )


class IntegrityPolicy(StrictModel):
    """How every base pose is tested, and what happens to one that fails.

    Every localization is an adjustment with a global test, w-tests of the
    observations that may be wrong (a prism, an anchor, a range) and a
    protection level (docs/integrity.md). A pose is also checked against the
    station the platform was sent to: farther off than the parking accuracy
    allows means a wrong map, a wrong anchor survey or a wrong station.
    """

    alpha: Annotated[Fraction, Field(gt=0, lt=0.5)] = 0.001
    """Significance level of the tests: the false-alarm probability of one visit."""
    on_failure: Literal["refuse", "warn"] = "refuse"
    """``refuse``: a failed visit stops the build (exit 2); ``warn``: the build goes
    on, the failed visit is reported and gets no program."""
    parking_sigma: NonNegativeFloat | None = None
    """Standard deviation of the platform's parking position per axis (metres), for
    the check against the planned station; default ``simulation.driving_error``."""
    parking_sigma_deg: NonNegativeFloat | None = None
    """The same for the heading (degrees); default
    ``simulation.driving_heading_error_deg``."""
