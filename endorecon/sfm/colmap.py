"""Everything that touches pycolmap: SfM runs and COLMAP model import/export.

This is the only module of endorecon that imports pycolmap (supported: 4.x).

* :func:`run_mapping` — feature extraction restricted by the endoscope mask,
  sequential matching (video overlap), incremental mapping with the **known**
  PINHOLE intrinsics (focal length, principal point and extra parameters are
  never refined: self-calibration fails on endoscopy).
* :func:`read_colmap_model` / :func:`write_colmap_model` — a COLMAP model
  (``cameras/images/points3D``, text or binary) <-> :class:`Sequence`.

COLMAP puts pixel (0, 0) at the top-left *corner*; our intrinsics put it at
the centre of the top-left pixel.  The conversion happens here and nowhere
else (:func:`endorecon.geometry.to_corner_convention`).
"""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import numpy as np
import torch

from endorecon.data.sequence import Sequence
from endorecon.geometry import from_corner_convention, project, to_corner_convention, transform_points
from endorecon.utils.errors import EndoreconError, InputError

log = logging.getLogger(__name__)

SUPPORTED_PYCOLMAP = ("4.",)

try:
    import pycolmap
except ImportError as e:  # pragma: no cover - environment problem
    raise EndoreconError(
        "pycolmap is not installed; endorecon's SfM stage needs pycolmap 4.x (pip install 'pycolmap>=4,<5')"
    ) from e

if not pycolmap.__version__.startswith(SUPPORTED_PYCOLMAP):  # pragma: no cover - environment problem
    raise EndoreconError(
        f"pycolmap {pycolmap.__version__} is not supported; endorecon's SfM stage supports pycolmap "
        f"{', '.join(v + 'x' for v in SUPPORTED_PYCOLMAP)} (tested with 4.2.1): pip install 'pycolmap>=4,<5'"
    )


# ----------------------------------------------------------------- conversion
def _rigid_to_matrix(rigid) -> np.ndarray:
    T = np.eye(4)
    T[:3, :4] = np.asarray(rigid.matrix(), dtype=np.float64)
    return T


def _camera_K_center(camera) -> np.ndarray:
    """Pixel-centre 3x3 intrinsics of a PINHOLE / SIMPLE_PINHOLE COLMAP camera."""
    model = camera.model.name
    p = np.asarray(camera.params, dtype=np.float64)
    if model == "PINHOLE":
        fx, fy, cx, cy = p
    elif model == "SIMPLE_PINHOLE":
        fx, cx, cy = p
        fy = fx
    else:
        raise InputError(
            f"COLMAP camera model {model} has distortion; endorecon needs undistorted PINHOLE frames",
            fix="undistort the frames (colmap image_undistorter) and pass the undistorted model",
        )
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    return from_corner_convention(K)


def reconstruction_arrays(rec, names: list[str]) -> dict:
    """Poses, points, visibility, colours and reprojection errors of a reconstruction, indexed by ``names``.

    Images are matched to ``names`` (frame order) by file name; images of the model not in
    ``names`` are ignored, observations in them dropped.

    Returns:
        dict with ``cam_from_world`` (N, 4, 4) (NaN rows: not registered), ``points_xyz`` (P, 3),
        ``visibility`` list of P int arrays (sorted, unique frame indices), ``points_rgb`` (P, 3) uint8,
        ``errors`` (P,) mean reprojection error in the model's pixels, ``camera`` the (first) camera.
    """
    index = {n: i for i, n in enumerate(names)}
    n = len(names)
    cam_from_world = np.full((n, 4, 4), np.nan)
    image_to_frame = {}
    for image_id, image in rec.images.items():
        i = index.get(image.name)
        if i is None:
            i = index.get(Path(image.name).name)
        if i is None or not image.has_pose:
            continue
        image_to_frame[image_id] = i
        cam_from_world[i] = _rigid_to_matrix(image.cam_from_world())
    xyz, rgb, err, vis = [], [], [], []
    for _, p in sorted(rec.points3D.items()):
        frames = sorted({image_to_frame[el.image_id] for el in p.track.elements if el.image_id in image_to_frame})
        if not frames:
            continue
        xyz.append(np.asarray(p.xyz, dtype=np.float64))
        rgb.append(np.asarray(p.color, dtype=np.uint8))
        err.append(float(p.error) if p.has_error() else np.nan)
        vis.append(np.asarray(frames, dtype=np.int64))
    return dict(
        cam_from_world=cam_from_world,
        points_xyz=np.stack(xyz) if xyz else np.zeros((0, 3)),
        points_rgb=np.stack(rgb) if rgb else np.zeros((0, 3), np.uint8),
        errors=np.asarray(err, dtype=np.float64),
        visibility=vis,
        camera=next(iter(rec.cameras.values())) if rec.num_cameras() else None,
    )


