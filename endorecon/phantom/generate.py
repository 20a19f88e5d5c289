"""Write a phantom dataset: videos the pipeline reads, ground truth kept apart.

Layout (the importers in :mod:`endorecon.data.dataset` read exactly this)::

    <out>/dataset.json                           format, version, seed, size, units, patients
    <out>/patient_00/seq_00/frames/000000.jpg    frames (what the pipeline reads)
    <out>/patient_00/seq_00/mask.png             valid pixels white
    <out>/patient_00/seq_00/camera.json          intrinsics (pixel-centre), units "mm"
    <out>/ground_truth/patient_00/mesh.ply       the "CT" surface (mm), for every patient
    <out>/ground_truth/patient_00/seq_00/depth_mm.npz   "depth_mm" (N, H, W) float32, 0 = invalid
    <out>/ground_truth/patient_00/seq_00/poses.txt      cam_from_world (mm)
    <out>/COMPLETE                               written last

The whole tree is built in a temporary folder beside ``out`` and renamed when
complete, so a crash never leaves a half dataset under ``out``.
"""

from __future__ import annotations

import io
import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from endorecon.phantom.anatomy import make_anatomy
from endorecon.phantom.appearance import Exposure, SolidTexture, sensor, shade
from endorecon.phantom.trajectory import (
    centreline_from_waypoints,
    endoscope_camera,
    estimate_centreline,
    plan_trajectory,
)
from endorecon.rendering import MeshRenderer
from endorecon.utils.errors import InputError
from endorecon.utils.io import atomic_dir

log = logging.getLogger(__name__)

FORMAT = "endorecon-phantom"
VERSION = 1
N_WITH_CT = 4  # patients 0-3 have CT for evaluation, as in the paper; the rest are train-only

__all__ = ["generate", "ensure_dataset", "render_video", "FORMAT", "VERSION"]


def _seed(*parts: int) -> np.random.Generator:
    return np.random.default_rng([int(p) for p in parts])


