"""The in-memory record of one video sequence, and its ground truth kept apart.

:class:`Sequence` is what every stage reads: frame paths, intrinsics, the
valid-pixel mask, ``cam_from_world`` per registered frame and the sparse SfM
points with their visibility.  :class:`GroundTruth` (GT depth, GT poses, the
"CT" mesh) is a separate object: only evaluation and tests are handed one, so
training code cannot read it by accident.

Conventions (see :mod:`endorecon.geometry`): ``intrinsics`` is a 3x3 pinhole
matrix at the frames' resolution with pixel (0, 0) the *centre* of the
top-left pixel; ``cam_from_world`` maps world to camera coordinates
(x_cam = R x_world + t); depth is z-depth in the sequence's ``units``.

On disk a sequence is a folder::

    <seq>/frames/*.jpg|*.png   frames, sorted by file name
    <seq>/mask.png             valid pixels white, same size as the frames
    <seq>/camera.json          {"width", "height", "fx", "fy", "cx", "cy",
                                "pixel_origin": "center", "units"}
    <seq>/sequence.npz         optional: poses and sparse points (after SfM)
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import re
import zipfile
import zlib
from pathlib import Path

import numpy as np

from endorecon.utils.errors import InputError
from endorecon.utils.io import atomic_save_npz, atomic_write_text

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff")


@dataclasses.dataclass
class Sequence:
    """One video sequence.

    Attributes:
        name: e.g. ``"patient_03/seq_00"``.
        frame_paths: N frame image paths, in temporal order.
        intrinsics: (3, 3) float64, pixel-centre convention, at (height, width).
        height, width: frame size in pixels.
        mask: (height, width) bool, True = valid (inside the endoscope's view).
        cam_from_world: (N, 4, 4) float64; rows of unregistered frames are NaN.
        points_xyz: (P, 3) float64 sparse SfM points in world coordinates.
        visibility: list of P int arrays, the frame indices (0..N-1) that see each point.
        points_rgb: optional (P, 3) uint8 colours.
        units: ``"mm"`` (phantom, metric) or ``"sfm"`` (arbitrary SfM scale).
        source: where it came from (``"phantom"``, ``"colmap"``, ``"original"``, ``"video"``...).
        patient: patient id used by the fold split (None if unknown).
        native_window: (x0, y0, w, h) window of the frame *files* that this record
            shows, resized to (height, width); None = the files are used as they are.
            Set by :func:`endorecon.data.transforms.resize_sequence` / ``crop_sequence``.
    """

    name: str
    frame_paths: list[Path]
    intrinsics: np.ndarray
    height: int
    width: int
    mask: np.ndarray
    cam_from_world: np.ndarray | None = None
    points_xyz: np.ndarray | None = None
    visibility: list[np.ndarray] | None = None
    points_rgb: np.ndarray | None = None
    units: str = "sfm"
    source: str = "unknown"
    patient: int | None = None
    native_window: tuple[int, int, int, int] | None = None

    def __post_init__(self) -> None:
        self.frame_paths = [Path(p) for p in self.frame_paths]
        self.intrinsics = np.asarray(self.intrinsics, dtype=np.float64)
        self.mask = np.asarray(self.mask, dtype=bool)
        if self.intrinsics.shape != (3, 3):
            raise InputError(f"intrinsics must be 3x3, got {self.intrinsics.shape}", fix="pass fx fy cx cy")
        if self.mask.shape != (self.height, self.width):
            raise InputError(
                f"mask has size {self.mask.shape[1]}x{self.mask.shape[0]} (WxH) but frames are "
                f"{self.width}x{self.height}",
                fix="give a mask of the frames' size (white = valid)",
            )
        n = len(self.frame_paths)
        if self.cam_from_world is None:
            self.cam_from_world = np.full((n, 4, 4), np.nan)
        self.cam_from_world = np.asarray(self.cam_from_world, dtype=np.float64)
        if self.cam_from_world.shape != (n, 4, 4):
            raise InputError(f"cam_from_world must be ({n}, 4, 4), got {self.cam_from_world.shape}")
        if self.points_xyz is None:
            self.points_xyz = np.zeros((0, 3))
        self.points_xyz = np.asarray(self.points_xyz, dtype=np.float64).reshape(-1, 3)
        if self.visibility is None:
            self.visibility = [np.zeros(0, dtype=np.int64) for _ in range(len(self.points_xyz))]
        self.visibility = [np.asarray(v, dtype=np.int64) for v in self.visibility]
        if len(self.visibility) != len(self.points_xyz):
            raise InputError(f"{len(self.points_xyz)} points but {len(self.visibility)} visibility lists")

    # ------------------------------------------------------------------ access
    def __len__(self) -> int:
        return len(self.frame_paths)

    @property
    def registered(self) -> np.ndarray:
        """(N,) bool: frames with a finite pose."""
        return np.isfinite(self.cam_from_world).all(axis=(1, 2))

    def load_frame(self, i: int) -> np.ndarray:
        """Frame ``i`` as (height, width, 3) uint8 RGB; a clear error if missing, unreadable or of the wrong size."""
        if self.native_window is None:
            return read_rgb(self.frame_paths[i], expect_hw=(self.height, self.width))
        from PIL import Image

        x0, y0, w, h = self.native_window
        img = read_rgb(self.frame_paths[i])
        if img.shape[0] < y0 + h or img.shape[1] < x0 + w:
            raise InputError(
                f"frame is {img.shape[1]}x{img.shape[0]} (WxH), smaller than the window {self.native_window}",
                self.frame_paths[i],
                "all frames of a sequence must have the same size",
            )
        img = img[y0 : y0 + h, x0 : x0 + w]
        if (h, w) != (self.height, self.width):
            img = np.asarray(Image.fromarray(img).resize((self.width, self.height), Image.BILINEAR))
        return img

    def replace(self, **changes) -> "Sequence":
        return dataclasses.replace(self, **changes)

    # -------------------------------------------------------------- save/load
    def save(self, path: str | Path) -> Path:
        """Write poses, points and metadata to one ``.npz`` (atomically). Frames are referenced, not copied."""
        path = Path(path)
        offsets = np.cumsum([0] + [len(v) for v in self.visibility]).astype(np.int64)
        flat = np.concatenate(self.visibility) if self.visibility else np.zeros(0, np.int64)
        meta = dict(
            name=self.name,
            frame_paths=[str(p) for p in self.frame_paths],
            height=self.height,
            width=self.width,
            units=self.units,
            source=self.source,
            patient=self.patient,
            native_window=None if self.native_window is None else [int(v) for v in self.native_window],
        )
        arrays = dict(
            meta=np.array(json.dumps(meta)),
            intrinsics=self.intrinsics,
            mask=self.mask,
            cam_from_world=self.cam_from_world,
            points_xyz=self.points_xyz,
            vis_offsets=offsets,
            vis_frames=flat.astype(np.int64),
        )
        if self.points_rgb is not None:
            arrays["points_rgb"] = np.asarray(self.points_rgb, dtype=np.uint8)
        return atomic_save_npz(path, **arrays)

    @classmethod
    def load(cls, path: str | Path) -> "Sequence":
        path = Path(path)
        if not path.is_file():
            raise InputError("sequence record not found", path, "run the SfM stage (python -m endorecon.sfm) first")
        try:
            z = np.load(path, allow_pickle=False)
            meta = json.loads(str(z["meta"]))
            offsets = z["vis_offsets"]
            flat = z["vis_frames"]
            vis = [flat[offsets[k] : offsets[k + 1]] for k in range(len(offsets) - 1)]
            return cls(
                name=meta["name"],
                frame_paths=meta["frame_paths"],
                intrinsics=z["intrinsics"],
                height=int(meta["height"]),
                width=int(meta["width"]),
                mask=z["mask"],
                cam_from_world=z["cam_from_world"],
                points_xyz=z["points_xyz"],
                visibility=vis,
                points_rgb=z["points_rgb"] if "points_rgb" in z else None,
                units=meta["units"],
                source=meta["source"],
                patient=meta["patient"],
                native_window=None if meta.get("native_window") is None else tuple(meta["native_window"]),
            )
        except (KeyError, ValueError, OSError, EOFError, zipfile.BadZipFile, zlib.error) as e:
            raise InputError(f"corrupt sequence record ({type(e).__name__}: {e})", path, "delete it and rerun the stage that wrote it") from e


@dataclasses.dataclass
class GroundTruth:
    """Ground truth of one sequence: only evaluation and tests open it.

    Attributes:
        depth_mm: (N, H, W) float32 z-depth in mm, 0 where invalid (outside mask / no hit).
        cam_from_world: (N, 4, 4) float64 poses in mm.
        mesh_path: the "CT" surface mesh (PLY, mm) or None for train-only patients.
    """

    depth_mm: np.ndarray
    cam_from_world: np.ndarray
    mesh_path: Path | None = None


# ---------------------------------------------------------------------- images
def read_rgb(path: str | Path, expect_hw: tuple[int, int] | None = None) -> np.ndarray:
    """Read an image as (H, W, 3) uint8 RGB with a clear error on any problem."""
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if not path.is_file():
        raise InputError("frame file is missing", path, "restore the file or remove it from the sequence")
    try:
        with Image.open(path) as im:
            im.load()
            arr = np.asarray(im.convert("RGB"))
    except (UnidentifiedImageError, OSError, SyntaxError) as e:
        raise InputError(f"cannot read image ({e})", path, "re-export the frame or delete it") from e
    if expect_hw is not None and arr.shape[:2] != tuple(expect_hw):
        raise InputError(
            f"frame is {arr.shape[1]}x{arr.shape[0]} (WxH), expected {expect_hw[1]}x{expect_hw[0]}",
            path,
            "all frames of a sequence must have the same size",
        )
    return arr


def read_mask(path: str | Path, expect_hw: tuple[int, int] | None = None) -> np.ndarray:
    """Read a valid-pixel mask (white/non-zero = valid) as (H, W) bool."""
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if not path.is_file():
        raise InputError("mask file is missing", path, "give a mask image (white = valid) or omit it to estimate one")
    try:
        with Image.open(path) as im:
            arr = np.asarray(im.convert("L"))
    except (UnidentifiedImageError, OSError, SyntaxError) as e:
        raise InputError(f"cannot read mask ({e})", path, "re-export the mask as PNG/BMP") from e
    if expect_hw is not None and arr.shape != tuple(expect_hw):
        raise InputError(
            f"mask is {arr.shape[1]}x{arr.shape[0]} (WxH) but frames are {expect_hw[1]}x{expect_hw[0]}",
            path,
            "resize the mask to the frames' size",
        )
    mask = arr > 127
    if not mask.any():
        raise InputError("mask has no valid (white) pixel", path, "white marks valid pixels")
    return mask


def natural_key(path: Path) -> list:
    """Sort key that orders numbered names by number (``frame_2`` before ``frame_10``), not as text."""
    return [(0, int(t), "") if t.isdigit() else (1, 0, t) for t in re.split(r"(\d+)", path.name)]


def list_frames(frames_dir: str | Path) -> list[Path]:
    """Image files of a directory in natural order (numbers by value); a clear error if there are none."""
    frames_dir = Path(frames_dir)
    if not frames_dir.is_dir():
        raise InputError("frames directory does not exist", frames_dir, "pass the folder that holds the frames")
    paths = sorted((p for p in frames_dir.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".")),
                   key=natural_key)
    if not paths:
        raise InputError(
            f"no images ({', '.join(IMAGE_SUFFIXES)}) in directory", frames_dir, "pass the folder that holds the frames"
        )
    return paths


# ------------------------------------------------------------- folder format
def write_camera_json(path: str | Path, K: np.ndarray, height: int, width: int, units: str = "mm") -> Path:
    """Write ``camera.json`` (pixel-centre convention)."""
    K = np.asarray(K, dtype=np.float64)
    cam = dict(
        width=int(width),
        height=int(height),
        fx=float(K[0, 0]),
        fy=float(K[1, 1]),
        cx=float(K[0, 2]),
        cy=float(K[1, 2]),
        pixel_origin="center",
        units=units,
    )
    return atomic_write_text(path, json.dumps(cam, indent=2) + "\n")


def read_camera_json(path: str | Path) -> tuple[np.ndarray, int, int, str]:
    """Read ``camera.json`` -> (K (3,3) pixel-centre, height, width, units)."""
    path = Path(path)
    if not path.is_file():
        raise InputError("camera file is missing", path, "write camera.json with width, height, fx, fy, cx, cy")
    try:
        cam = json.loads(path.read_text())
        K = np.array([[cam["fx"], 0, cam["cx"]], [0, cam["fy"], cam["cy"]], [0, 0, 1]], dtype=np.float64)
        origin = cam.get("pixel_origin", "center")
        if origin not in ("center", "corner"):  # a misspelling read as "center" would shift K by half a pixel
            raise InputError(f"camera pixel_origin must be \"center\" or \"corner\", got {origin!r}", path,
                             'write "center" if (cx, cy) count from the first pixel\'s centre (COLMAP: "corner")')
        if origin == "corner":
            K[0, 2] -= 0.5
            K[1, 2] -= 0.5
        h, w = int(cam["height"]), int(cam["width"])
    except (KeyError, ValueError, TypeError) as e:
        raise InputError(f"bad camera file ({e})", path, "it needs width, height, fx, fy, cx, cy") from e
    if not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError("camera intrinsics are not finite and positive", path)
    return K, h, w, cam.get("units", "sfm")


def load_sequence_folder(seq_dir: str | Path, name: str | None = None, patient: int | None = None) -> Sequence:
    """Read a sequence folder (frames/, mask.png, camera.json, optional sequence.npz)."""
    seq_dir = Path(seq_dir)
    if not seq_dir.is_dir():
        raise InputError("sequence folder does not exist", seq_dir)
    frames = list_frames(seq_dir / "frames")
    K, h, w, units = read_camera_json(seq_dir / "camera.json")
    mask = read_mask(seq_dir / "mask.png", expect_hw=(h, w))
    rec = seq_dir / "sequence.npz"
    if rec.is_file():
        seq = Sequence.load(rec)
        if [p.name for p in seq.frame_paths] != [p.name for p in frames]:
            raise InputError(
                "sequence.npz lists other frames than frames/", rec, "delete sequence.npz and rerun the SfM stage"
            )
        return seq.replace(frame_paths=frames)
    return Sequence(
        name=name or seq_dir.name,
        frame_paths=frames,
        intrinsics=K,
        height=h,
        width=w,
        mask=mask,
        units=units,
        source="folder",
        patient=patient,
    )


# ------------------------------------------------------------------ poses.txt
def write_poses_txt(path: str | Path, names: list[str], cam_from_world: np.ndarray) -> Path:
    """Write ``poses.txt``: one line per frame, ``<name> m00 m01 ... m33`` (cam_from_world, row-major).

    Unregistered frames (NaN rows) are written as ``nan``.
    """
    cam_from_world = np.asarray(cam_from_world, dtype=np.float64)
    if len(names) != len(cam_from_world):
        raise ValueError(f"{len(names)} names but {len(cam_from_world)} poses")
    lines = ["# frame cam_from_world (4x4 row-major; x_cam = R x_world + t)"]
    for n, T in zip(names, cam_from_world):
        if not n.strip() or n != n.strip() or "\n" in n:  # read back as the first field(s) of its line
            raise ValueError(f"frame name {n!r} cannot be written to poses.txt (empty, edge spaces or a newline)")
        lines.append(n + " " + " ".join(f"{v:.10g}" for v in T.reshape(-1)))
    return atomic_write_text(path, "\n".join(lines) + "\n")


def read_poses_txt(path: str | Path) -> tuple[list[str], np.ndarray]:
    """Read ``poses.txt`` -> (names, cam_from_world (N, 4, 4))."""
    path = Path(path)
    if not path.is_file():
        raise InputError("pose file is missing", path)
    names, mats = [], []
    for ln, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip() or line.startswith("#"):
            continue
        # the 16 numbers from the right: a frame's name may hold spaces (any frames folder is an input)
        parts = line.strip().rsplit(None, 16)
        if len(parts) != 17:
            raise InputError(f"line {ln}: expected a name and 16 numbers, got {len(parts)} fields", path)
        try:
            mats.append(np.array([float(v) for v in parts[1:]]).reshape(4, 4))
        except ValueError as e:
            raise InputError(f"line {ln}: {e}", path) from e
        names.append(parts[0])
    return names, np.stack(mats) if mats else np.zeros((0, 4, 4))


# ------------------------------------------------------- which SfM model a run used
def sfm_fingerprint(seq: Sequence) -> str | None:
    """A short digest of the sequence's sparse SfM points (None without any).

    Refined poses are only meaningful against the SfM model they were refined from: another run of SfM
    (other settings, another data path, a deleted cache) puts the same video in another world frame and
    scale.  Each iteration records this digest beside its poses so that the next one can check it."""
    if seq.points_xyz is None or not len(seq.points_xyz):
        return None
    pts = np.ascontiguousarray(np.asarray(seq.points_xyz, dtype=np.float64))
    return hashlib.sha1(pts.tobytes()).hexdigest()[:16]


def same_fixed_frame(sfm_cam_from_world: np.ndarray, refined_cam_from_world: np.ndarray,
                     rtol: float = 1e-6) -> bool | None:
    """Whether refined poses keep the first registered frame of the SfM poses where it is, as dense PGO does
    (it fixes that frame bit-exact; poses.txt stores 10 significant digits).  For runs that predate
    :func:`sfm_fingerprint`.  None when the SfM poses have no registered frame or the counts differ."""
    sfm = np.asarray(sfm_cam_from_world, dtype=np.float64)
    ref = np.asarray(refined_cam_from_world, dtype=np.float64)
    reg = np.flatnonzero(np.isfinite(sfm).all(axis=(1, 2)))
    if len(sfm) != len(ref) or not len(reg):
        return None
    a, b = sfm[reg[0]], ref[reg[0]]
    if not np.isfinite(b).all():
        return False
    return bool(np.abs(a - b).max() <= rtol * (1.0 + np.abs(a).max()))
