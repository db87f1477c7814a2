"""Parameters of a synthetic room (:class:`SyntheticParams`) and their strict parsing."""

from __future__ import annotations

import dataclasses

from ...errors import ConfigError
from ...params import from_mapping


@dataclasses.dataclass
class SyntheticParams:
    """Parameters of one synthetic room; the defaults are the default benchmark room.

    Attributes:
        seed: seeds the layout, the textures and the camera path.
        width, height: image size in pixels.
        fov_x_deg: horizontal field of view (square pixels, principal point at the image centre).
        num_views: views on the 360-degree loop.
        test_every: every ``test_every``-th view (starting at ``test_every // 2``) is a test view.
        num_objects: objects in the room, not counting walls, floor and ceiling (a composite object
            such as a table counts once; its parts are extra leaf ids).
        room_width_range, room_depth_range, room_height_range: metres, (min, max) sampled uniformly.
        camera_radius: mean radius of the camera loop around the room centre (metres).
        camera_height: mean camera height above the floor (metres).
        camera_height_amplitude: height variation along the loop (metres).
        camera_pitch_deg: mean pitch (negative looks down).
        camera_pitch_amplitude_deg, camera_yaw_amplitude_deg: pitch / yaw variation along the loop.
        clear_radius: radius of the furniture-free disk around the room centre (metres); must exceed
            the camera loop so that no camera sits inside an object.
        supersample: RGB rays per pixel per axis (2 -> 2x2 anti-aliasing); instance ids and depth
            always come from the single pixel-centre ray.
        texture_scale: multiplies every texture feature size.
        texture_contrast: multiplies every texture contrast.
        ambient: hemispherical ambient light level.
        light_power: power of each of the two ceiling lights.
        shadows: cast hard shadows from the ceiling lights.
        min_visible_pixels: an object is evaluated when some view shows at least this many of its
            pixels.
    """

    seed: int = 0
    width: int = 160
    height: int = 120
    fov_x_deg: float = 80.0
    num_views: int = 72
    test_every: int = 8
    num_objects: int = 32
    room_width_range: tuple[float, float] = (5.4, 6.6)
    room_depth_range: tuple[float, float] = (4.6, 5.6)
    room_height_range: tuple[float, float] = (2.6, 3.0)
    camera_radius: float = 0.5
    camera_height: float = 1.45
    camera_height_amplitude: float = 0.15
    camera_pitch_deg: float = -18.0
    camera_pitch_amplitude_deg: float = 8.0
    camera_yaw_amplitude_deg: float = 12.0
    clear_radius: float = 1.05
    supersample: int = 2
    texture_scale: float = 1.0
    texture_contrast: float = 1.0
    ambient: float = 0.45
    light_power: float = 0.9
    shadows: bool = True
    min_visible_pixels: int = 64

    # each field's range: refused on input and in the config schema (trace3d.params.check_ranges)
    RANGES = {"width": ">= 8", "height": ">= 8", "fov_x_deg": "[20, 150]", "num_views": ">= 2", "test_every": ">= 2",
              "num_objects": ">= 1", "supersample": "[1, 8]", "texture_scale": "> 0", "texture_contrast": ">= 0",
              "min_visible_pixels": ">= 0", "camera_height": ">= 0.5", "seed": ">= 0"}

    def __post_init__(self) -> None:
        where = "synthetic params"
        if self.width < 8 or self.height < 8:
            raise ConfigError(f"{where}: width and height must be at least 8 pixels, got {self.width}x{self.height}.")
        if not 20.0 <= self.fov_x_deg <= 150.0:
            raise ConfigError(f"{where}: fov_x_deg must lie in [20, 150], got {self.fov_x_deg}.")
        if self.num_views < 2:
            raise ConfigError(f"{where}: num_views must be at least 2, got {self.num_views}.")
        if self.test_every < 2:
            raise ConfigError(f"{where}: test_every must be at least 2, got {self.test_every}.")
        if self.num_objects < 1:
            raise ConfigError(f"{where}: num_objects must be at least 1, got {self.num_objects}.")
        for name in ("room_width_range", "room_depth_range", "room_height_range"):
            lo, hi = getattr(self, name)
            if not 0 < lo <= hi:
                raise ConfigError(f"{where}: {name} must be (min, max) with 0 < min <= max, got {(lo, hi)}.")
            setattr(self, name, (float(lo), float(hi)))
        if min(self.room_width_range[0], self.room_depth_range[0]) < 2 * self.clear_radius + 1.6:
            raise ConfigError(
                f"{where}: the room's smaller side must be at least 2 * clear_radius + 1.6 m "
                f"= {2 * self.clear_radius + 1.6:.2f} m to fit furniture around the camera loop."
            )
        if self.room_height_range[0] < 2.3:
            raise ConfigError(f"{where}: room_height_range must start at 2.3 m or more, got {self.room_height_range}.")
        if self.camera_radius * 1.3 + 0.3 > self.clear_radius:
            raise ConfigError(
                f"{where}: clear_radius ({self.clear_radius}) must exceed 1.3 * camera_radius + 0.3 m "
                f"({self.camera_radius * 1.3 + 0.3:.2f}) so that cameras stay away from furniture."
            )
        if not 0.5 <= self.camera_height <= self.room_height_range[0] - 0.5:
            raise ConfigError(f"{where}: camera_height must lie between 0.5 m and the ceiling minus 0.5 m.")
        if self.supersample < 1 or self.supersample > 8:
            raise ConfigError(f"{where}: supersample must lie in 1..8, got {self.supersample}.")
        if self.texture_scale <= 0 or self.texture_contrast < 0:
            raise ConfigError(f"{where}: texture_scale must be positive and texture_contrast non-negative.")
        if self.min_visible_pixels < 0:
            raise ConfigError(f"{where}: min_visible_pixels must be non-negative.")


def params_from(d: dict | None) -> SyntheticParams:
    """Strictly typed :class:`SyntheticParams` from a config mapping (unknown keys are refused)."""
    return from_mapping(SyntheticParams, d, "synthetic params")
