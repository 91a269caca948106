"""Families of synthetic beds the shipped recipe does not train on as such: the robustness suite.

Each family is a ``SceneConfig`` that changes one thing a grower's bed may differ in (cap shape,
sampling, sensor, bed), made by ``mushroom-pose synth --family NAME`` and scored by
``bench/robustness.py``. The suite's beds come from ``SUITE_SEED``'s seed sequence, a stream apart
from the training runs' ``SeedSequence([run seed, iteration])``, so they are never trained on.
"""

from __future__ import annotations

from dataclasses import dataclass

from capture.virtual import SENSOR_MODELS
from perception.cap import CAP_HEIGHT_RATIO, CAP_RADIUS_AT_UNIT_SCALE
from perception.synthetic.dataset import scene_seeds
from perception.synthetic.scene import SceneConfig

SUITE_SEED = 2026_1205
"""Base seed of the suite's beds (family k draws from the k-th seed derived from it)."""


def _scale_for_diameters(low_mm: float, high_mm: float) -> tuple[float, float]:
    """The generator's scale range whose round caps are ``low_mm``-``high_mm`` across."""
    return low_mm / 2000 / CAP_RADIUS_AT_UNIT_SCALE, high_mm / 2000 / CAP_RADIUS_AT_UNIT_SCALE


def _height_for_ratios(low: float, high: float) -> tuple[float, float]:
    """The generator's cap height factors whose caps stand ``low``-``high`` times their rim radius."""
    return low / CAP_HEIGHT_RATIO, high / CAP_HEIGHT_RATIO


ROUND = (1.0, 1.0)
"""Per-axis factors of round caps: the shape families state each cap's height over its rim radius."""


@dataclass(frozen=True)
class BedFamily:
    group: str
    """What the family varies: cap shape, sampling, sensor or bed."""
    description: str
    config: SceneConfig
    in_range: bool = True
    """Whether the family lies inside the stated operating range (its targets apply)."""


FAMILIES = {
    "shallow-domes": BedFamily("cap shape", "shallow domes, height 0.33-0.45 of the rim radius",
                               SceneConfig(axis_factor=ROUND, cap_height=_height_for_ratios(0.33, 0.45))),
    "real-domes": BedFamily("cap shape", "domes 0.45-0.70 of the rim radius, as the real caps",
                            SceneConfig(axis_factor=ROUND, cap_height=_height_for_ratios(0.45, 0.70))),
    "flats": BedFamily("cap shape", "flat opened caps 50-80 mm, height 0.2-0.3 of the rim radius",
                       SceneConfig(mushrooms=(5, 25), scale=_scale_for_diameters(50, 80), axis_factor=ROUND,
                                   cap_height=_height_for_ratios(0.2, 0.3))),
    "large-brown": BedFamily("cap shape", "large brown caps 80-120 mm", SceneConfig(
        mushrooms=(4, 14), scale=_scale_for_diameters(80, 120), axis_factor=ROUND, cap_height=_height_for_ratios(0.4, 0.6)),
        in_range=False),
    "dense-pins": BedFamily("cap shape", "dense pins 8-15 mm across", SceneConfig(
        mushrooms=(60, 120), scale=_scale_for_diameters(8, 15), axis_factor=(0.9, 1.1)), in_range=False),
    "spacing-1mm": BedFamily("sampling", "points 1 mm apart", SceneConfig(spacing=0.001)),
    "spacing-5mm": BedFamily("sampling", "points 5 mm apart (a cloud voxelised to 5 mm)",
                             SceneConfig(spacing=0.005, scale=_scale_for_diameters(30, 72))),
    "spacing-8mm": BedFamily("sampling", "points 8 mm apart (another generator's beds)",
                             SceneConfig(spacing=0.008, scale=_scale_for_diameters(30, 72))),
    "single-view": BedFamily("sampling", "one view of the virtual D405", SceneConfig(visibility="camera")),
    "fused-views": BedFamily("sampling", "2-6 views of the virtual D405 fused",
                             SceneConfig(visibility="fused", views=(2, 6))),
    "oak-stereo": BedFamily("sensor", "2-6 fused views of a noisier OAK-class stereo camera",
                            SceneConfig(visibility="fused", views=(2, 6), sensor=SENSOR_MODELS["oak"])),
    "tilted-uneven": BedFamily("bed", "a bed tilted 6-12 degrees on clodded, uneven soil",
                               SceneConfig(bed_tilt_deg=12.0, terrain="clods")),
    "touching-clusters": BedFamily("bed", "most caps in touching clusters of 5 and more",
                                   SceneConfig(mushrooms=(25, 45), cluster_probability=0.9,
                                               cluster_spacing=(0.85, 1.0))),
    "casing-soil": BedFamily("bed", "casing soil with lumps, banks and holes", SceneConfig(
        soil_holes=(0.2, 0.5), soil_lumps=(6, 12), soil_banks=(2, 6))),
    "mycelium": BedFamily("bed", "white mycelium mats over 20-50 % of the soil, 1.5-4 mm thick",
                          SceneConfig(mycelium=(0.2, 0.5))),
}
"""The suite's families by name, in the order the suite prints them; a family's place in it picks its
seeds (``family_seeds``), so new families go last."""


def family_seeds(name: str, beds: int, base_seed: int = SUITE_SEED) -> list[int]:
    """The bed seeds of family ``name`` drawn from ``base_seed`` (the suite's, or the calibration's):
    the same on every machine, apart per family."""
    if name not in FAMILIES:
        raise ValueError(f"unknown bed family {name!r}; choose one of {', '.join(FAMILIES)}")
    family_base = scene_seeds(base_seed, len(FAMILIES))[list(FAMILIES).index(name)]
    return scene_seeds(family_base, beds)
