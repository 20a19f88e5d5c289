"""Endoscope appearance: solid mucosa texture, point-light shading, sensor effects.

The texture is a function of the 3D surface point (a solid texture): band-
limited periodic noise tiles sampled at several scales and rotations give the
mucosa's colour variation, fine granular detail (what SIFT keys on) and
branching vessels (zero-crossings of a noise field drawn as thin dark-red
lines).  Octaves finer than the pixel footprint fade out, so distant walls do
not alias.  Because it depends only on the 3D point, every frame sees the same
texture at the same place.

Shading: a point light at the camera centre, inverse-square fall-off, Lambert
diffuse plus a Blinn-Phong specular lobe (wet mucosa; with light = viewer the
half vector is the view direction), normals perturbed by fine noise so the
highlights break up as on real tissue.  Then auto-exposure, gamma, shot and
read noise.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import map_coordinates

__all__ = ["SolidTexture", "shade", "Exposure", "sensor"]

_TILE = 48  # noise tile size (cells); features ~ 4 cells
_CELLS_PER_FEATURE = 4.0


def _noise_tile(rng: np.random.Generator, n: int = _TILE) -> np.ndarray:
    """Periodic band-limited Gaussian noise (n, n, n) float32 with unit std."""
    white = rng.standard_normal((n, n, n))
    k = np.fft.fftfreq(n)
    k2 = k[:, None, None] ** 2 + k[None, :, None] ** 2 + k[None, None, :] ** 2
    sigma = 1.0 / _CELLS_PER_FEATURE  # spectral width: features ~ 4 cells
    spec = np.fft.fftn(white) * np.exp(-0.5 * k2 / (0.5 * sigma) ** 2)
    tile = np.real(np.fft.ifftn(spec))
    return ((tile - tile.mean()) / tile.std()).astype(np.float32)


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.standard_normal((3, 3)))
    return q * np.sign(np.diag(r))


class SolidTexture:
    """Mucosa albedo, specular strength and normal perturbation as functions of 3D points (mm).

    Args:
        seed: texture seed.
    """

    def __init__(self, seed: int):
        rng = np.random.default_rng(seed)
        self.tiles = [_noise_tile(rng) for _ in range(2)]
        self.rots = [_random_rotation(rng) for _ in range(16)]
        self.offsets = rng.uniform(0, _TILE, (16, 3))
        # per-patient tint: some mucosa is paler, some redder
        self.base = np.array([0.80, 0.24, 0.14]) * rng.uniform(0.92, 1.08, 3)

    def noise(self, p: np.ndarray, scale_mm: float, k: int) -> np.ndarray:
        """Unit-std smooth noise (N,) at points (N, 3) with features of ``scale_mm``; ``k`` picks an independent field."""
        return self.noises(p, [(scale_mm, k)])[0]

    def noises(self, p: np.ndarray, fields: list[tuple[float, int]]) -> np.ndarray:
        """Several noise fields at once: (len(fields), N) for ``fields`` = [(scale_mm, k), ...]."""
        p = np.asarray(p, dtype=np.float32)
        out = np.empty((len(fields), len(p)), np.float32)
        for tile_id in (0, 1):
            sel = [i for i, (_, k) in enumerate(fields) if k % 2 == tile_id]
            if not sel:
                continue
            M = np.concatenate([self.rots[fields[i][1] % 16] * (_CELLS_PER_FEATURE / fields[i][0]) for i in sel]).astype(np.float32)
            off = np.concatenate([self.offsets[fields[i][1] % 16] for i in sel]).astype(np.float32)
            c = (M @ p.T + off[:, None]).reshape(len(sel), 3, -1).transpose(1, 0, 2)  # (3, fields, N)
            out[sel] = map_coordinates(self.tiles[tile_id], c, order=1, mode="grid-wrap", prefilter=False)
        return out

    def __call__(self, p: np.ndarray, footprint_mm: np.ndarray) -> dict[str, np.ndarray]:
        """Surface properties at points.

        Args:
            p: (N, 3) surface points in mm.
            footprint_mm: (N,) size of one pixel on the surface (fades out finer octaves).
        Returns:
            ``albedo`` (N, 3) linear RGB, ``specular`` (N,), ``bump`` (N, 3) normal perturbation.
        """

        def fade(scale):  # 1 when the feature spans >= 3 pixels, 0 below 1.2 pixels
            return np.clip((scale / footprint_mm - 1.2) / 1.8, 0.0, 1.0)

        (n_low, n_mid, g1, g2, patch_n, vb, vs, vs_patch, wet, b0, b1, b2) = self.noises(
            p, [(14.0, 0), (4.0, 1), (1.0, 2), (0.45, 3), (10.0, 4), (6.0, 5), (2.2, 6), (5.0, 7), (8.0, 8), (1.5, 9), (1.5, 10), (1.5, 11)]
        )
        # base colour: redder / paler patches
        albedo = self.base[None] * (1 + 0.18 * n_low[:, None] * np.array([0.2, -1.0, -1.0])[None])
        albedo = albedo * (1 + 0.08 * n_mid)[:, None]
        # granular detail at 0.45-1 mm (what feature detectors find on mucosa)
        g = 0.09 * fade(1.0) * g1 + 0.07 * fade(0.45) * g2
        albedo = albedo * (1 + g)[:, None]
        # vessels: thin lines at zero crossings of band-passed noise, in patches
        patch = np.clip(0.1 + 0.8 * patch_n, 0.0, 1.0)
        v_big = np.exp(-((vb / 0.07) ** 2)) * patch
        v_small = np.exp(-((vs / 0.10) ** 2)) * np.clip(0.8 * vs_patch, 0, 1) * fade(0.6)
        vessel = np.clip(0.8 * v_big + 0.6 * v_small, 0, 0.9)
        vessel_rgb = np.array([0.42, 0.04, 0.04])
        albedo = albedo * (1 - vessel[:, None]) + vessel_rgb[None] * vessel[:, None]
        # wetness: specular strength varies over the surface
        specular = 0.7 + 0.4 * np.clip(wet, -1, 1)
        bump = 0.03 * np.stack([b0, b1, b2], 1) * fade(1.5)[:, None]
        return {"albedo": np.clip(albedo, 0, 1), "specular": specular, "bump": bump}


def shade(
    points: np.ndarray,
    normals: np.ndarray,
    ray_dirs: np.ndarray,
    ray_len: np.ndarray,
    texture: SolidTexture,
    footprint_mm: np.ndarray,
    shininess: float = 30.0,
) -> np.ndarray:
    """Linear radiance (N, 3) of hit points lit by a point light at the camera.

    Args:
        points: (N, 3) world points (mm).
        normals: (N, 3) unit surface normals (either orientation).
        ray_dirs: (N, 3) unit directions from the camera to the points.
        ray_len: (N,) distance camera -> point (mm).
        texture: the surface's :class:`SolidTexture`.
        footprint_mm: (N,) pixel footprint on the surface.
    """
    props = texture(points, footprint_mm)
    n = normals + props["bump"]
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-9)
    cos = np.abs(np.sum(n * ray_dirs, axis=1))  # light at the camera: cos(incidence) = cos(view)
    falloff = 1.0 / np.maximum(ray_len, 1.0) ** 2
    diffuse = props["albedo"] * cos[:, None]
    spec = props["specular"] * cos**shininess
    return (diffuse + spec[:, None]) * falloff[:, None]


class Exposure:
    """Auto-exposure with temporal smoothing, like an endoscope's video processor.

    Args:
        target: value the 98th percentile of the frame is mapped to.
        smoothing: weight of the previous gain (0 = per-frame exposure).
    """

    def __init__(self, target: float = 0.7, smoothing: float = 0.6):
        self.target = target
        self.smoothing = smoothing
        self.gain: float | None = None

    def __call__(self, radiance: np.ndarray) -> float:
        ref = float(np.percentile(radiance.mean(axis=-1), 93)) if radiance.size else 1.0
        g = self.target / max(ref, 1e-12)
        self.gain = g if self.gain is None else self.smoothing * self.gain + (1 - self.smoothing) * g
        return self.gain


def sensor(linear: np.ndarray, rng: np.random.Generator, read_noise: float = 0.004, shot_noise: float = 0.012) -> np.ndarray:
    """Tone-map linear RGB (H, W, 3) to uint8 with gamma, shot and read noise, and a mild optical blur."""
    from scipy.ndimage import gaussian_filter

    img = 1.0 - np.exp(-1.6 * np.maximum(linear, 0.0))  # soft shoulder: highlights saturate smoothly
    img = img / (1.0 - np.exp(-1.6))
    img = np.clip(img, 0.0, 1.0)
    img = gaussian_filter(img, sigma=(0.6, 0.6, 0), mode="nearest")  # lens PSF / demosaicing softness
    img = img + rng.standard_normal(img.shape).astype(np.float32) * (read_noise + shot_noise * np.sqrt(img))
    img = np.clip(img, 0.0, 1.0) ** (1 / 2.2)
    return np.round(img * 255).astype(np.uint8)
