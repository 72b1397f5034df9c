"""Procedural tissue-like texture for the scene's tissue surface.

Multi-octave value noise (random lattices upsampled bicubically) is mapped through a palette
of tissue tones (deep red muscle, pink mucosa, yellowish fat, pale grey-pink fascia) with
dark-red vessels traced along level sets of a low-frequency noise and wet patches that carry
specular highlights. The palette deliberately overlaps the robot's grey-pink metallic
reflections: this is the hard case of Watson et al. (Table II: colour thresholding reaches an
IoU of 0.02).

The texture is a square image over a square patch of the tissue plane; the renderer samples
it at the ray hits, so every camera (including stereo rigs) sees the same tissue.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

# Linear-ish display RGB in [0, 1].
PALETTE = np.array(
    [
        [0.50, 0.12, 0.12],  # deep red muscle
        [0.70, 0.30, 0.30],  # red
        [0.84, 0.52, 0.50],  # pink mucosa
        [0.74, 0.62, 0.62],  # grey-pink fascia (overlaps the metal's reflections)
        [0.90, 0.78, 0.56],  # yellowish fat
    ],
    dtype=np.float32,
)


@dataclass(frozen=True)
class TissueTexture:
    """A sampled tissue texture.

    Attributes:
        albedo: (S, S, 3) float32 RGB in [0, 1].
        height: (S, S) float32 bump height in metres (for shading normals).
        wet: (S, S) float32 in [0, 1], specular strength of the wet surface.
        slope: (S, S, 2) float32 height gradient d(height)/d(u, v) (dimensionless).
        extent: side of the square patch of the tissue plane the texture covers (metres).
    """

    albedo: np.ndarray
    height: np.ndarray
    wet: np.ndarray
    slope: np.ndarray
    extent: float

    @property
    def size(self) -> int:
        return self.albedo.shape[0]


def value_noise(rng: np.random.Generator, size: int, cells: int) -> np.ndarray:
    """One octave of value noise: a random (cells+1)^2 lattice upsampled bicubically to
    ``size`` x ``size``; float32 roughly in [0, 1]."""
    lattice = rng.random((cells + 1, cells + 1)).astype(np.float32)
    return cv2.resize(lattice, (size, size), interpolation=cv2.INTER_CUBIC)


def fractal_noise(
    rng: np.random.Generator, size: int, base_cells: int, octaves: int, gain: float = 0.5
) -> np.ndarray:
    """Sum of ``octaves`` value-noise octaves (cell counts doubling), normalised to [0, 1]."""
    total = np.zeros((size, size), np.float32)
    amp = 1.0
    for k in range(octaves):
        total += amp * value_noise(rng, size, min(base_cells * 2**k, size // 2))
        amp *= gain
    lo, hi = np.percentile(total, [0.5, 99.5])
    return np.clip((total - lo) / max(hi - lo, 1e-6), 0.0, 1.0)


def _palette_lookup(x: np.ndarray) -> np.ndarray:
    """Piecewise-linear palette map from [0, 1] to RGB."""
    k = len(PALETTE) - 1
    pos = np.clip(x, 0.0, 1.0) * k
    i = np.minimum(pos.astype(np.int32), k - 1)
    f = (pos - i)[..., None]
    return (1.0 - f) * PALETTE[i] + f * PALETTE[i + 1]


def make_tissue_texture(
    rng: np.random.Generator, size: int = 1024, extent: float = 0.4
) -> TissueTexture:
    """Generate a tissue texture of ``size``^2 texels covering ``extent`` metres square."""
    base = fractal_noise(rng, size, 4, 6, 0.55)
    tone = fractal_noise(rng, size, 2, 3, 0.5)
    detail = fractal_noise(rng, size, 48, 3, 0.6)
    # Tone index: mostly red/pink, fat and fascia in patches.
    idx = 0.2 + 0.75 * base + 0.6 * (tone - 0.5) + 0.12 * (detail - 0.5)
    albedo = _palette_lookup(idx)
    # Vessels: thin dark-red bands where two low-frequency noises cross mid-level.
    vessel = np.zeros((size, size), np.float32)
    for cells, width in ((3, 0.010), (6, 0.007), (10, 0.005)):
        n = fractal_noise(rng, size, cells, 2, 0.4)
        presence = np.clip((fractal_noise(rng, size, 3, 2) - 0.35) / 0.3, 0.0, 1.0)
        vessel = np.maximum(vessel, presence * np.exp(-(((n - 0.5) / width) ** 2)))
    vessel_rgb = np.array([0.32, 0.03, 0.06], np.float32)
    albedo = albedo * (1.0 - 0.7 * vessel[..., None]) + 0.7 * vessel[..., None] * vessel_rgb
    # Fine speckle so flat regions are not perfectly smooth.
    albedo *= (0.92 + 0.16 * fractal_noise(rng, size, 128, 2))[..., None]
    texel = extent / size
    height = (1.5e-3 * base + 0.3e-3 * detail - 0.15e-3 * vessel).astype(np.float32)
    height = cv2.GaussianBlur(height, (0, 0), 1.5)
    gv, gu = np.gradient(height, texel)
    wet = np.clip(2.0 * fractal_noise(rng, size, 10, 3) - 0.9, 0.0, 1.0)
    return TissueTexture(
        albedo=np.clip(albedo, 0.0, 1.0).astype(np.float32),
        height=height,
        wet=wet.astype(np.float32),
        slope=np.stack([gu, gv], axis=-1).astype(np.float32),
        extent=float(extent),
    )