def read_colmap_model(
    model_dir: str | Path,
    frames: list[str | Path],
    mask: np.ndarray | None = None,
    name: str | None = None,
    source: str = "colmap",
) -> Sequence:
    """Read a COLMAP model (text or binary) into a :class:`Sequence`.

    Args:
        model_dir: folder with ``cameras``, ``images``, ``points3D`` (``.bin`` or ``.txt``).
        frames: the frame image paths in temporal order; model images are matched by file name.
        mask: (H, W) bool valid-pixel mask at the camera's size (default: all valid).
    Returns:
        Sequence with pixel-centre intrinsics, cam_from_world (NaN for frames the model lacks),
        points and visibility, ``units="sfm"``.
    """
    model_dir = Path(model_dir)
    if not model_dir.is_dir() or not any(
        (model_dir / f"cameras.{ext}").is_file() for ext in ("bin", "txt")
    ):
        raise InputError("not a COLMAP model (no cameras.bin/cameras.txt)", model_dir,
                         "pass the folder that holds cameras, images and points3D")
    try:
        rec = pycolmap.Reconstruction(str(model_dir))
    except Exception as e:  # pycolmap raises plain RuntimeError/ValueError on corrupt files
        raise InputError(f"cannot read COLMAP model ({e})", model_dir, "re-export the model") from e
    if rec.num_cameras() != 1:
        raise InputError(f"COLMAP model has {rec.num_cameras()} cameras; endorecon needs one camera per sequence",
                         model_dir)
    frames = [Path(f) for f in frames]
    arrays = reconstruction_arrays(rec, [f.name for f in frames])
    camera = arrays["camera"]
    K = _camera_K_center(camera)
    h, w = int(camera.height), int(camera.width)
    if mask is None:
        mask = np.ones((h, w), dtype=bool)
    if not np.isfinite(arrays["cam_from_world"]).any():
        raise InputError("no image of the COLMAP model matches a frame file name", model_dir,
                         "pass the frames the model was computed from")
    return Sequence(
        name=name or model_dir.name,
        frame_paths=frames,
        intrinsics=K,
        height=h,
        width=w,
        mask=mask,
        cam_from_world=arrays["cam_from_world"],
        points_xyz=arrays["points_xyz"],
        visibility=arrays["visibility"],
        points_rgb=arrays["points_rgb"],
        units="sfm",
        source=source,
    )


def sequence_to_reconstruction(seq: Sequence):
    """A ``pycolmap.Reconstruction`` of a sequence: one PINHOLE camera (corner convention), one image per
    registered frame (named by its file name), points with tracks whose 2D observations are the points'
    projections into their visible frames."""
    rec = pycolmap.Reconstruction()
    Kc = to_corner_convention(seq.intrinsics)
    cam = pycolmap.Camera(
        camera_id=1, model="PINHOLE", width=int(seq.width), height=int(seq.height),
        params=[Kc[0, 0], Kc[1, 1], Kc[0, 2], Kc[1, 2]],
    )
    rec.add_camera_with_trivial_rig(cam)
    reg = seq.registered
    # observations per frame: point index and its projection (corner convention)
    obs: dict[int, list[int]] = {int(i): [] for i in np.nonzero(reg)[0]}
    for p, frames in enumerate(seq.visibility):
        for f in frames:
            if int(f) in obs:
                obs[int(f)].append(p)
    point_tracks: list[list[tuple[int, int]]] = [[] for _ in range(len(seq.points_xyz))]
    pts = torch.from_numpy(seq.points_xyz)
    K = torch.from_numpy(seq.intrinsics)[None]
    for i in sorted(obs):
        idx = obs[i]
        T = torch.from_numpy(seq.cam_from_world[i])[None]
        if idx:
            uv, _ = project(transform_points(T, pts[idx][None]), K)
            xy = uv[0].numpy() + 0.5
        else:
            xy = np.zeros((0, 2))
        image = pycolmap.Image(name=seq.frame_paths[i].name, keypoints=xy, camera_id=1, image_id=i + 1)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(seq.cam_from_world[i][:3, :4]))
        for k, p in enumerate(idx):
            point_tracks[p].append((i + 1, k))
    rgb = seq.points_rgb if seq.points_rgb is not None else np.zeros((len(seq.points_xyz), 3), np.uint8)
    for p, track_list in enumerate(point_tracks):
        track = pycolmap.Track()
        for image_id, k in track_list:
            track.add_element(image_id, k)
        rec.add_point3D(seq.points_xyz[p], track, rgb[p])
    return rec


