"""Endoscope appearance: solid mucosa texture, point-light shading, sensor effects.

The texture is a function of the 3D surface point (a solid texture): band-
limited periodic noise tiles sampled at several scales and rotations give the
mucosa's colour variation, a self-similar mucosa pattern of equal-contrast
octaves from 0.13 to 3.4 mm (so detail of a few pixels is there at every working
distance: what SIFT keys on) and branching vessels (level sets of noise fields
drawn as thin dark-red lines, small ones only beside larger ones).  Band-
limiting is in screen space: an octave finer than ~2 pixels is dropped and a
line thinner than a pixel is widened and dimmed, so distant walls neither
alias nor lose their coarser detail.  Because it depends only on the 3D point,
every frame sees the same texture at the same place.

Shading: a point light at the camera centre, inverse-square fall-off, Lambert
diffuse plus a narrow Blinn-Phong specular lobe (wet mucosa; with light =
viewer the half vector is the view direction) whose strength varies with a
wetness field; the highlight's normals are perturbed by ~2 mm bumps so
highlights form soft blobs on their crests, as on real tissue.  Then auto-exposure, gamma, shot and
read noise.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import map_coordinates

__all__ = ["SolidTexture", "shade", "Exposure", "sensor"]

_TILE = 48  # noise tile size (cells); features ~ 4 cells
_CELLS_PER_FEATURE = 4.0
_N_FIELDS = 24  # independent noise fields (rotation + offset of a tile)
_MUCOSA_OCTAVES_MM = (0.13, 0.2, 0.32, 0.5, 0.8, 1.3, 2.1, 3.4)
_MUCOSA_CONTRAST = 0.09  # log-albedo std of each octave
_TONE_A = 20.0  # strength of the logarithmic tone curve (larger lifts the far, dark walls more)


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
        self.rots = [_random_rotation(rng) for _ in range(_N_FIELDS)]
        self.offsets = rng.uniform(0, _TILE, (_N_FIELDS, 3))
        # per-patient tint: some mucosa is paler, some redder
        self.base = np.array([0.80, 0.19, 0.11]) * rng.uniform(0.92, 1.08, 3)

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
            M = np.concatenate(
                [self.rots[fields[i][1] % _N_FIELDS] * (_CELLS_PER_FEATURE / fields[i][0]) for i in sel]
            ).astype(np.float32)
            off = np.concatenate([self.offsets[fields[i][1] % _N_FIELDS] for i in sel]).astype(np.float32)
            c = (M @ p.T + off[:, None]).reshape(len(sel), 3, -1).transpose(1, 0, 2)  # (3, fields, N)
            out[sel] = map_coordinates(self.tiles[tile_id], c, order=1, mode="grid-wrap", prefilter=False)
        return out

    def __call__(self, p: np.ndarray, footprint_mm: np.ndarray) -> dict[str, np.ndarray]:
        """Surface properties at points.

        Args:
            p: (N, 3) surface points in mm.
            footprint_mm: (N,) size of one pixel on the surface (band-limits the pattern to the pixel grid).
        Returns:
            ``albedo`` (N, 3) linear RGB, ``specular`` (N,), ``bump`` (N, 3) normal perturbation.
        """
        fp = np.asarray(footprint_mm, dtype=np.float32)

        def fade(scale):  # an octave is kept where its features span >= 3 pixels, gone below 1.5
            return np.clip((scale / fp - 1.5) / 1.5, 0.0, 1.0)

        fields = [(14.0, 0), (10.0, 1), (5.0, 2), (7.0, 3), (2.4, 4), (0.9, 5), (2.5, 6)]
        fields += [(sc, 7 + i) for i, sc in enumerate(_MUCOSA_OCTAVES_MM)]
        fields += [(2.0, 20), (2.0, 21), (2.0, 22)]
        n = self.noises(p, fields)
        n_low, patch_n, wet, v_big, v_mid, v_small, small_patch = n[:7]
        octaves = n[7 : 7 + len(_MUCOSA_OCTAVES_MM)]
        b0, b1, b2 = n[-3:]
        # base colour: redder / paler patches over centimetres
        albedo = self.base[None] * (1 + 0.20 * n_low[:, None] * np.array([0.2, -1.0, -1.0])[None])
        # mucosa pattern: equal-contrast octaves from 0.2 to 4 mm (a self-similar pattern looks alike
        # at every working distance); each octave is dropped where it falls below the pixel grid, so the
        # image is band-limited in screen space instead of aliasing, and the coarser octaves remain
        m = np.zeros_like(fp)
        for sc, o in zip(_MUCOSA_OCTAVES_MM, octaves):
            m += _MUCOSA_CONTRAST * fade(sc) * o
        # perfusion: darker spots are redder (blood absorbs green and blue most)
        albedo = albedo * np.exp(m[:, None] * np.array([0.45, 1.0, 1.1])[None])
        # vessels: a hierarchy of thin lines (level sets of noise fields); the smaller ones grow only
        # beside the larger ones, so they look like branches
        patch = np.clip(0.2 + 0.8 * patch_n, 0.0, 1.0)
        big = _line(v_big, 0.07, 7.0, fp) * patch
        near_big = np.exp(-((v_big / 0.7) ** 2)) * patch
        mid = _line(v_mid, 0.08, 2.4, fp) * np.clip(1.6 * near_big, 0, 1)
        near_mid = np.exp(-((v_mid / 0.6) ** 2)) * np.clip(1.6 * near_big, 0, 1)
        small = _line(v_small, 0.10, 0.9, fp) * np.clip(near_mid + 0.5 * small_patch - 0.2, 0, 1)
        vessel = np.clip(0.85 * big + 0.7 * mid + 0.55 * small, 0, 0.9)
        vessel_rgb = np.array([0.40, 0.03, 0.04])
        albedo = albedo * (1 - vessel[:, None]) + vessel_rgb[None] * vessel[:, None]
        # wetness: specular strength varies over the surface (mucus film)
        specular = 0.6 * np.clip(0.8 + 0.6 * wet, 0.1, 1.6)
        # normal perturbation of ~1-2 mm bumps: highlights break into blobs on their crests
        bump = 0.06 * np.stack([b0, b1, b2], 1) * fade(2.0)[:, None]
        return {"albedo": np.clip(albedo, 0, 1), "specular": specular, "bump": bump}


def _line(v: np.ndarray, width: float, scale_mm: float, footprint_mm: np.ndarray) -> np.ndarray:
    """Line coverage in [0, 1] at the zero level set of a unit-std noise field ``v`` of feature size ``scale_mm``.

    ``width`` is the half-width in units of the field; on the surface it is about ``width * scale_mm / 4.4`` mm
    (the field's gradient is ~4.4 / scale_mm per mm).  A line thinner than ~0.7 pixel is widened to that and
    dimmed to keep its integrated darkness (a band-limited line instead of broken dashes).
    """
    grad = 4.4 / scale_mm
    w_min = 0.7 * footprint_mm * grad
    w = np.maximum(width, w_min)
    return (width / w) * np.exp(-((v / w) ** 2))


def shade(
    points: np.ndarray,
    normals: np.ndarray,
    ray_dirs: np.ndarray,
    ray_len: np.ndarray,
    texture: SolidTexture,
    footprint_mm: np.ndarray,
    shininess: float = 90.0,
) -> np.ndarray:
    """Linear radiance (N, 3) of hit points lit by a point light at the camera.

    Args:
        points: (N, 3) world points (mm).
        normals: (N, 3) unit surface normals (either orientation).
        ray_dirs: (N, 3) unit directions from the camera to the points.
        ray_len: (N,) distance camera -> point (mm).
        texture: the surface's :class:`SolidTexture`.
        footprint_mm: (N,) pixel footprint on the surface.
        shininess: Blinn-Phong exponent of the wet-mucosa highlight (larger = smaller highlights).
    """
    props = texture(points, footprint_mm)
    cos = np.abs(np.sum(normals * ray_dirs, axis=1))  # light at the camera: cos(incidence) = cos(view)
    # the bumps shape the highlights only: on diffuse shading at grazing views they would make a
    # strongly view-dependent pattern that moves over the surface from frame to frame
    n = normals + props["bump"]
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-9)
    cos_b = np.abs(np.sum(n * ray_dirs, axis=1))
    falloff = 1.0 / np.maximum(ray_len, 1.0) ** 2
    diffuse = props["albedo"] * cos[:, None]
    spec = props["specular"] * cos_b**shininess
    return (diffuse + spec[:, None]) * falloff[:, None]


class Exposure:
    """Auto-exposure with temporal smoothing, like an endoscope's video processor.

    Args:
        target: value the 98th percentile of the frame is mapped to.
        smoothing: weight of the previous gain (0 = per-frame exposure).
    """

    def __init__(self, target: float = 0.4, smoothing: float = 0.6):
        self.target = target
        self.smoothing = smoothing
        self.gain: float | None = None

    def __call__(self, radiance: np.ndarray) -> float:
        ref = float(np.percentile(radiance.mean(axis=-1), 93)) if radiance.size else 1.0
        g = self.target / max(ref, 1e-12)
        self.gain = g if self.gain is None else self.smoothing * self.gain + (1 - self.smoothing) * g
        return self.gain


def sensor(linear: np.ndarray, rng: np.random.Generator, read_noise: float = 0.002, shot_noise: float = 0.010) -> np.ndarray:
    """Tone-map linear RGB (H, W, 3) to uint8 with gamma, shot and read noise, and a mild optical blur.

    The tone curve is logarithmic (as an endoscope's video processor compresses its wide dynamic range):
    walls at a few millimetres do not burn out while the far, inverse-square-dark walls keep visible
    detail; its shoulder makes highlights saturate softly.
    """
    from scipy.ndimage import gaussian_filter

    img = np.log1p(_TONE_A * np.maximum(linear, 0.0)) / np.log1p(_TONE_A)
    img = np.clip(img, 0.0, 1.0)
    img = gaussian_filter(img, sigma=(0.6, 0.6, 0), mode="nearest")  # lens PSF / demosaicing softness
    img = img + rng.standard_normal(img.shape).astype(np.float32) * (read_noise + shot_noise * np.sqrt(img))
    img = np.clip(img, 0.0, 1.0) ** (1 / 2.2)
    return np.round(img * 255).astype(np.uint8)
