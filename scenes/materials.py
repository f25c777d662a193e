"""Surface materials: what a face does to ultrasound and to a LiDAR beam."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, kw_only=True)
class Material:
    """Acoustic and optical surface properties of one material.

    Attributes:
        name: Short identifier, unique within a scene's material table.
        acoustic_reflection: Fraction of incident sound energy that is reflected
            (1 - absorption coefficient), in [0, 1], for the 25-80 kHz band.
        acoustic_scattering: Fraction of the reflected energy that leaves
            non-specularly (ISO 17497-1 scattering coefficient), in [0, 1].
        lidar_reflectivity: Diffuse reflectivity at the LiDAR wavelength, in [0, 1].
        lidar_transparent: True for glass and similar: LiDAR beams pass through.
    """

    name: str
    acoustic_reflection: float
    acoustic_scattering: float
    lidar_reflectivity: float
    lidar_transparent: bool = False

    def __post_init__(self) -> None:
        if not self.name:
            raise ValueError("Material.name must be a non-empty string")
        for field in ("acoustic_reflection", "acoustic_scattering", "lidar_reflectivity"):
            value = getattr(self, field)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"Material {self.name!r}: {field} must lie in [0, 1], got {value}")


# Ultrasound values are rough mid-band (~40 kHz) figures for indoor surfaces: hard, smooth
# surfaces reflect almost everything specularly; soft or rough ones absorb or scatter more.
MATERIALS: dict[str, Material] = {
    m.name: m
    for m in (
        Material(name="painted_wall", acoustic_reflection=0.97, acoustic_scattering=0.05, lidar_reflectivity=0.8),
        Material(name="brick", acoustic_reflection=0.95, acoustic_scattering=0.30, lidar_reflectivity=0.5),
        Material(name="floor", acoustic_reflection=0.95, acoustic_scattering=0.10, lidar_reflectivity=0.4),
        Material(name="ceiling_tile", acoustic_reflection=0.60, acoustic_scattering=0.30, lidar_reflectivity=0.8),
        Material(name="wood", acoustic_reflection=0.90, acoustic_scattering=0.10, lidar_reflectivity=0.6),
        Material(name="metal", acoustic_reflection=0.99, acoustic_scattering=0.02, lidar_reflectivity=0.6),
        Material(name="fabric", acoustic_reflection=0.60, acoustic_scattering=0.40, lidar_reflectivity=0.5),
        Material(
            name="glass",
            acoustic_reflection=0.98,
            acoustic_scattering=0.02,
            lidar_reflectivity=0.05,
            lidar_transparent=True,
        ),
        # Test material: a perfect specular mirror.
        Material(name="mirror", acoustic_reflection=1.0, acoustic_scattering=0.0, lidar_reflectivity=1.0),
    )
}


def material(name_or_material: str | Material) -> Material:
    """Return a preset by name, or the given Material unchanged."""
    if isinstance(name_or_material, Material):
        return name_or_material
    try:
        return MATERIALS[name_or_material]
    except KeyError:
        raise ValueError(f"unknown material {name_or_material!r}; presets are {sorted(MATERIALS)}") from None
