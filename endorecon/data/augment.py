"""Training augmentations of a frame pair: photometric and geometric.

Photometric (images only, kornia functional ops): colour shift (brightness,
contrast, saturation, hue), Gaussian blur, Gaussian noise.  Both frames of a
pair get the same colour shift and blur; noise is drawn per image.

Geometric (flip, rotation) change the camera, so everything that depends on
the camera changes with the images.  A geometric transform is the triple
(A, M, K'):

* ``A`` (3x3) maps old pixel coordinates to new ones, u' = A u (homogeneous);
* ``M`` (3x3, orthogonal) maps old camera coordinates to new ones, X' = M X,
  with M's third row (0, 0, 1) so z-depth is unchanged;
* ``K' = A K Mᵀ``, so that projecting X' with K' gives A u.

Horizontal flip: A: u -> W−1−u, M = diag(−1, 1, 1), K' has cx' = W−1−cx (and
the skew negated).  Rotation by angle a: the camera rolls about its optical
axis, M = R_z(a), A = K R_z(a) K⁻¹ (a rotation of the image about the principal
point, exact for fx = fy; with fx ≠ fy it is the affine map the roll really
produces) and K' = K.

Both frames of a pair get the same transform, so the relative pose becomes
``M cam_j_from_cam_i Mᵀ`` (4x4, a proper rigid motion even for the flip), and
sparse flow (u_j' − u_i') = A₂ₓ₂ (u_j − u_i).  Sparse depth and flow are
transformed as point sets (sub-pixel uv mapped by A, then rasterised again by
:mod:`endorecon.data.sparse`), never interpolated.  Images are warped
bilinearly, masks and simulated depth with nearest neighbour (z is invariant).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Mapping

import numpy as np
import torch
from kornia.enhance import adjust_brightness, adjust_contrast, adjust_hue, adjust_saturation
from kornia.filters import gaussian_blur2d
from kornia.geometry.transform import warp_affine

from endorecon.utils.errors import InputError


# ----------------------------------------------------------------- config
@dataclasses.dataclass
class AugmentConfig:
    """Probabilities and ranges (``conf/data/default.yaml: augment``).

    Attributes:
        enabled: master switch (validation/test/predict never augment).
        p_color: probability of a colour shift; then brightness b ~ U(−brightness, brightness)
            added, contrast and saturation factors ~ U(1 − x, 1 + x), hue shift ~ U(−hue, hue)
            in fractions of a full turn.
        p_blur: probability of a Gaussian blur with sigma ~ U(blur_sigma).
        p_noise: probability of additive Gaussian noise with std ~ U(0, noise_std).
        p_flip: probability of a horizontal flip.
        p_rotate: probability of a roll about the optical axis by U(−max_rotation_deg, max_rotation_deg).
    """

    enabled: bool = True
    p_color: float = 0.8
    brightness: float = 0.1
    contrast: float = 0.2
    saturation: float = 0.2
    hue: float = 0.02
    p_blur: float = 0.2
    blur_sigma: tuple[float, float] = (0.2, 1.0)
    p_noise: float = 0.2
    noise_std: float = 0.02
    p_flip: float = 0.5
    p_rotate: float = 0.5
    max_rotation_deg: float = 10.0

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None, key: str = "data.augment") -> "AugmentConfig":
        """From a (Hydra/omegaconf) mapping; unknown keys and bad values raise :class:`InputError`."""
        if d is None:
            return cls()
        if isinstance(d, AugmentConfig):
            return d
        d = dict(d)
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise InputError(f"unknown key(s) {unknown} in {key}", fix=f"allowed keys: {sorted(names)}")
        if "blur_sigma" in d:
            d["blur_sigma"] = tuple(float(v) for v in d["blur_sigma"])
        cfg = cls(**d)
        for name in ("p_color", "p_blur", "p_noise", "p_flip", "p_rotate"):
            p = getattr(cfg, name)
            if not 0.0 <= float(p) <= 1.0:
                raise InputError(f"{key}.{name} = {p} is not a probability", fix="use a value in [0, 1]")
        for name in ("brightness", "contrast", "saturation", "hue", "noise_std", "max_rotation_deg"):
            if float(getattr(cfg, name)) < 0:
                raise InputError(f"{key}.{name} must be >= 0, got {getattr(cfg, name)}")
        lo, hi = cfg.blur_sigma
        if not 0 < lo <= hi:
            raise InputError(f"{key}.blur_sigma must be [low, high] with 0 < low <= high, got {cfg.blur_sigma}")
        return cfg


# ------------------------------------------------------------- geometric
@dataclasses.dataclass
class GeometricTransform:
    """u' = A u, X' = M X, K' = A K Mᵀ (see module docstring).

    Attributes:
        A: (3, 3) float64 pixel map (last row 0, 0, 1).
        M: (3, 3) float64 orthogonal camera-frame map with third row (0, 0, 1).
        K_src: (3, 3) intrinsics before.
        K: (3, 3) intrinsics after.
    """

    A: np.ndarray
    M: np.ndarray
    K_src: np.ndarray
    K: np.ndarray

    @staticmethod
    def identity(K: np.ndarray) -> "GeometricTransform":
        K = np.asarray(K, dtype=np.float64)
        return GeometricTransform(np.eye(3), np.eye(3), K.copy(), K.copy())

    def then(self, other: "GeometricTransform") -> "GeometricTransform":
        """``other`` applied after ``self``."""
        if not np.allclose(other.K_src, self.K, atol=1e-9):
            raise ValueError("transforms do not chain: other.K_src != self.K")
        return GeometricTransform(other.A @ self.A, other.M @ self.M, self.K_src, other.K)

    def inverse(self) -> "GeometricTransform":
        return GeometricTransform(np.linalg.inv(self.A), self.M.T.copy(), self.K.copy(), self.K_src.copy())

    def apply_uv(self, uv: np.ndarray) -> np.ndarray:
        """Pixel coordinates (n, 2) -> (n, 2)."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        return uv @ self.A[:2, :2].T + self.A[:2, 2]

    def apply_vectors(self, d: np.ndarray) -> np.ndarray:
        """Pixel displacements (n, 2) -> (n, 2) (the linear part of A)."""
        return np.asarray(d, dtype=np.float64).reshape(-1, 2) @ self.A[:2, :2].T

    def apply_pose(self, cam_j_from_cam_i: np.ndarray) -> np.ndarray:
        """Relative pose (4, 4) of a pair whose frames both get this transform: M T Mᵀ."""
        M4 = np.eye(4)
        M4[:3, :3] = self.M
        return M4 @ np.asarray(cam_j_from_cam_i, dtype=np.float64) @ M4.T

    def warp(self, image: torch.Tensor, mode: str = "bilinear") -> torch.Tensor:
        """Warp (C, H, W) (any dtype; bool is warped as 0/1 with nearest) so that out(A u) = in(u); zeros outside."""
        if image.dim() != 3:
            raise ValueError(f"image must be (C, H, W), got {tuple(image.shape)}")
        if np.allclose(self.A, np.eye(3), atol=1e-12):
            return image.clone()
        H, W = image.shape[-2:]
        if np.allclose(self.A, [[-1.0, 0.0, W - 1.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], atol=1e-12):
            return torch.flip(image, dims=[-1])  # exact, no resampling
        dtype = image.dtype
        x = image.float()[None]
        if dtype == torch.bool:
            mode = "nearest"
        Mt = torch.as_tensor(self.A[:2], dtype=torch.float32)[None]
        # kornia: dst(A u) = src(u) in pixel coordinates with centres at integers (align_corners=True).
        out = warp_affine(x, Mt, (H, W), mode=mode, padding_mode="zeros", align_corners=True)[0]
        return out > 0.5 if dtype == torch.bool else out.to(dtype)


def flip_transform(K: np.ndarray, width: int) -> GeometricTransform:
    """Horizontal flip of a ``width``-pixel image: u -> W−1−u, X -> −X, cx -> W−1−cx."""
    K = np.asarray(K, dtype=np.float64)
    A = np.array([[-1.0, 0.0, width - 1.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    M = np.diag([-1.0, 1.0, 1.0])
    return GeometricTransform(A, M, K.copy(), A @ K @ M.T)


def rotation_transform(K: np.ndarray, angle_rad: float) -> GeometricTransform:
    """Roll about the optical axis: M = R_z(angle), A = K M K⁻¹, K unchanged."""
    K = np.asarray(K, dtype=np.float64)
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    M = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    A = K @ M @ np.linalg.inv(K)
    A[2] = (0.0, 0.0, 1.0)  # exact, not 1 ± eps
    return GeometricTransform(A, M, K.copy(), K.copy())


def sample_geometric(rng: np.random.Generator, cfg: AugmentConfig, K: np.ndarray, width: int) -> GeometricTransform:
    """Draw flip / rotation with the configured probabilities (identity when disabled)."""
    tf = GeometricTransform.identity(K)
    if not cfg.enabled:
        return tf
    # Always draw both numbers so that one choice does not shift the stream of the next.
    u_flip, u_rot, angle = rng.random(), rng.random(), rng.uniform(-1.0, 1.0)
    if u_flip < cfg.p_flip:
        tf = tf.then(flip_transform(tf.K, width))
    if u_rot < cfg.p_rotate and cfg.max_rotation_deg > 0:
        tf = tf.then(rotation_transform(tf.K, math.radians(angle * cfg.max_rotation_deg)))
    return tf


# ------------------------------------------------------------ photometric
def photometric(images: torch.Tensor, rng: np.random.Generator, cfg: AugmentConfig) -> torch.Tensor:
    """Colour shift + blur (same for all images) and noise (per image).

    Args:
        images: (B, 3, H, W) float in [0, 1] (e.g. the two frames of a pair).
    Returns:
        (B, 3, H, W) float in [0, 1].
    """
    if images.dim() != 4 or images.shape[1] != 3:
        raise ValueError(f"images must be (B, 3, H, W), got {tuple(images.shape)}")
    if not cfg.enabled:
        return images
    r = rng.random(3)
    colour = rng.uniform(-1.0, 1.0, size=4)
    sigma = rng.uniform(*cfg.blur_sigma)
    noise_std = rng.uniform(0.0, cfg.noise_std)
    noise_seed = int(rng.integers(0, 2**62))
    x = images
    if r[0] < cfg.p_color:
        x = adjust_brightness(x, float(colour[0] * cfg.brightness))
        x = adjust_contrast(x, float(1.0 + colour[1] * cfg.contrast))
        x = adjust_saturation(x, float(1.0 + colour[2] * cfg.saturation))
        x = adjust_hue(x, float(colour[3] * cfg.hue * 2.0 * math.pi))
    if r[1] < cfg.p_blur:
        k = 2 * math.ceil(2.0 * sigma) + 1
        x = gaussian_blur2d(x, (k, k), (sigma, sigma))
    if r[2] < cfg.p_noise and noise_std > 0:
        g = torch.Generator().manual_seed(noise_seed)
        x = x + noise_std * torch.randn(x.shape, generator=g, dtype=x.dtype)
    return x.clamp(0.0, 1.0)


# ------------------------------------------------------------ pair sample
@dataclasses.dataclass
class PairSample:
    """One training pair before rasterisation: dense images and sparse point sets.

    Attributes:
        image_i, image_j: (3, H, W) float32 in [0, 1].
        mask_i, mask_j: (1, H, W) bool.
        K: (3, 3) float64 pixel-centre intrinsics (shared by both frames).
        cam_j_from_cam_i: (4, 4) float64.
        ids_i, uv_i, z_i: frame i's visible sparse points: ids (n,), uv (n, 2), z (n,).
        ids_j, uv_j, z_j: the same for frame j.
        sim_depth_i, sim_depth_j: (1, H, W) float32 or None; sim_valid_i, sim_valid_j: (1, H, W) bool or None.
    """

    image_i: torch.Tensor
    image_j: torch.Tensor
    mask_i: torch.Tensor
    mask_j: torch.Tensor
    K: np.ndarray
    cam_j_from_cam_i: np.ndarray
    ids_i: np.ndarray
    uv_i: np.ndarray
    z_i: np.ndarray
    ids_j: np.ndarray
    uv_j: np.ndarray
    z_j: np.ndarray
    sim_depth_i: torch.Tensor | None = None
    sim_depth_j: torch.Tensor | None = None
    sim_valid_i: torch.Tensor | None = None
    sim_valid_j: torch.Tensor | None = None


def apply_geometric(sample: PairSample, tf: GeometricTransform) -> PairSample:
    """The pair seen through the transformed camera (both frames alike)."""
    has_sim = sample.sim_depth_i is not None
    # images bilinear; masks nearest (no blending)
    img = tf.warp(torch.cat([sample.image_i, sample.image_j]).float(), "bilinear")
    near = tf.warp(torch.cat([sample.mask_i.float(), sample.mask_j.float()]), "nearest")
    out = dataclasses.replace(
        sample,
        image_i=img[:3],
        image_j=img[3:],
        mask_i=near[0:1] > 0.5,
        mask_j=near[1:2] > 0.5,
        K=tf.K.copy(),
        cam_j_from_cam_i=tf.apply_pose(sample.cam_j_from_cam_i),
        uv_i=tf.apply_uv(sample.uv_i),
        uv_j=tf.apply_uv(sample.uv_j),
    )
    if has_sim:
        # The simulated depth (a label): bilinear over valid pixels only, kept where (almost) all the weight is
        # valid and renormalised by it, as geometry.warp_depth samples depth.  Nearest put each rotated pixel's
        # label on a surface point up to 0.7 px away (p95 ~0.3 mm on the phantom); z itself is unchanged by the
        # roll.  Identity and flip are exact either way.
        vs = [sample.sim_valid_i.float(), sample.sim_valid_j.float()]
        ds = [torch.where(v > 0.5, d, torch.zeros_like(d)) for v, d in zip(vs, (sample.sim_depth_i, sample.sim_depth_j))]
        w = tf.warp(torch.cat([*vs, *ds]), "bilinear")
        for k, name in enumerate(("i", "j")):
            support, depth = w[k:k + 1], w[2 + k:3 + k]
            ok = support > 1.0 - 1e-3
            setattr(out, f"sim_valid_{name}", ok)
            setattr(out, f"sim_depth_{name}",
                    torch.where(ok, depth / torch.where(ok, support, torch.ones_like(support)), torch.zeros_like(depth)))
    return out


def augment_pair(sample: PairSample, rng: np.random.Generator, cfg: AugmentConfig) -> PairSample:
    """Random geometric then photometric augmentation of a training pair (identity when ``cfg.enabled`` is False)."""
    if not cfg.enabled:
        return sample
    tf = sample_geometric(rng, cfg, sample.K, sample.image_i.shape[-1])
    out = apply_geometric(sample, tf)
    pair = photometric(torch.stack([out.image_i, out.image_j]), rng, cfg)
    out.image_i, out.image_j = pair[0], pair[1]
    return out
