"""Town styles: layout, palette, texture, lighting and ego-driving parameters of one town domain.

`TOWN_STYLES` names the styles a `orbis2.sim.town.Town` can be generated with: ``default`` (the
training domain) and ``heldout`` (the unseen domain).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class TownStyle:
    """Layout, palette, texture and lighting parameters of one town domain.

    Colours are sRGB in [0, 1]; ranges are (low, high) for uniform draws.
    """

    blocks_per_axis: tuple[int, int] = (5, 7)
    block_size_m: tuple[float, float] = (22.0, 45.0)
    # The four corners of the grid are bends, not junctions: the boundary roads form a ring
    # whose corners are quarter circles (road centre radius drawn per corner), driven without
    # stopping. The corner blocks are wider so that a bend ends well before the next junction.
    corner_block_m: tuple[float, float] = (56.0, 72.0)
    bend_radius_m: tuple[float, float] = (24.0, 40.0)
    bend_lateral_accel_ms2: tuple[float, float] = (1.6, 3.0)
    lane_width_m: float = 3.5
    sidewalk_m: float = 3.0
    kerb_height_m: float = 0.15
    road_extension_m: float = 220.0
    park_fraction: float = 0.15
    paved_yard_fraction: float = 0.3
    lot_size_m: tuple[float, float] = (10.0, 26.0)
    setback_m: tuple[float, float] = (0.0, 4.0)
    building_height_m: tuple[float, float] = (7.0, 38.0)
    height_skew: float = 2.2  # heights are low + (high - low) * u ** skew
    upper_tier_prob: float = 0.3
    floor_height_m: tuple[float, float] = (3.0, 3.7)
    window_spacing_m: tuple[float, float] = (2.2, 3.4)
    window_width: tuple[float, float] = (0.4, 0.7)
    window_height: tuple[float, float] = (0.45, 0.62)
    glass_tower_prob: float = 0.2
    facade_palette: tuple[tuple[float, float, float], ...] = (
        (0.56, 0.29, 0.22), (0.70, 0.60, 0.47), (0.60, 0.60, 0.58), (0.80, 0.78, 0.73),
        (0.38, 0.28, 0.23), (0.46, 0.51, 0.56), (0.83, 0.76, 0.60), (0.52, 0.50, 0.43),
        (0.64, 0.42, 0.33))
    glass_rgb: tuple[float, float, float] = (0.16, 0.22, 0.26)
    roof_rgb: tuple[float, float, float] = (0.35, 0.34, 0.33)
    asphalt_rgb: tuple[float, float, float] = (0.29, 0.29, 0.30)
    paint_rgb: tuple[float, float, float] = (0.86, 0.86, 0.83)
    centre_line_rgb: tuple[float, float, float] = (0.86, 0.86, 0.83)
    centre_line_double: bool = False
    dash_m: tuple[float, float] = (3.0, 9.0)  # dash length, dash period
    crosswalk_prob: float = 0.6
    sidewalk_rgb: tuple[float, float, float] = (0.62, 0.60, 0.57)
    kerb_rgb: tuple[float, float, float] = (0.72, 0.71, 0.68)
    tile_m: float = 0.5
    grass_rgb: tuple[tuple[float, float, float], tuple[float, float, float]] = (
        (0.26, 0.42, 0.15), (0.40, 0.46, 0.21))
    terrain_rgb: tuple[tuple[float, float, float], tuple[float, float, float]] = (
        (0.33, 0.44, 0.18), (0.50, 0.46, 0.30))
    tree_palette: tuple[tuple[float, float, float], ...] = (
        (0.17, 0.34, 0.11), (0.25, 0.40, 0.14), (0.14, 0.29, 0.15), (0.30, 0.38, 0.12))
    palm_fraction: float = 0.0
    bark_rgb: tuple[float, float, float] = (0.33, 0.26, 0.20)
    street_tree_prob: float = 0.7
    forest_trees: int = 420
    hedge_prob: float = 0.5
    metal_rgb: tuple[float, float, float] = (0.30, 0.32, 0.33)
    car_palette: tuple[tuple[float, float, float], ...] = (
        (0.85, 0.85, 0.85), (0.60, 0.61, 0.63), (0.08, 0.08, 0.09), (0.30, 0.31, 0.33),
        (0.62, 0.08, 0.07), (0.10, 0.22, 0.52), (0.06, 0.10, 0.26), (0.18, 0.32, 0.20),
        (0.70, 0.62, 0.48), (0.85, 0.68, 0.10))
    car_spacing_m: tuple[float, float] = (120.0, 300.0)
    car_speed_ms: tuple[float, float] = (5.5, 9.0)
    # Ego driving: cruise speed per leg, how often it goes straight at a junction (left and right
    # share the rest equally) and how often it stops at a junction without being forced to.
    # Tuned for a world that turns often, both ways (left arcs are wider and take longer, so
    # right turns are drawn a little more often to balance the turning frames). Each turn arc is
    # driven at its nominal speed times a factor drawn from `turn_speed_scale`, so the yaw rate
    # of a turn (speed / arc radius) is graded rather than one value.
    cruise_ms: tuple[float, float] = (8.0, 14.0)
    turn_speed_scale: tuple[float, float] = (0.4, 1.8)
    straight_weight: float = 0.05
    right_share: float = 0.55
    stop_prob: float = 0.05
    stop_wait_s: tuple[float, float] = (0.3, 1.5)
    sky_zenith_rgb: tuple[float, float, float] = (0.28, 0.47, 0.80)
    sky_horizon_rgb: tuple[float, float, float] = (0.74, 0.83, 0.93)
    cloud_cover: float = 0.45
    sun_elevation_deg: float = 40.0
    sun_azimuth_deg: float = 215.0
    sun_rgb: tuple[float, float, float] = (1.0, 0.95, 0.86)
    sun_intensity: float = 2.6
    ambient_rgb: tuple[float, float, float] = (0.50, 0.60, 0.78)
    ambient_intensity: float = 0.95
    fog_distance_m: float = 420.0
    exposure: float = 1.15


TOWN_STYLES: dict[str, TownStyle] = {
    "default": TownStyle(),
    # Sunny desert town: small low adobe-coloured blocks, dusty pale roads with a double yellow
    # centre line, sand terrain, palms, a high warm sun and a hazy pale sky.
    "heldout": TownStyle(
        blocks_per_axis=(6, 8), block_size_m=(34.0, 62.0), lane_width_m=3.2, sidewalk_m=3.6,
        park_fraction=0.1, paved_yard_fraction=0.8, lot_size_m=(8.0, 18.0), setback_m=(0.0, 2.5),
        building_height_m=(3.8, 13.0), height_skew=1.6, upper_tier_prob=0.35,
        floor_height_m=(3.2, 3.9), window_spacing_m=(3.0, 4.6), window_width=(0.28, 0.45),
        window_height=(0.35, 0.5), glass_tower_prob=0.0,
        facade_palette=((0.86, 0.73, 0.53), (0.78, 0.46, 0.31), (0.80, 0.62, 0.33),
                        (0.93, 0.90, 0.84), (0.88, 0.70, 0.62), (0.70, 0.53, 0.39),
                        (0.62, 0.70, 0.66)),
        glass_rgb=(0.10, 0.09, 0.08), roof_rgb=(0.62, 0.45, 0.33),
        asphalt_rgb=(0.44, 0.41, 0.37), paint_rgb=(0.90, 0.88, 0.80),
        centre_line_rgb=(0.90, 0.72, 0.15), centre_line_double=True, crosswalk_prob=0.35,
        sidewalk_rgb=(0.78, 0.70, 0.58), kerb_rgb=(0.86, 0.80, 0.70), tile_m=0.8,
        grass_rgb=((0.50, 0.50, 0.26), (0.66, 0.58, 0.38)),
        terrain_rgb=((0.80, 0.67, 0.47), (0.70, 0.55, 0.38)),
        tree_palette=((0.33, 0.42, 0.16), (0.40, 0.45, 0.20), (0.28, 0.36, 0.16)),
        palm_fraction=0.75, bark_rgb=(0.48, 0.40, 0.30), street_tree_prob=0.45, forest_trees=160,
        hedge_prob=0.2, metal_rgb=(0.45, 0.44, 0.42),
        car_palette=((0.90, 0.90, 0.88), (0.75, 0.72, 0.66), (0.55, 0.18, 0.12),
                     (0.20, 0.35, 0.45), (0.82, 0.78, 0.55), (0.35, 0.36, 0.30)),
        sky_zenith_rgb=(0.38, 0.57, 0.85), sky_horizon_rgb=(0.92, 0.88, 0.80), cloud_cover=0.12,
        sun_elevation_deg=63.0, sun_azimuth_deg=120.0, sun_rgb=(1.0, 0.92, 0.78),
        sun_intensity=2.9, ambient_rgb=(0.70, 0.70, 0.72), ambient_intensity=0.7,
        fog_distance_m=330.0, exposure=1.0),
}