def render_video(
    renderer: MeshRenderer,
    texture: SolidTexture,
    K: np.ndarray,
    mask: np.ndarray,
    cam_from_world: np.ndarray,
    rng: np.random.Generator,
    blur_poses: np.ndarray | None = None,
    exposure: Exposure | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Shade one sequence.

    Args:
        renderer: the scene.
        texture: surface texture.
        K: (3, 3) pixel-centre intrinsics; mask: (H, W) bool.
        cam_from_world: (N, 4, 4) frame poses (ground truth).
        rng: noise generator.
        blur_poses: optional (N, S, 4, 4) sub-poses averaged into each frame (motion blur).
        exposure: auto-exposure state (default: a fresh one).
    Returns:
        frames (N, H, W, 3) uint8 (black outside the mask), depth_mm (N, H, W) float32 (0 = invalid).
    """
    h, w = mask.shape
    n = len(cam_from_world)
    exposure = exposure or Exposure()
    frames = np.zeros((n, h, w, 3), np.uint8)
    depth = np.zeros((n, h, w), np.float32)
    d_cam = renderer._rays_cam(K, h, w)
    d_len = np.linalg.norm(d_cam, axis=-1)
    f = 0.5 * (K[0, 0] + K[1, 1])
    for i in range(n):
        poses = [cam_from_world[i]] if blur_poses is None else list(blur_poses[i])
        radiance = np.zeros((h, w, 3), np.float32)
        for T in poses:
            out = renderer.render(K, T, h, w)
            sel = out["hit"] & mask
            if not sel.any():
                continue
            R = T[:3, :3]
            dirs = (d_cam[sel] / d_len[sel, None]) @ R  # R^T d: unit world directions
            ray_len = out["depth"][sel] * d_len[sel]
            nrm = out["normals_world"][sel].astype(np.float64)
            cos = np.abs(np.sum(nrm * dirs, 1))
            footprint = ray_len / f / np.maximum(cos, 0.25)
            radiance[sel] += shade(out["points_world"][sel].astype(np.float64), nrm, dirs, ray_len, texture, footprint)
        radiance /= len(poses)
        gt = renderer.render(K, cam_from_world[i], h, w) if blur_poses is not None else out
        valid = gt["hit"] & mask
        depth[i][valid] = gt["depth"][valid]
        gain = exposure(radiance[valid]) if valid.any() else 1.0
        img = sensor(radiance * gain, rng)
        img[~mask] = 0
        frames[i] = img
    return frames, depth


def _jpeg_bytes(img: np.ndarray, quality: int) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="JPEG", quality=int(quality), subsampling=0)
    return buf.getvalue()


def _write_mesh(path: Path, vertices: np.ndarray, triangles: np.ndarray) -> None:
    """Binary little-endian PLY (float32 xyz, int32 faces), written byte-for-byte deterministically."""
    v = np.ascontiguousarray(vertices, dtype="<f4")
    f = np.empty(len(triangles), dtype=[("n", "u1"), ("idx", "<i4", (3,))])
    f["n"] = 3
    f["idx"] = triangles
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment endorecon phantom CT surface, units mm\n"
        f"element vertex {len(v)}\nproperty float x\nproperty float y\nproperty float z\n"
        f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(header.encode("ascii") + v.tobytes() + f.tobytes())


def _check_args(patients, sequences, frames, height, width) -> None:
    for name, v, lo in [("patients", patients, 1), ("sequences", sequences, 1), ("frames", frames, 2), ("height", height, 16), ("width", width, 16)]:
        if not isinstance(v, (int, np.integer)) or v < lo:
            raise InputError(f"{name}={v!r} must be an integer >= {lo}", fix=f"pass {name}=<int >= {lo}>")


def generate(
    out: str | Path,
    patients: int = 6,
    sequences: int = 1,
    frames: int = 60,
    height: int = 256,
    width: int = 320,
    seed: int = 0,
    mesh: str | Path | None = None,
    waypoints: Any = None,
    fov_deg: float = 100.0,
    step_mm: float = 0.5,
    motion_blur: int = 0,
    jpeg_quality: int = 92,
    progress: bool = False,
) -> Path:
    """Generate a phantom dataset into ``out`` (replacing it atomically) and return ``out``.

    Args:
        out: dataset folder.
        patients: number of patients; patients 0-3 have CT (``has_ct``), the rest are train-only.
        sequences: videos per patient.
        frames: frames per video.
        height, width: frame size.
        seed: everything is deterministic given the seed (same seed, same bytes).
        mesh: optional mesh file (mm) to render instead of the procedural anatomies; every patient
            then shares this anatomy, with its own texture and trajectories.
        waypoints: optional (K, 3) camera path through ``mesh`` in mm (default: a planned centreline).
        fov_deg: field of view across the circular mask's diameter.
        step_mm: mean forward motion per frame.
        motion_blur: sub-poses averaged per frame (0 = no blur; 3 gives a mild blur).
        jpeg_quality: JPEG quality of the frames.
        progress: show a rich progress bar.
    """
    _check_args(patients, sequences, frames, height, width)
    out = Path(out)
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and (_read_meta(out) or {}).get("format") != FORMAT)):
        # generation replaces `out` as a whole: never do that to a folder that is not a phantom
        raise InputError("output exists and is not a phantom dataset", out, "choose a new or empty folder for out=")
    K, mask = endoscope_camera(height, width, fov_deg)
    given = None
    if mesh is not None:
        given = MeshRenderer(mesh)
        if waypoints is not None:
            centre = centreline_from_waypoints(np.asarray(waypoints, dtype=np.float64))
            clearance = given.distance(centre)
            if not given.occupancy(centre).all() or clearance.min() < 0.5:
                raise InputError("waypoints leave the cavity (or touch its wall)", mesh, "give waypoints inside the mesh")
        else:
            centre, clearance = estimate_centreline(given)

    total = patients * sequences * frames
    bar = None
    if progress:
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

        bar = Progress(TextColumn("phantom"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
        task = bar.add_task("frames", total=total)
        bar.start()
    try:
        with atomic_dir(out) as tmp:
            meta_patients = []
            for p in range(patients):
                if given is None:
                    anat = make_anatomy(int(_seed(seed, p, 0).integers(2**31)))
                    renderer = MeshRenderer((anat.vertices, anat.triangles))
                    centre_p, clear_p = anat.centreline, anat.clearance
                else:
                    renderer, centre_p, clear_p = given, centre, clearance
                texture = SolidTexture(int(_seed(seed, p, 1).integers(2**31)))
                _write_mesh(tmp / "ground_truth" / f"patient_{p:02d}" / "mesh.ply", renderer.vertices, renderer.triangles)
                seq_names = []
                for q in range(sequences):
                    name = f"seq_{q:02d}"
                    seq_names.append(name)
                    rng_traj = _seed(seed, p, 2, q)
                    T = plan_trajectory(centre_p, clear_p, frames, rng_traj, step_mm=step_mm)
                    _check_inside(renderer, T, given is None, mesh)
                    blur = None
                    if motion_blur and motion_blur > 1:
                        offs = np.linspace(-0.2, 0.2, int(motion_blur))
                        times = (np.arange(frames)[:, None] + offs[None]).ravel()
                        blur = plan_trajectory(centre_p, clear_p, frames, _seed(seed, p, 2, q), step_mm=step_mm, times=times)
                        blur = blur.reshape(frames, int(motion_blur), 4, 4)
                    imgs, depth = _render_with_progress(renderer, texture, K, mask, T, _seed(seed, p, 3, q), blur, bar, task if bar else None)
                    _write_sequence(tmp, p, name, imgs, depth, T, K, mask, jpeg_quality)
                meta_patients.append({"id": p, "has_ct": p < N_WITH_CT, "sequences": seq_names})
            meta = {
                "format": FORMAT,
                "version": VERSION,
                "seed": int(seed),
                "height": int(height),
                "width": int(width),
                "units": "mm",
                "frames": int(frames),
                "fov_deg": float(fov_deg),
                "mesh": None if mesh is None else str(Path(mesh).resolve()),
                "patients": meta_patients,
            }
            (tmp / "dataset.json").write_text(json.dumps(meta, indent=2) + "\n")
            (tmp / "COMPLETE").write_text("ok\n")
    finally:
        if bar is not None:
            bar.stop()
    return out


def _render_with_progress(renderer, texture, K, mask, T, rng, blur, bar, task):
    exposure = Exposure()
    frames, depths = [], []
    for i in range(len(T)):  # frame by frame so the bar moves; exposure state carries over
        f, d = render_video(renderer, texture, K, mask, T[i : i + 1], rng, None if blur is None else blur[i : i + 1], exposure)
        frames.append(f[0])
        depths.append(d[0])
        if bar is not None:
            bar.advance(task)
    return np.stack(frames), np.stack(depths)


def _check_inside(renderer: MeshRenderer, T: np.ndarray, procedural: bool, mesh) -> None:
    """The camera centres must lie inside the cavity, away from the wall."""
    centres = -np.einsum("nji,nj->ni", T[:, :3, :3], T[:, :3, 3])
    inside = renderer.occupancy(centres)
    dist = renderer.distance(centres)
    if not inside.all() or dist.min() < 0.5:
        bad = int(np.argmin(np.where(inside, dist, -1)))
        what = f"camera of frame {bad} is outside the cavity or within 0.5 mm of its wall (distance {dist[bad]:.2f} mm)"
        if procedural:
            raise RuntimeError(what)  # a bug in the anatomy/trajectory, not the user's input
        raise InputError(what, mesh, "give waypoints well inside the mesh, or a closed (watertight) mesh in mm")


def _write_sequence(root: Path, p: int, name: str, imgs, depth, T, K, mask, quality: int) -> None:
    from PIL import Image

    from endorecon.data.sequence import write_camera_json, write_poses_txt

    seq_dir = root / f"patient_{p:02d}" / name
    (seq_dir / "frames").mkdir(parents=True, exist_ok=True)
    names = []
    for i, img in enumerate(imgs):
        fn = f"{i:06d}.jpg"
        names.append(fn)
        (seq_dir / "frames" / fn).write_bytes(_jpeg_bytes(img, quality))
    Image.fromarray((mask * 255).astype(np.uint8)).save(seq_dir / "mask.png")
    write_camera_json(seq_dir / "camera.json", K, mask.shape[0], mask.shape[1], units="mm")
    gt_dir = root / "ground_truth" / f"patient_{p:02d}" / name
    gt_dir.mkdir(parents=True, exist_ok=True)
    _write_npz_deterministic(gt_dir / "depth_mm.npz", depth_mm=depth.astype(np.float32))
    write_poses_txt(gt_dir / "poses.txt", names, T)


def _write_npz_deterministic(path: Path, **arrays: np.ndarray) -> None:
    """A compressed ``.npz`` with fixed zip timestamps (np.savez stamps the current time): same data, same bytes."""
    import zipfile

    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for key, arr in arrays.items():
            info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.ascontiguousarray(arr), allow_pickle=False)
            zf.writestr(info, buf.getvalue())


def _read_meta(root: Path) -> dict | None:
    try:
        return json.loads((root / "dataset.json").read_text())
    except (OSError, ValueError):
        return None


def ensure_dataset(cfg: Any, root: str | Path | None = None) -> Path:
    """Generate the phantom into ``root`` unless a complete one with the same settings is there.

    Args:
        cfg: mapping (dict or OmegaConf) with the keys of ``conf/data/phantom.yaml``:
            ``root``, ``patients``, ``sequences``, ``frames``, ``height``, ``width``, ``seed``,
            optional ``mesh``, ``fov_deg``, ``step_mm``, ``motion_blur``.
        root: dataset folder (default ``cfg.root``).
    Returns:
        the dataset folder.
    """
    get = (lambda k, d=None: cfg.get(k, d)) if hasattr(cfg, "get") else (lambda k, d=None: getattr(cfg, k, d))
    root = root if root is not None else get("root")
    if root is None or str(root) in ("", "None"):
        raise InputError("no phantom root given", fix="set data.root (e.g. ${paths.data_dir}/phantom)")
    root = Path(root)
    kw = dict(
        patients=int(get("patients", 6)),
        sequences=int(get("sequences", 1)),
        frames=int(get("frames", 60)),
        height=int(get("height", 256)),
        width=int(get("width", 320)),
        seed=int(get("seed", 0)),
        mesh=get("mesh", None),
        fov_deg=float(get("fov_deg", 100.0)),
        step_mm=float(get("step_mm", 0.5)),
        motion_blur=int(get("motion_blur", 0) or 0),
    )
    if (root / "COMPLETE").is_file():
        meta = _read_meta(root)
        if meta is None or meta.get("format") != FORMAT:
            raise InputError(
                "folder holds something other than an endorecon phantom", root, "point data.root at an empty or phantom folder"
            )
        same = (
            meta.get("seed") == kw["seed"]
            and meta.get("height") == kw["height"]
            and meta.get("width") == kw["width"]
            and meta.get("frames") == kw["frames"]
            and len(meta.get("patients", [])) == kw["patients"]
            and all(len(p["sequences"]) == kw["sequences"] for p in meta["patients"])
            and meta.get("mesh") == (None if kw["mesh"] is None else str(Path(kw["mesh"]).resolve()))
        )
        if same:
            return root
        log.warning("phantom at %s was made with other settings: regenerating it", root)
    elif root.exists() and any(root.iterdir()) and _read_meta(root) is None:
        raise InputError("folder exists, is not empty and is not a phantom dataset", root, "choose another data.root")
    log.info("generating the phantom into %s", root)
    return generate(root, **kw, progress=True)
