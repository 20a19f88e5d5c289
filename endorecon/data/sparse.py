"""Sparse SfM supervision: per-frame sparse depth and per-pair sparse flow.

The SfM stage gives world points and, per point, the frames that see it.  At
the training resolution each observation (frame f, point p) becomes a pixel
position (u, v) (pixel-centre convention, via :func:`endorecon.geometry.project`)
and a z-depth.  :class:`SparseCache` stores these observations once per
sequence, grouped by frame, so that the data module only gathers and
rasterises:

* sparse depth of frame i: z of i's points at their nearest pixel;
* sparse flow i -> j: for points seen in both, (u_j − u_i, v_j − v_i) at the
  point's nearest pixel in i.

Points are kept as point sets (sub-pixel uv) until the very end, so geometric
augmentation transforms the points and rasterises again rather than
interpolating a sparse map (see :mod:`endorecon.data.augment`).  When two points
fall on one pixel the nearer one (smaller z in the rasterised frame) wins.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import zipfile
from pathlib import Path

import numpy as np
import torch

from endorecon.data.sequence import Sequence
from endorecon.geometry import project, transform_points
from endorecon.utils.errors import InputError
from endorecon.utils.io import atomic_save_npz

CACHE_VERSION = 1


def sequence_fingerprint(seq: Sequence) -> str:
    """Hash of everything the cache depends on: size, K, mask, poses, points, visibility."""
    h = hashlib.sha1()
    h.update(np.array([seq.height, seq.width, len(seq)], dtype=np.int64).tobytes())
    for a in (seq.intrinsics, seq.mask, np.nan_to_num(seq.cam_from_world, nan=1e300), seq.points_xyz):
        h.update(np.ascontiguousarray(a).tobytes())
    for v in seq.visibility:
        h.update(np.int64(len(v)).tobytes())
        h.update(np.ascontiguousarray(v, dtype=np.int64).tobytes())
    return h.hexdigest()


def nearest_pixel(uv: np.ndarray) -> np.ndarray:
    """Nearest pixel (col, row) of pixel-centre coordinates: (M, 2) float -> (M, 2) int64.

    Pixel k covers [k − 0.5, k + 0.5); the floor keeps that rule for negative values too.
    """
    return np.floor(np.asarray(uv, dtype=np.float64) + 0.5).astype(np.int64)


def inside_image(uv: np.ndarray, height: int, width: int, mask: np.ndarray | None = None) -> np.ndarray:
    """(M,) bool: the nearest pixel of each uv (M, 2) lies in the image (and in ``mask`` (H, W) bool if given)."""
    px = nearest_pixel(uv)
    ok = (px[:, 0] >= 0) & (px[:, 0] < width) & (px[:, 1] >= 0) & (px[:, 1] < height)
    if mask is not None and ok.any():
        ok[ok] = mask[px[ok, 1], px[ok, 0]]
    return ok


def rasterize_points(
    uv: np.ndarray,
    values: np.ndarray,
    z: np.ndarray,
    height: int,
    width: int,
    mask: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Write per-point values at their nearest pixel; on collisions the smallest ``z`` wins.

    Args:
        uv: (M, 2) pixel-centre coordinates (u = column, v = row).
        values: (M, C) values to write (e.g. z for depth, du/dv for flow).
        z: (M,) depth used to resolve collisions (nearer point kept).
        height, width: output size.
        mask: optional (H, W) bool; points whose pixel is outside it are dropped.
    Returns:
        image: (C, H, W) float32, 0 where no point.
        valid: (1, H, W) bool.
    """
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    values = np.asarray(values)
    if values.ndim != 2 or len(values) != len(uv):
        raise ValueError(f"values must be ({len(uv)}, C), got {values.shape}")
    z = np.asarray(z, dtype=np.float64).reshape(-1)
    if len(z) != len(uv):
        raise ValueError(f"z must be ({len(uv)},), got {z.shape}")
    C = values.shape[1]
    image = np.zeros((C, height * width), dtype=np.float32)
    valid = np.zeros(height * width, dtype=bool)
    keep = inside_image(uv, height, width, mask)
    if keep.any():
        px = nearest_pixel(uv[keep])
        lin = px[:, 1] * width + px[:, 0]
        # Sort by pixel, then by z: the first entry of each pixel is the nearest point.
        order = np.lexsort((z[keep], lin))
        lin_sorted = lin[order]
        first = np.ones(len(order), dtype=bool)
        first[1:] = lin_sorted[1:] != lin_sorted[:-1]
        sel = order[first]
        image[:, lin[sel]] = values[keep][sel].T
        valid[lin[sel]] = True
    return image.reshape(C, height, width), valid.reshape(1, height, width)


