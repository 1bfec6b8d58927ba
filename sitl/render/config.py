"""What the simulated camera is and what the world looks like: strict, frozen pydantic models.

``CameraModel`` is the sensor (D435i-like defaults). ``VisualConfig`` is the scene: light, weather,
structures, the leader's look. A scenario TOML's opaque ``[visual]`` table validates into
``VisualConfig`` (:func:`visual_from_mapping`), so unknown keys and out-of-range values fail loudly.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, Literal

from pydantic import AliasChoices, ConfigDict, Field, ValidationError, model_validator

from companion.kernel.camera import Intrinsics
from companion.kernel.config import Section, format_validation_error
from companion.kernel.errors import ConfigError

RGB = tuple[float, float, float]

Airframe = Literal["f450", "phantom", "racer", "heavy", "micro", "hexa"]
#: Motor-to-motor diagonal of each airframe, m (a 450-class frame is 0.45).
AIRFRAME_SPAN_M: dict[str, float] = {
    "f450": 0.45,
    "phantom": 0.35,
    "racer": 0.22,
    "heavy": 0.90,
    "micro": 0.12,
    "hexa": 0.55,
}


class CameraModel(Section):
    """The simulated RGB-D sensor: an Intel RealSense D435i's colour camera with depth aligned to it.

    Stereo depth noise follows the D400 model ``sigma_z = z^2 * subpixel / (f * baseline)``, applied as
    Gaussian noise on disparity (so the error distribution is skewed at range as a real matcher's is).
    """

    width_px: int = Field(640, ge=32, le=4096)
    height_px: int = Field(480, ge=32, le=4096)
    rate_hz: float = Field(30.0, gt=0, le=240)
    hfov_deg: float = Field(69.0, gt=10, lt=170)
    depth_min_m: float = Field(0.3, gt=0)
    depth_max_m: float = Field(10.0, gt=0)
    baseline_m: float = Field(0.050, gt=0)
    subpixel_px: float = Field(0.08, ge=0)
    #: Spatial correlation of the stereo noise (Gaussian sigma), px: a block matcher smears its errors.
    depth_noise_corr_px: float = Field(0.8, ge=0)
    depth_noise: bool = True
    #: Zeros at stereo shadows and depth edges, on low texture and out of range, as a D435 reports them.
    depth_holes: bool = True
    colour_noise: bool = True
    motion_blur: bool = True
    #: Longest exposure before analog gain takes over (auto exposure), s.
    exposure_max_s: float = Field(1.0 / 60.0, gt=0)

    @model_validator(mode="after")
    def _range_ordered(self) -> CameraModel:
        if self.depth_max_m <= self.depth_min_m:
            raise ValueError("depth_max_m must exceed depth_min_m")
        return self

    @property
    def intrinsics(self) -> Intrinsics:
        """Pinhole intrinsics (square pixels, centred principal point)."""
        return Intrinsics.from_hfov(self.width_px, self.height_px, self.hfov_deg)

    @property
    def focal_baseline_px_m(self) -> float:
        """F * B, px*m: disparity in px is this divided by depth in m."""
        return self.intrinsics.fx_px * self.baseline_m


class LeaderLook(Section):
    """How the leader quad-X looks. ``None`` colours take the airframe's usual livery."""

    airframe: Airframe = "f450"
    #: Motor-to-motor diagonal, m; None = the airframe's usual size.
    span_m: float | None = Field(None, gt=0.05, le=3.0)
    body_rgb: RGB | None = None
    arm_rgb: RGB | None = None
    accent_rgb: RGB | None = None
    prop_rgb: RGB | None = None
    rotor_rpm: float = Field(6000.0, ge=0)

    @property
    def resolved_span_m(self) -> float:
        return self.span_m if self.span_m is not None else AIRFRAME_SPAN_M[self.airframe]


class OccluderSpec(Section):
    """One structure placed on purpose (a scenario's occluder).

    Buildings, trees, poles and walls stand on the ground below ``p_ned_m``; a ``branch`` is a box
    floating where ``p_ned_m`` says (z up is negative). Size either as ``size_m`` (x north, y east, z
    height before yaw; for trees x is the crown diameter, for poles the radius) or, for trees and
    poles, as ``radius_m`` + ``height_m`` (the scenario files' shorthand).
    """

    model_config = ConfigDict(frozen=True, extra="forbid", populate_by_name=True)

    kind: Literal["building", "tree", "conifer", "pole", "wall", "branch"]
    #: Position in local NED, m (alias ``ned_m``).
    p_ned_m: tuple[float, float, float] = Field(validation_alias=AliasChoices("p_ned_m", "ned_m"))
    size_m: tuple[float, float, float] | None = None
    radius_m: float | None = Field(None, gt=0)
    height_m: float | None = Field(None, gt=0)
    yaw_deg: float = 0.0
    rgb: RGB | None = None

    @model_validator(mode="after")
    def _one_size(self) -> OccluderSpec:
        shorthand = self.radius_m is not None or self.height_m is not None
        if self.size_m is not None and shorthand:
            raise ValueError("give size_m or radius_m + height_m, not both")
        if self.size_m is None and (self.radius_m is None or self.height_m is None):
            raise ValueError("needs size_m, or radius_m and height_m")
        if shorthand and self.kind not in ("tree", "conifer", "pole"):
            raise ValueError(f"radius_m + height_m describe trees and poles, not a {self.kind}")
        return self

    @property
    def resolved_size_m(self) -> tuple[float, float, float]:
        if self.size_m is not None:
            return self.size_m
        assert self.radius_m is not None  # noqa: S101 (validated)
        assert self.height_m is not None  # noqa: S101
        if self.kind == "pole":
            return (self.radius_m, 1.6, self.height_m)
        return (2.0 * self.radius_m, 2.0 * self.radius_m, self.height_m)


class VisualConfig(Section):
    """The scene around the vehicles: light, sky, fog, ground, structures and the leader's look.

    Everything random here (structure layout, cloud shapes, ground patches) derives from ``seed``, so a
    scenario renders identically on every run.
    """

    seed: int = Field(0, ge=0)
    time_of_day: Literal["day", "dusk"] = "day"
    #: Sun elevation above the horizon, deg; None takes 45 by day and 4 at dusk.
    sun_elevation_deg: float | None = Field(None, ge=-5.0, le=90.0)
    #: Sun azimuth, deg clockwise from north.
    sun_azimuth_deg: float = 135.0
    #: Fraction of the sky covered by cloud: 0 clear, 1 overcast.
    cloud_cover: float = Field(0.3, ge=0.0, le=1.0)
    #: Extinction of the fog, 1/m (meteorological visibility is about 3 / density); alias fog_density.
    fog_density_per_m: float = Field(
        0.0008, ge=0.0, le=0.2, validation_alias=AliasChoices("fog_density_per_m", "fog_density")
    )
    #: Colour of the fog (linear RGB); None takes the horizon's. Alias fog_color.
    fog_rgb: RGB | None = Field(None, validation_alias=AliasChoices("fog_rgb", "fog_color"))
    #: Ground materials in use, mixed in large patches.
    ground_materials: tuple[Literal["grass", "field", "dirt", "asphalt", "gravel", "snow"], ...] = (
        "grass",
        "field",
        "dirt",
    )
    road: bool = True
    #: Random structures (buildings, trees, poles) scattered between clear_radius_m and world_radius_m.
    structures: int = Field(40, ge=0, le=2000)
    clear_radius_m: float = Field(40.0, ge=0.0)
    world_radius_m: float = Field(350.0, gt=0.0)
    #: A ring of forest on the horizon and a ring of distant hills.
    tree_line: bool = True
    hills: bool = True
    occluders: tuple[OccluderSpec, ...] = ()
    #: Exposure bias on top of auto exposure, EV.
    exposure_ev: float = Field(0.0, ge=-4.0, le=4.0)
    #: Colour temperature the camera's white balance assumes, K (5500 = neutral daylight).
    white_balance_k: float = Field(5500.0, ge=2500.0, le=10000.0)
    sensor_noise: float = Field(1.0, ge=0.0, le=10.0)
    vignetting: float = Field(0.25, ge=0.0, le=1.0)
    #: Display contrast around mid-grey (the sensor's tone curve is gamma 2).
    contrast: float = Field(1.0, ge=0.5, le=1.6)
    leader: LeaderLook = LeaderLook()
    #: For the evaluation harness (the follower's standoff band in this scenario); not used in rendering.
    leader_distance_m: tuple[float, float] | None = None
    #: Scenario metadata: its occluders cross the line of sight only partly. No rendering effect.
    partial_occlusion: bool = False

    model_config = ConfigDict(frozen=True, extra="forbid", populate_by_name=True)

    @model_validator(mode="after")
    def _radii_ordered(self) -> VisualConfig:
        if self.world_radius_m <= self.clear_radius_m:
            raise ValueError("world_radius_m must exceed clear_radius_m")
        if not self.ground_materials:
            raise ValueError("ground_materials must name at least one material")
        return self

    @property
    def resolved_sun_elevation_deg(self) -> float:
        if self.sun_elevation_deg is not None:
            return self.sun_elevation_deg
        return 45.0 if self.time_of_day == "day" else 4.0

    @property
    def sun_dir_ned(self) -> tuple[float, float, float]:
        """Unit vector towards the sun in local NED."""
        el = math.radians(self.resolved_sun_elevation_deg)
        az = math.radians(self.sun_azimuth_deg)
        return (math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), -math.sin(el))


def visual_from_mapping(data: Mapping[str, Any] | None, source: str = "[visual]") -> VisualConfig:
    """Validate a scenario's ``[visual]`` table; one :class:`ConfigError` line per problem."""
    try:
        return VisualConfig.model_validate(dict(data or {}))
    except ValidationError as exc:
        raise ConfigError(source, format_validation_error(exc)) from None
