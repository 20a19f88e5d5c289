"""Importer of the original method's example format (EndoscopyDepthEstimation-Pytorch).

A folder such as ``../shared/data/sinus_example`` holds::

    00004584.jpg ...             frames; the file name is the frame index
    undistorted_mask.bmp         valid pixels white
    camera_intrinsics_per_view   fx fy cx cy (whitespace/newline separated, one set per view or one in all),
                                 COLMAP's corner convention -> converted to pixel centres here
    motion.yaml                  ROS-style poses, one per registered frame in the order of
                                 visible_view_indexes, **camera-to-world** -> inverted here
    structure.ply                sparse points (first three vertex properties x, y, z)
    view_indexes_per_point       -1 starts a point, then the frame indexes that see it
    visible_view_indexes         registered frame indexes
    selected_indexes             frames of the sequence (optional; default: all images)

All poses are converted to ``cam_from_world`` here, so the pipeline only ever sees
that convention.  Units are SfM's (arbitrary scale).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import torch

from endorecon.data.sequence import IMAGE_SUFFIXES, Sequence, read_mask
from endorecon.geometry import from_corner_convention, invert_pose, pose_from_rt, quaternion_to_matrix
from endorecon.utils.errors import InputError


def _read_ints(path: Path) -> list[int]:
    if not path.is_file():
        raise InputError("file is missing", path, "the original format needs it (see endorecon/data/original.py)")
    try:
        return [int(float(v)) for v in path.read_text().split()]
    except ValueError as e:
        raise InputError(f"expected integers ({e})", path) from e


def read_intrinsics(path: Path) -> np.ndarray:
    """``camera_intrinsics_per_view`` -> (3, 3) pixel-centre K (the views must share one camera)."""
    if not path.is_file():
        raise InputError("camera intrinsics file is missing", path, "write fx fy cx cy (COLMAP convention)")
    try:
        vals = np.array([float(v) for v in path.read_text().split()], dtype=np.float64)
    except ValueError as e:
        raise InputError(f"bad number in intrinsics ({e})", path) from e
    if len(vals) == 0 or len(vals) % 4:
        raise InputError(f"expected groups of 4 numbers (fx fy cx cy), got {len(vals)}", path)
    if not np.isfinite(vals).all():
        raise InputError("intrinsics are not finite (inf or nan)", path, "write fx fy cx cy (COLMAP convention)")
    per_view = vals.reshape(-1, 4)
    if not np.allclose(per_view, per_view[0]):
        raise InputError("views have different intrinsics; endorecon needs one camera per sequence", path)
    fx, fy, cx, cy = per_view[0]
    if not (fx > 0 and fy > 0):
        raise InputError("focal lengths must be positive", path)
    return from_corner_convention(np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]))


def read_motion_yaml(path: Path) -> np.ndarray:
    """``motion.yaml`` (ROS-style list of position x,y,z + orientation x,y,z,w) -> (M, 4, 4) world_from_cam."""
    if not path.is_file():
        raise InputError("pose file is missing", path, "motion.yaml holds one camera-to-world pose per frame")
    text = path.read_text()
    # The file is not plain YAML (keys like "poses[0]:"); read the numbers by block.
    blocks = re.split(r"^\s*poses\[\d+\]:\s*$", text, flags=re.M)[1:]
    poses = []
    for b, block in enumerate(blocks):
        pos = re.search(r"position:\s*x:\s*(\S+)\s*y:\s*(\S+)\s*z:\s*(\S+)", block)
        ori = re.search(r"orientation:\s*x:\s*(\S+)\s*y:\s*(\S+)\s*z:\s*(\S+)\s*w:\s*(\S+)", block)
        if pos is None or ori is None:
            raise InputError(f"pose {b} has no position/orientation x y z (w)", path)
        try:
            p = np.array([float(v) for v in pos.groups()])
            qx, qy, qz, qw = (float(v) for v in ori.groups())
        except ValueError as e:
            raise InputError(f"pose {b}: {e}", path) from e
        R = quaternion_to_matrix(torch.tensor([[qw, qx, qy, qz]], dtype=torch.float64))
        poses.append(pose_from_rt(R, torch.from_numpy(p)[None])[0].numpy())
    if not poses:
        raise InputError("no poses found", path, "expected ROS-style 'poses[i]: position/orientation' blocks")
    return np.stack(poses)


def read_ply_xyz(path: Path) -> np.ndarray:
    """First three properties (x, y, z) of the vertices of an ASCII PLY -> (P, 3)."""
    if not path.is_file():
        raise InputError("point cloud file is missing", path, "structure.ply holds the sparse SfM points")
    lines = path.read_text(errors="replace").splitlines()
    try:
        end = next(i for i, ln in enumerate(lines) if ln.strip() == "end_header")
    except StopIteration:
        raise InputError("not a PLY file (no end_header)", path) from None
    header = lines[:end]
    if not any("ascii" in ln for ln in header if ln.startswith("format")):
        raise InputError("only ASCII PLY point clouds are supported", path, "re-export structure.ply as ASCII")
    m = [re.match(r"element\s+vertex\s+(\d+)", ln) for ln in header]
    counts = [int(x.group(1)) for x in m if x]
    if not counts:
        raise InputError("PLY has no vertex element", path)
    n = counts[0]
    if n == 0:
        raise InputError("point cloud is empty", path, "run SfM again; the sequence needs sparse points")
    try:
        xyz = np.array([[float(v) for v in ln.split()[:3]] for ln in lines[end + 1 : end + 1 + n]])
    except ValueError as e:
        raise InputError(f"bad vertex line ({e})", path) from e
    if xyz.shape != (n, 3):
        raise InputError(f"PLY announces {n} vertices but holds {len(xyz)}", path)
    return xyz


def read_view_indexes_per_point(path: Path) -> list[list[int]]:
    vals = _read_ints(path)
    points: list[list[int]] = []
    for v in vals:
        if v == -1:
            points.append([])
        elif not points:
            raise InputError("the file must start with -1 (start of the first point)", path)
        else:
            points[-1].append(v)
    return points


def load_original(folder: str | Path, name: str | None = None, patient: int | None = None,
                  sfm: bool = True) -> Sequence:
    """Import a sequence in the original method's format (see the module docstring).

    With ``sfm=False`` only the frames, intrinsics and mask are read (a new video in that format, which
    ``reconstruct.py`` runs SfM on itself): no poses or points are needed then.

    Returns:
        Sequence(source="original", units="sfm") with pixel-centre intrinsics, cam_from_world per registered
        frame (NaN for the others), the sparse points and their visibility as frame positions 0..N-1.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError("folder does not exist", folder, "pass the folder of a sequence in the original format")
    images = {}
    for p in folder.iterdir():
        if p.suffix.lower() in IMAGE_SUFFIXES and p.stem.isdigit():
            images[int(p.stem)] = p
    sel_path = folder / "selected_indexes"
    indexes = _read_ints(sel_path) if sel_path.is_file() else sorted(images)
    if not indexes:
        raise InputError("no frames (images named by their frame index, e.g. 00004584.jpg)", folder)
    for idx in indexes:
        if idx not in images:
            raise InputError(f"frame {idx} is listed but has no image", folder / f"{idx:08d}.jpg",
                             "restore the frame file or remove it from selected_indexes")
    frames = [images[i] for i in indexes]
    position = {idx: k for k, idx in enumerate(indexes)}

    from PIL import Image

    sizes = []
    for f in frames:  # headers only: cheap, and names the bad file before any stage runs
        try:
            with Image.open(f) as im:
                sizes.append(im.size)
        except OSError as e:
            raise InputError(f"cannot read image ({e})", f, "re-export the frame or delete it") from e
    width, height = sizes[0]
    for f, sz in zip(frames, sizes):
        if sz != (width, height):
            raise InputError(f"frame is {sz[0]}x{sz[1]} but {frames[0].name} is {width}x{height}", f,
                             "all frames of a sequence must have the same size")
    K = read_intrinsics(folder / "camera_intrinsics_per_view")
    mask = read_mask(folder / "undistorted_mask.bmp", expect_hw=(height, width))
    if not sfm:
        return Sequence(name=name or folder.name, frame_paths=frames, intrinsics=K, height=height, width=width,
                        mask=mask, units="sfm", source="original", patient=patient)

    visible = _read_ints(folder / "visible_view_indexes")
    world_from_cam = read_motion_yaml(folder / "motion.yaml")
    if len(world_from_cam) != len(visible):
        raise InputError(f"{len(world_from_cam)} poses but {len(visible)} visible_view_indexes",
                         folder / "motion.yaml", "motion.yaml needs one pose per visible view, in that order")
    cam_from_world = np.full((len(frames), 4, 4), np.nan)
    cam_from_world_reg = invert_pose(torch.from_numpy(world_from_cam)).numpy()
    for idx, T in zip(visible, cam_from_world_reg):
        if idx not in position:
            raise InputError(f"pose for frame {idx}, which has no image", folder / "visible_view_indexes",
                             f"restore {idx:08d}.jpg or remove the frame from visible_view_indexes/motion.yaml")
        cam_from_world[position[idx]] = T

    xyz = read_ply_xyz(folder / "structure.ply")
    views = read_view_indexes_per_point(folder / "view_indexes_per_point")
    if len(views) != len(xyz):
        raise InputError(f"{len(views)} points in view_indexes_per_point but {len(xyz)} in structure.ply",
                         folder / "view_indexes_per_point")
    visibility = []
    for k, v in enumerate(views):
        missing = [i for i in v if i not in position]
        if missing:
            raise InputError(f"point {k} is seen in frame {missing[0]}, which has no image",
                             folder / "view_indexes_per_point", "restore the frame or re-export the SfM result")
        visibility.append(np.unique([position[i] for i in v]).astype(np.int64))
    return Sequence(
        name=name or folder.name,
        frame_paths=frames,
        intrinsics=K,
        height=height,
        width=width,
        mask=mask,
        cam_from_world=cam_from_world,
        points_xyz=xyz,
        visibility=visibility,
        units="sfm",
        source="original",
        patient=patient,
    )