@dataclasses.dataclass
class SparseCache:
    """Visible sparse points of every frame of one sequence at one resolution.

    Observations are stored flat, grouped by frame: frame f owns rows
    ``offsets[f]:offsets[f + 1]``, sorted by point id.

    Attributes:
        height, width: image size the pixel coordinates refer to.
        intrinsics: (3, 3) float64 pixel-centre K used for the projection.
        offsets: (N + 1,) int64.
        point_ids: (M,) int64 index into the sequence's ``points_xyz``.
        uv: (M, 2) float64 pixel coordinates (u = column, v = row), centre convention.
        z: (M,) float64 z-depth (> 0) in the sequence's units.
        mask: (H, W) bool mask the points were filtered with.
        fingerprint: :func:`sequence_fingerprint` of the sequence it was built from.
    """

    height: int
    width: int
    intrinsics: np.ndarray
    offsets: np.ndarray
    point_ids: np.ndarray
    uv: np.ndarray
    z: np.ndarray
    mask: np.ndarray
    fingerprint: str = ""

    def __post_init__(self) -> None:
        self.offsets = np.asarray(self.offsets, dtype=np.int64)
        self.point_ids = np.asarray(self.point_ids, dtype=np.int64)
        self.uv = np.asarray(self.uv, dtype=np.float64).reshape(-1, 2)
        self.z = np.asarray(self.z, dtype=np.float64)
        self.intrinsics = np.asarray(self.intrinsics, dtype=np.float64)
        self.mask = np.asarray(self.mask, dtype=bool)
        M = len(self.point_ids)
        if self.offsets.ndim != 1 or len(self.offsets) < 1 or self.offsets[0] != 0 or self.offsets[-1] != M:
            raise ValueError("offsets must start at 0 and end at the number of observations")
        if len(self.uv) != M or len(self.z) != M:
            raise ValueError("point_ids, uv and z must have the same length")
        if self.mask.shape != (self.height, self.width):
            raise ValueError(f"mask must be ({self.height}, {self.width}), got {self.mask.shape}")

    @property
    def num_frames(self) -> int:
        return len(self.offsets) - 1

    def __len__(self) -> int:
        return self.num_frames

    def _check_frame(self, i: int) -> int:
        i = int(i)
        if not 0 <= i < self.num_frames:
            raise IndexError(f"frame {i} out of range 0..{self.num_frames - 1}")
        return i

    def num_points(self, i: int) -> int:
        i = self._check_frame(i)
        return int(self.offsets[i + 1] - self.offsets[i])

    def frame_points(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Points visible in frame i: (ids (n,) int64 sorted, uv (n, 2) float64, z (n,) float64)."""
        i = self._check_frame(i)
        s = slice(self.offsets[i], self.offsets[i + 1])
        return self.point_ids[s], self.uv[s], self.z[s]

    def pair_points(self, i: int, j: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Points visible in both i and j: (uv_i (n, 2), uv_j (n, 2), z_i (n,), z_j (n,))."""
        ids_i, uv_i, z_i = self.frame_points(i)
        ids_j, uv_j, z_j = self.frame_points(j)
        _, a, b = np.intersect1d(ids_i, ids_j, assume_unique=True, return_indices=True)
        return uv_i[a], uv_j[b], z_i[a], z_j[b]

    def depth_map(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Sparse depth of frame i: (depth (1, H, W) float32, 0 = none; valid (1, H, W) bool)."""
        _, uv, z = self.frame_points(i)
        return rasterize_points(uv, z[:, None], z, self.height, self.width)

    def flow_map(self, i: int, j: int) -> tuple[np.ndarray, np.ndarray]:
        """Sparse flow i -> j at i's pixels: (flow (2, H, W) float32 in pixels; valid (1, H, W) bool)."""
        uv_i, uv_j, z_i, _ = self.pair_points(i, j)
        return rasterize_points(uv_i, uv_j - uv_i, z_i, self.height, self.width)

    # -------------------------------------------------------------- save/load
    def save(self, path: str | Path) -> Path:
        """Write the cache to one ``.npz`` (atomically)."""
        meta = dict(
            version=CACHE_VERSION, height=int(self.height), width=int(self.width), fingerprint=self.fingerprint
        )
        return atomic_save_npz(
            path,
            meta=np.array(json.dumps(meta)),
            intrinsics=self.intrinsics,
            offsets=self.offsets,
            point_ids=self.point_ids,
            uv=self.uv,
            z=self.z,
            mask=self.mask,
        )

    @classmethod
    def load(cls, path: str | Path) -> "SparseCache":
        path = Path(path)
        if not path.is_file():
            raise InputError("sparse cache not found", path, "build it with endorecon.data.sparse.build_sparse_cache")
        try:
            with np.load(path, allow_pickle=False) as f:
                meta = json.loads(str(f["meta"]))
                if meta.get("version") != CACHE_VERSION:
                    raise ValueError(f"cache version {meta.get('version')} != {CACHE_VERSION}")
                return cls(
                    height=int(meta["height"]),
                    width=int(meta["width"]),
                    intrinsics=f["intrinsics"],
                    offsets=f["offsets"],
                    point_ids=f["point_ids"],
                    uv=f["uv"],
                    z=f["z"],
                    mask=f["mask"],
                    fingerprint=str(meta.get("fingerprint", "")),
                )
        except (KeyError, ValueError, OSError, zipfile.BadZipFile, EOFError) as e:  # a cut file is a BadZipFile
            raise InputError(f"corrupt sparse cache ({e})", path, "delete it; it is rebuilt from the sequence") from e

    def matches(self, seq: Sequence) -> bool:
        """True if the cache was built from exactly this sequence (resolution, K, mask, poses, points)."""
        return self.fingerprint == sequence_fingerprint(seq)


def build_sparse_cache(seq: Sequence, min_depth: float = 1e-6) -> SparseCache:
    """Project every (point, visible frame) observation of ``seq`` at its current resolution.

    Call it on a sequence already resized/cropped to the training resolution
    (:func:`endorecon.data.transforms.resize_sequence`).  Observations in
    unregistered frames, behind the camera (z <= ``min_depth``), outside the
    image or outside ``seq.mask`` (at the nearest pixel) are dropped.
    """
    N, P = len(seq), len(seq.points_xyz)
    lens = np.array([len(v) for v in seq.visibility], dtype=np.int64)
    obs_frame = np.concatenate(seq.visibility).astype(np.int64) if P else np.zeros(0, np.int64)
    obs_point = np.repeat(np.arange(P, dtype=np.int64), lens)
    if len(obs_frame) and (obs_frame.min() < 0 or obs_frame.max() >= N):
        bad = int(obs_frame[(obs_frame < 0) | (obs_frame >= N)][0])
        raise InputError(
            f"sequence {seq.name!r}: visibility names frame {bad} but the sequence has {N} frames",
            fix="rerun the SfM stage for this sequence",
        )
    if not np.isfinite(seq.points_xyz).all():
        raise InputError(f"sequence {seq.name!r}: sparse points are not finite", fix="rerun the SfM stage")
    keep = seq.registered[obs_frame]
    obs_frame, obs_point = obs_frame[keep], obs_point[keep]
    uv = np.zeros((0, 2))
    z = np.zeros(0)
    if len(obs_frame):
        T = torch.from_numpy(seq.cam_from_world[obs_frame])  # (M, 4, 4) float64
        X = torch.from_numpy(seq.points_xyz[obs_point])[:, None]  # (M, 1, 3)
        X_cam = transform_points(T, X).reshape(1, -1, 3)
        uv_t, z_t = project(X_cam, torch.from_numpy(seq.intrinsics)[None])
        uv, z = uv_t[0].numpy(), z_t[0].numpy()
        ok = (z > min_depth) & np.isfinite(uv).all(axis=1)
        ok[ok] = inside_image(uv[ok], seq.height, seq.width, seq.mask)
        obs_frame, obs_point, uv, z = obs_frame[ok], obs_point[ok], uv[ok], z[ok]
    order = np.lexsort((obs_point, obs_frame))
    obs_frame, obs_point, uv, z = obs_frame[order], obs_point[order], uv[order], z[order]
    # A point listed twice for one frame is kept once.
    if len(obs_frame) > 1:
        dup = np.zeros(len(obs_frame), dtype=bool)
        dup[1:] = (obs_frame[1:] == obs_frame[:-1]) & (obs_point[1:] == obs_point[:-1])
        obs_frame, obs_point, uv, z = obs_frame[~dup], obs_point[~dup], uv[~dup], z[~dup]
    offsets = np.concatenate([[0], np.cumsum(np.bincount(obs_frame, minlength=N))]).astype(np.int64)
    return SparseCache(
        height=seq.height,
        width=seq.width,
        intrinsics=seq.intrinsics.copy(),
        offsets=offsets,
        point_ids=obs_point,
        uv=uv,
        z=z,
        mask=seq.mask.copy(),
        fingerprint=sequence_fingerprint(seq),
    )


def load_or_build_sparse_cache(seq: Sequence, path: str | Path) -> SparseCache:
    """The cache at ``path`` if it was built from this very ``seq``, else build and save it (new poses -> rebuilt)."""
    path = Path(path)
    if path.is_file():
        try:
            cache = SparseCache.load(path)
            if cache.matches(seq):
                return cache
        except InputError:
            pass  # stale or corrupt: rebuilt below
    cache = build_sparse_cache(seq)
    cache.save(path)
    return cache