def write_colmap_model(seq: Sequence, out_dir: str | Path, binary: bool = True) -> Path:
    """Write a sequence as a COLMAP model (``cameras/images/points3D`` ``.bin`` or ``.txt``) into ``out_dir``
    (replaced atomically).  Unregistered frames are left out; points keep their visibility as tracks."""
    from endorecon.utils.io import atomic_dir

    rec = sequence_to_reconstruction(seq)
    out_dir = Path(out_dir)
    with atomic_dir(out_dir) as tmp:
        if binary:
            rec.write_binary(str(tmp))
        else:
            rec.write_text(str(tmp))
    return out_dir


# ------------------------------------------------------------------ SfM runs
def _mapping_options(attempt: dict, num_threads: int, init_pair: tuple[int, int] | None):
    opts = pycolmap.IncrementalPipelineOptions()
    # Known intrinsics: never refine them (self-calibration fails on endoscopy).
    opts.ba_refine_focal_length = False
    opts.ba_refine_principal_point = False
    opts.ba_refine_extra_params = False
    opts.mapper.abs_pose_refine_focal_length = False
    opts.mapper.abs_pose_refine_extra_params = False
    opts.num_threads = num_threads
    opts.min_model_size = int(attempt.get("min_model_size", 3))
    opts.min_num_matches = int(attempt.get("min_num_matches", 15))
    if "init_min_tri_angle" in attempt:
        opts.mapper.init_min_tri_angle = float(attempt["init_min_tri_angle"])
    if "init_min_num_inliers" in attempt:
        opts.mapper.init_min_num_inliers = int(attempt["init_min_num_inliers"])
    if "abs_pose_min_num_inliers" in attempt:
        opts.mapper.abs_pose_min_num_inliers = int(attempt["abs_pose_min_num_inliers"])
    if "filter_min_tri_angle" in attempt:
        opts.mapper.filter_min_tri_angle = float(attempt["filter_min_tri_angle"])
    if "tri_min_angle" in attempt:
        opts.triangulation.min_angle = float(attempt["tri_min_angle"])
    if "filter_max_reproj_error" in attempt:
        opts.mapper.filter_max_reproj_error = float(attempt["filter_max_reproj_error"])
    if "seed" in attempt:
        opts.random_seed = int(attempt["seed"])
        opts.mapper.random_seed = int(attempt["seed"])
    if init_pair is not None:
        opts.init_image_id1, opts.init_image_id2 = init_pair
    return opts


def run_mapping(
    image_dir: str | Path,
    image_names: list[str],
    mask_path: str | Path | None,
    K: np.ndarray,
    attempt: dict,
    work_dir: str | Path,
    num_threads: int = -1,
    verbose: bool = False,
) -> tuple[list, dict]:
    """One SfM attempt with pycolmap on the images ``image_dir/<image_names>``.

    Args:
        K: (3, 3) pixel-centre intrinsics at the images' size (converted to COLMAP's corner convention here).
        mask_path: one mask for all images (black = ignored), or None.
        attempt: hyperparameters: ``peak_threshold``, ``max_num_features``, ``overlap``, ``quadratic_overlap``,
            ``init_pair`` (fraction of the sequence where the initial pair starts, or null = COLMAP's choice),
            ``init_gap`` (frames between the pair), ``seed`` (seeds COLMAP's random numbers: RANSAC in
            matching and in mapping; unseeded, a run may land in another solution now and then, and with
            ``num_threads=1`` a seeded one repeats bit for bit) and the mapper options of :func:`_mapping_options`.
        work_dir: holds ``database.db`` and ``sparse/``; cleared first.
        verbose: let COLMAP print its own log (else only errors).
    Returns:
        (models sorted by registered images, largest first; stats dict with ``num_features`` (mean per image),
        ``num_verified_pairs``).
    """
    work_dir = Path(work_dir)
    level = pycolmap.logging.minloglevel
    if not verbose:
        pycolmap.logging.minloglevel = 2  # COLMAP's INFO/WARNING stream is long; our log has the numbers
    try:
        return _run_mapping(image_dir, image_names, mask_path, K, attempt, work_dir, num_threads)
    finally:
        pycolmap.logging.minloglevel = level


def _run_mapping(image_dir, image_names, mask_path, K, attempt, work_dir: Path, num_threads: int):
    if work_dir.exists():
        shutil.rmtree(work_dir)
    work_dir.mkdir(parents=True)
    db_path = work_dir / "database.db"
    Kc = to_corner_convention(np.asarray(K, dtype=np.float64))
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    reader.camera_params = ",".join(f"{v:.10g}" for v in (Kc[0, 0], Kc[1, 1], Kc[0, 2], Kc[1, 2]))
    if mask_path is not None:
        reader.camera_mask_path = str(mask_path)
    if "seed" in attempt:
        pycolmap.set_random_seed(int(attempt["seed"]))
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = num_threads
    extraction.use_gpu = False
    extraction.sift.peak_threshold = float(attempt.get("peak_threshold", 0.003))
    extraction.sift.max_num_features = int(attempt.get("max_num_features", 8192))
    pycolmap.extract_features(
        str(db_path), str(image_dir), image_names=list(image_names), camera_mode=pycolmap.CameraMode.SINGLE,
        reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu,
    )
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = num_threads
    matching.use_gpu = False
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = int(attempt.get("overlap", 10))
    pairing.quadratic_overlap = bool(attempt.get("quadratic_overlap", True))
    verification = pycolmap.TwoViewGeometryOptions()
    if "seed" in attempt:
        verification.ransac.random_seed = int(attempt["seed"])
    pycolmap.match_sequential(str(db_path), matching_options=matching, pairing_options=pairing,
                              verification_options=verification, device=pycolmap.Device.cpu)

    db = pycolmap.Database.open(str(db_path))
    try:
        images = {im.name: im.image_id for im in db.read_all_images()}
        num_kp = [db.num_keypoints_for_image(images[n]) for n in image_names if n in images]
        stats = dict(
            num_features=float(np.mean(num_kp)) if num_kp else 0.0,
            num_verified_pairs=int(db.num_verified_image_pairs()),
        )
    finally:
        db.close()
    init_pair = None
    if attempt.get("init_pair") is not None and len(image_names) > 2:
        gap = int(attempt.get("init_gap", 3))
        first = int(round(float(attempt["init_pair"]) * (len(image_names) - 1 - gap)))
        first = min(max(first, 0), len(image_names) - 1 - gap)
        init_pair = (images[image_names[first]], images[image_names[first + gap]])
    opts = _mapping_options(attempt, num_threads, init_pair)
    sparse = work_dir / "sparse"
    sparse.mkdir()
    models = pycolmap.incremental_mapping(str(db_path), str(image_dir), str(sparse), options=opts)
    if not models and init_pair is not None:
        # A forced initial pair that cannot be triangulated gives nothing: let COLMAP choose.
        log.info("forced initial pair failed; retrying with COLMAP's choice")
        models = pycolmap.incremental_mapping(str(db_path), str(image_dir), str(sparse),
                                              options=_mapping_options(attempt, num_threads, None))
    ranked = sorted(models.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()), reverse=True)
    return ranked, stats


def write_reconstruction(rec, out_dir: str | Path) -> Path:
    """Write a pycolmap reconstruction (binary) atomically."""
    from endorecon.utils.io import atomic_dir

    with atomic_dir(out_dir) as tmp:
        rec.write_binary(str(tmp))
    return Path(out_dir)


def load_reconstruction(model_dir: str | Path):
    return pycolmap.Reconstruction(str(model_dir))
