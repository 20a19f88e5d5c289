"""Pipeline steps shared by the train and reconstruct tasks.

Each step is resumable: it writes its outputs atomically and skips work whose
complete outputs exist.

* :func:`load_sequences` — the sequences of a dataset (the generated phantom by default).
* :func:`run_sfm` — the SfM stage for each sequence, cached under ``paths.cache_dir``.
* :func:`infer_depth` — network depth and std for every frame of a sequence.
* :func:`refine_sequence` — fusion → simulated depth → failure detection → PGO →
  fusion again with refined poses and without flagged frames → simulated depth
  for the next iteration.  It writes one sequence's artifacts.
"""

from __future__ import annotations

import hashlib
import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from endorecon.data.sequence import Sequence, read_poses_txt, sfm_fingerprint, write_poses_txt
from endorecon.utils.errors import InputError
from endorecon.utils.io import atomic_save_npz, atomic_write_text, read_json

log = logging.getLogger(__name__)


# ------------------------------------------------------------------ datasets
@dataclass
class DatasetInfo:
    root: Path
    sequences: list[Sequence]
    patients_with_ct: list[int]


def load_sequences(cfg: DictConfig) -> DatasetInfo:
    """The dataset named by ``cfg.data`` (``data=phantom`` generates it on first use)."""
    name = cfg.data.get("name")
    if name is None:  # data=default: the training keys alone, which data=phantom builds on
        raise InputError("data=default holds only the training keys (resolution, batches, augmentation), no dataset",
                         fix="use data=phantom (the default) and override its keys, e.g. data.height=256")
    if name == "phantom":
        from endorecon.data.dataset import load_dataset, patients_with_ct
        from endorecon.phantom import ensure_dataset

        root = ensure_dataset(cfg.data.phantom, Path(cfg.data.root))
        return DatasetInfo(root, load_dataset(root), patients_with_ct(root))
    raise InputError(f"unknown data.name {name!r}", fix="use data=phantom")


def check_fold(fold: int, patients_with_ct: list[int]) -> None:
    if fold not in patients_with_ct:
        raise InputError(
            f"unknown fold {fold}: a fold holds out one patient with CT, one of {patients_with_ct}",
            fix=f"pass fold=<k> with k in {patients_with_ct}",
        )


def _slug(name: str) -> str:
    return name.replace("/", "__")


def config_hash(*parts) -> str:
    h = hashlib.sha1()
    for p in parts:
        if isinstance(p, DictConfig):
            p = OmegaConf.to_container(p, resolve=True)
        h.update(json.dumps(p, sort_keys=True, default=str).encode())
    return h.hexdigest()[:10]


SFM_NO_EFFECT = ("colmap_verbose", "num_threads")  # sfm settings that change nothing SfM keeps


def sfm_cache_dir(cfg: DictConfig, data_root: Path | None) -> Path:
    """``paths.cache_dir/sfm/<hash of the sfm settings, the dataset stamp and the resolved data path>``.

    The resolved path: the same data reached through a symlink or from another working directory must find
    the same SfM, not make another one (another world frame and scale, which poses refined in earlier
    iterations would not fit; :func:`endorecon.tasks.train.check_same_sfm` refuses them).  A cache made
    before the path was resolved (its key: the path as given) is reused where it exists."""
    stamp = ""
    if data_root is not None and (Path(data_root) / "dataset.json").is_file():
        stamp = (Path(data_root) / "dataset.json").read_text()
    root = Path(cfg.paths.cache_dir) / "sfm"
    resolved = str(Path(data_root).resolve()) if data_root is not None else "None"
    sfm = OmegaConf.to_container(cfg.sfm, resolve=True) if isinstance(cfg.sfm, DictConfig) else dict(cfg.sfm)
    # COLMAP's log and thread count change nothing the cache keeps (train.py's settings check ignores them too);
    # an unset seed keys the cache as before the key existed
    if sfm.get("seed", 0) is None:
        sfm = {k: v for k, v in sfm.items() if k != "seed"}
    key = config_hash({k: v for k, v in sfm.items() if k not in SFM_NO_EFFECT}, stamp, resolved)
    if (root / key).is_dir():
        return root / key
    # caches made before: keyed by every sfm setting (those two at the values given, or at their defaults), and
    # before that by the data path as given
    olds = [sfm, {**sfm, "num_threads": -1, "colmap_verbose": False}]
    for old in olds:
        for path in (resolved, str(data_root)):
            legacy = config_hash(old, stamp, path)
            if (root / legacy).is_dir():
                log.info("SfM cache %s (made under an earlier key) reused", root / legacy)
                return root / legacy
    return root / key


def run_sfm(cfg: DictConfig, sequences: list[Sequence], data_root: Path | None = None) -> list[Sequence]:
    """SfM for every sequence, cached in ``paths.cache_dir/sfm/<hash>/<sequence>`` (resumable)."""
    from endorecon.sfm.stage import load_result
    from endorecon.sfm.stage import run as sfm_run

    root = sfm_cache_dir(cfg, data_root)
    out = []
    for seq in sequences:
        out_dir = root / _slug(seq.name)
        sfm_run(cfg.sfm, seq, out_dir)
        res = load_result(out_dir)
        if [p.name for p in res.frame_paths] != [p.name for p in seq.frame_paths]:
            raise InputError(f"the SfM cache of {seq.name} lists other frames than the dataset", out_dir,
                             f"delete {out_dir} so that SfM is run again")
        # the cache is shared by every working directory that reads this data (its key is the resolved data
        # path); the frame paths it recorded may be relative to another one
        res = res.replace(frame_paths=list(seq.frame_paths))
        res.patient = seq.patient
        res.name = seq.name
        out.append(res)
    return out


# ----------------------------------------------------------------- inference
@torch.no_grad()
def infer_depth(module, seq: Sequence, cache, batch_size: int = 8, frames: list[int] | None = None):
    """Network depth and std of every frame (scaled to SfM units by the Depth Scaling Layer).

    Args:
        module: a :class:`endorecon.module.DepthModule`.
        seq: the sequence at the network's resolution.
        cache: its :class:`endorecon.data.sparse.SparseCache` (for the per-frame scale).
    Returns:
        depth (N,1,H,W), std (N,1,H,W) float32 tensors, colours (N,H,W,3) float32 in [0, 1].
    """
    from rich.progress import Progress

    module.eval()
    device = next(module.parameters()).device
    n = len(seq)
    frames = list(range(n)) if frames is None else frames
    H, W = seq.height, seq.width
    depth = torch.zeros(n, 1, H, W)
    std = torch.zeros(n, 1, H, W)
    colors = np.zeros((n, H, W, 3), np.float32)
    mask = torch.from_numpy(seq.mask)[None, None]
    with Progress(transient=True) as bar:
        task = bar.add_task(f"depth {seq.name}", total=len(frames))
        for s in range(0, len(frames), batch_size):
            idx = frames[s : s + batch_size]
            imgs = np.stack([seq.load_frame(i) for i in idx]).astype(np.float32) / 255.0
            colors[idx] = imgs
            img_t = torch.from_numpy(imgs).permute(0, 3, 1, 2).to(device)
            sd, sv = zip(*(cache.depth_map(i) for i in idx))
            sd = torch.from_numpy(np.stack(sd)).to(device)
            sv = torch.from_numpy(np.stack(sv)).to(device)
            d, s_ = module.predict(img_t, mask.expand(len(idx), -1, -1, -1).to(device), sd, sv)
            depth[idx] = d.float().cpu()
            std[idx] = s_.float().cpu()
            bar.advance(task, len(idx))
    return depth, std, colors


# ------------------------------------------------------------------- fusion
def fuse_sequence(cfg_fusion, seq: Sequence, depth, std, colors, cam_from_world, use: np.ndarray,
                  saved: bool = True):
    """Fuse the frames ``use`` (N,) bool into a volume; returns the volume (call ``extract_mesh``/``save_mesh``).

    ``saved=False``: only ``extract_mesh`` will be called, so the free-space check of the saved mesh is off
    and the volume keeps no copy of the frames' depth for it."""
    from endorecon.fusion.run import build_fusion

    if not saved:
        cfg_fusion = {**cfg_fusion, "free_space_max_fraction": None}

    idx = np.flatnonzero(use & np.isfinite(cam_from_world).all(axis=(1, 2)))
    if len(idx) == 0:
        raise InputError(f"{seq.name}: no registered, unflagged frame left to fuse",
                         fix="check SfM (registered frames) and failure.thresholds")
    d = depth[idx, 0]
    m = torch.from_numpy(seq.mask)[None].expand(len(idx), -1, -1) & (d > 0) & torch.isfinite(d)
    if not bool(m.any()):
        raise InputError(f"{seq.name}: no finite, positive depth inside the mask in the {len(idx)} frame(s) to fuse",
                         fix="check the network's depth (NaN / zeros) and the mask")
    med = float(d[m].median())
    volume = build_fusion(cfg_fusion, med)
    for i in idx:
        volume.integrate(depth[i, 0].numpy(), std[i, 0].numpy(), colors[i], seq.intrinsics, cam_from_world[i], seq.mask)
    return volume


def render_simulated(mesh, seq: Sequence, cam_from_world: np.ndarray):
    """Simulated depth: the fused mesh rendered at every frame's pose. -> depth (N,H,W) f32, valid (N,H,W) bool."""
    import open3d as o3d

    from endorecon.rendering.raycast import render_depth

    if isinstance(mesh, o3d.t.geometry.TriangleMesh) and ("indices" not in mesh.triangle or
                                                          len(mesh.triangle.indices) == 0):
        raise InputError(f"{seq.name}: fusion gave an empty mesh ({len(seq)} frames): no surface was seen by "
                         f"fusion.mesh_weight_threshold frames, or no depth was usable",
                         fix="use a longer clip, or lower fusion.mesh_weight_threshold (default 4)")
    return render_depth(mesh, seq.intrinsics, cam_from_world, seq.height, seq.width, mask=seq.mask)


def save_simulated(path: Path, depth: np.ndarray, valid: np.ndarray) -> Path:
    return atomic_save_npz(path, depth=depth.astype(np.float32), valid=valid)


def load_simulated(path: Path) -> tuple[np.ndarray, np.ndarray]:
    try:
        z = np.load(path)
        return z["depth"], z["valid"]
    except (OSError, KeyError, ValueError) as e:
        raise InputError(f"corrupt simulated depth ({e})", path, "delete the iteration dir and rerun it") from e


def _stage_cfg(cfg_group: DictConfig) -> dict:
    """A stage's config as a plain dict without the pipeline's own keys (``enabled``, ``resolution_scale``)."""
    d = OmegaConf.to_container(cfg_group, resolve=True)
    d.pop("enabled", None)
    d.pop("resolution_scale", None)
    return d


def _flow_fn(cache):
    """``(i, j) -> (flow (2,H,W), valid (1,H,W))`` torch tensors from a SparseCache (failure detection, PGO)."""

    def sparse_flow_fn(i, j):
        f, v = cache.flow_map(i, j)
        return torch.from_numpy(f), torch.from_numpy(v)

    return sparse_flow_fn


def refine_poses(cfg_pgo: DictConfig, seq: Sequence, cache, depth, std):
    """Dense PGO, at ``cfg_pgo.resolution_scale`` of the network's resolution.

    The dense consistency term costs per pixel: at half resolution it is 4x cheaper.  The
    sparse flow is re-projected exactly at the lower resolution (not resampled), and depth and
    std are area-averaged.
    """
    import torch.nn.functional as F

    from endorecon.data.sparse import build_sparse_cache
    from endorecon.data.transforms import resize_sequence
    from endorecon.pgo import optimize_poses

    scale = float(cfg_pgo.get("resolution_scale", 1.0))
    if scale != 1.0:
        h, w = max(8, round(seq.height * scale)), max(8, round(seq.width * scale))
        seq = resize_sequence(seq, h, w)
        cache = build_sparse_cache(seq)
        depth = F.interpolate(depth, size=(h, w), mode="area")
        std = F.interpolate(std, size=(h, w), mode="area")

    sparse_flow_fn = _flow_fn(cache)
    K = torch.from_numpy(seq.intrinsics).float()
    mask = torch.from_numpy(seq.mask)[None]
    return optimize_poses(depth, std, K, torch.from_numpy(seq.cam_from_world), mask, sparse_flow_fn,
                          _stage_cfg(cfg_pgo))


# Config groups that the end-of-iteration stage (refine_sequence) reads, less the keys that do not change
# its output (how it runs, not what it computes)
REFINE_SETTINGS = ("fusion", "failure", "pgo")
_NO_EFFECT = {"fusion": ("compile", "device"), "pgo": ("progress", "std_cache_mb", "flow_at_points")}
# failure keys added since runs began to record their settings: what refine_sequence does without them
FAILURE_ADDED_DEFAULTS = {"keep_excluded": False, "check_last_frame": False, "low_thresholds": None}


def refine_settings(cfg) -> dict | None:
    """The resolved ``fusion``/``failure``/``pgo`` settings of ``cfg`` that :func:`refine_sequence` makes its mesh
    with (what a cached result must match); None if unreadable."""
    from endorecon.fusion.run import FUSION_DEFAULTS

    try:
        out = {}
        for g in REFINE_SETTINGS:
            d = OmegaConf.to_container(cfg[g], resolve=True) if g in cfg else None
            if g == "fusion" and isinstance(d, dict):  # a key a config lacks: what build_fusion used for it
                d = {**FUSION_DEFAULTS, **d}
            if g == "failure" and isinstance(d, dict):
                d = {**FAILURE_ADDED_DEFAULTS, **d}
            if isinstance(d, dict):
                d = {k: v for k, v in d.items() if k not in _NO_EFFECT.get(g, ())}
            out[g] = d
        return out
    except Exception:  # an unreadable / unresolvable record counts as unknown
        return None


def weights_digest(module: torch.nn.Module) -> str:
    """Short digest of a module's weights and buffers (names, dtypes, shapes, values): which network made a result."""
    h = hashlib.sha1()
    for name, t in module.state_dict().items():
        h.update(f"{name}:{t.dtype}:{tuple(t.shape)};".encode())
        flat = t.detach().cpu().contiguous().reshape(-1)  # 1-d: a 0-d tensor cannot be viewed as bytes
        h.update(flat.view(torch.uint8).numpy().tobytes() if flat.numel() else b"")
    return h.hexdigest()[:16]


def reusable_summary(out_dir: Path, made_by: str | None = None) -> dict | None:
    """``out_dir/summary.json`` of a refined sequence if it may be reused: there, and (with ``made_by``) made by
    those weights (:func:`weights_digest`); else None."""
    done = Path(out_dir) / "summary.json"
    if not done.is_file():
        return None
    summary = read_json(done, f"delete {out_dir} so that the sequence is refined again")
    return summary if made_by is None or summary.get("made_by") == made_by else None


def refine_sequence(cfg: DictConfig, seq: Sequence, cache, depth, std, colors, excluded: np.ndarray | None,
                    out_dir: Path, made_by: str | None = None) -> dict:
    """One sequence's end-of-iteration work; writes ``out_dir/{mesh.ply, poses.txt, simulated_depth.npz,
    failures.csv, resfm.json, summary.json}`` and returns the summary.  Skips if ``summary.json`` exists, unless
    ``made_by`` (e.g. :func:`weights_digest` of the network whose depth this is) differs from the one it records:
    an iteration trained again after an interruption must not keep sequences the earlier network refined.

    A frame range flagged again after being flagged in the previous iteration
    (``<run>/iteration=<i-1>/sequences/<slug>/failures.csv``) is solved again by SfM and its aligned poses
    replace the current ones before PGO (:mod:`endorecon.tasks.resfm`, ``failure.rerun``).

    ``excluded`` (N,) bool: the frames the previous iteration left out.  They stay out of both fusions here, and
    this iteration's check decides whether the next iteration leaves them out again; with
    ``failure.keep_excluded`` it does whatever the check says (``kept_out`` in the summary: the ones that passed),
    so a frame once left out stays out for the rest of the run."""
    from endorecon.failure import detect_failures

    out_dir = Path(out_dir)
    done = out_dir / "summary.json"
    summary = reusable_summary(out_dir, made_by)
    if summary is not None:
        return summary
    if done.is_file():
        log.info("%s: %s was made by other weights; refining again with %s", seq.name, done, made_by)
    out_dir.mkdir(parents=True, exist_ok=True)
    n = len(seq)
    times = {}
    poses = seq.cam_from_world.copy()
    registered = np.isfinite(poses).all(axis=(1, 2))
    use = registered if excluded is None else registered & ~excluded

    # 1. fuse with the current poses, render it back: the simulated depth that failure detection judges.
    t0 = time.perf_counter()
    volume = fuse_sequence(cfg.fusion, seq, depth, std, colors, poses, use, saved=False)
    mesh0 = volume.extract_mesh()
    sim, sim_valid = render_simulated(mesh0, seq, poses)
    times["fusion_s"] = time.perf_counter() - t0

    K = torch.from_numpy(seq.intrinsics).float()
    mask = torch.from_numpy(seq.mask)[None]

    sparse_flow_fn = _flow_fn(cache)
    # 2. failure detection.
    t0 = time.perf_counter()
    flagged = np.zeros(n, bool)  # the checked frames flagged and the frames around them that take their verdict
    kept_out = []  # left out by the previous iteration, passed this check, passed on anyway (failure.keep_excluded)
    report = detect_failures(depth, std, torch.from_numpy(sim)[:, None], torch.from_numpy(sim_valid)[:, None], K,
                             torch.from_numpy(poses), mask, sparse_flow_fn, _stage_cfg(cfg.failure))
    report.to_csv(out_dir / "failures.csv")
    if cfg.failure.enabled:
        # only every interval-th frame is checked; its neighbours within exclude_radius share its verdict
        radius = cfg.failure.get("exclude_radius")
        flagged[[f for f in report.excluded_frames(None if radius is None else int(radius)) if f < n]] = True
        if excluded is not None and cfg.failure.get("keep_excluded", False):
            kept_out = [int(f) for f in np.flatnonzero(excluded & ~flagged & registered)]
            flagged |= excluded
            if kept_out:
                log.info("%s: frames %s passed this check but stay out of the next iteration "
                         "(failure.keep_excluded)", seq.name, kept_out)
    times["failure_s"] = time.perf_counter() - t0

    # 2b. a range flagged in this and the previous iteration: SfM rerun on it, aligned poses spliced in.
    resfm_info = {}
    if cfg.failure.enabled:
        from endorecon.tasks import resfm

        t0 = time.perf_counter()
        try:
            poses, resfm_info = resfm.run(cfg, seq, report, poses, out_dir)
        except Exception as e:  # a failed rerun must not cost the iteration: keep the poses, record why
            log.exception("%s: SfM rerun of repeatedly flagged ranges failed; poses kept", seq.name)
            resfm_info = dict(ranges=[], replaced_frames=[], error=f"{type(e).__name__}: {e}")
            try:
                resfm.write_info(out_dir, resfm_info)
            except OSError:
                pass
        registered = np.isfinite(poses).all(axis=(1, 2))  # a rerun may register a frame SfM had lost
        use = registered if excluded is None else registered & ~excluded
        times["resfm_s"] = time.perf_counter() - t0

    # 3. dense pose graph optimisation.
    t0 = time.perf_counter()
    pgo_summary = {}
    if cfg.pgo.enabled:
        res = refine_poses(cfg.pgo, seq.replace(cam_from_world=poses), cache, depth, std)
        new_poses = res.cam_from_world.detach().double().numpy()
        new_poses[~registered] = np.nan
        rot = res.update_rotation_deg[torch.isfinite(res.update_rotation_deg)]
        trans = res.update_translation[torch.isfinite(res.update_translation)]
        pgo_summary = dict(loss_before=float(res.loss_before), loss_after=float(res.loss_after),
                           update_rotation_deg_median=float(rot.median()) if len(rot) else None,
                           update_rotation_deg_max=float(rot.max()) if len(rot) else None,
                           update_translation_median=float(trans.median()) if len(trans) else None,
                           update_translation_max=float(trans.max()) if len(trans) else None)
        poses = new_poses
    times["pgo_s"] = time.perf_counter() - t0
    write_poses_txt(out_dir / "poses.txt", [p.name for p in seq.frame_paths], poses)

    # 4. fuse again with refined poses and without flagged frames; render for the next iteration.
    t0 = time.perf_counter()
    keep = use & ~flagged
    all_flagged = not keep.any() and bool(use.any())
    if all_flagged:
        log.warning("%s: every frame flagged; fusing all registered frames", seq.name)
        keep = use
        flagged = np.zeros(n, bool)  # nothing was left out after all (nor is in the next iteration)
        kept_out = []
    volume = fuse_sequence(cfg.fusion, seq, depth, std, colors, poses, keep)
    volume.save_mesh(out_dir / "mesh.ply")
    free_space = getattr(volume, "last_free_space", None)  # what the free-space check removed from the saved mesh (None: off)
    uncertain = getattr(volume, "last_uncertain", None)  # what the uncertainty trim removed (None: off)
    far_only = getattr(volume, "last_far_only", None)  # what the nearest-view check removed (None: off)
    sim, sim_valid = render_simulated(volume.extract_mesh(), seq, poses)
    save_simulated(out_dir / "simulated_depth.npz", sim, sim_valid)
    times["fusion2_s"] = time.perf_counter() - t0

    summary = dict(
        sequence=seq.name,
        frames=n,
        registered=int(registered.sum()),
        fused=int(keep.sum()),
        flagged=[int(f) for f in report.flagged_frames] if cfg.failure.enabled else [],
        n_flagged=len(report.flagged_frames) if cfg.failure.enabled else 0,
        # of those, the ones flagged by the hysteresis (next to a flagged frame, over a low threshold)
        flagged_low=report.low_flagged_frames if cfg.failure.enabled else [],
        excluded=[int(i) for i in np.flatnonzero(flagged)],  # left out of this fusion and the next iteration
        kept_out=kept_out,  # of those, the ones passed on although they passed the check (failure.keep_excluded)
        all_flagged_fused=all_flagged,  # every frame was flagged: all were fused, none left out
        checked=int(len(report.checked_frames)) if hasattr(report, "checked_frames") else None,
        pgo=pgo_summary,
        resfm=resfm_info,
        free_space=free_space,
        uncertain=uncertain,
        far_only=far_only,
        times=times,
        sfm_fingerprint=sfm_fingerprint(seq),  # the next iteration checks its SfM against these poses
    )
    if made_by is not None:
        summary["made_by"] = made_by
    atomic_write_text(done, json.dumps(summary, indent=2) + "\n")
    return summary


# --------------------------------------------------------------- evaluation
def evaluate_against_ct(data_root: Path, seq: Sequence, mesh_path: Path, cam_from_world: np.ndarray,
                        out_dir: Path, reference: Path | None = None) -> dict | None:
    """Residuals (mm) of a sequence's mesh against its patient's CT, registered with a similarity that is
    initialised from the camera trajectory.  None for patients without CT.  The only reader of ground truth.

    ``reference``: another surface in the CT's frame instead (analyses of train-only patients pass their
    phantom surface, which no run reads)."""
    from endorecon.data.dataset import load_ground_truth
    from endorecon.evaluation import evaluate_mesh
    from endorecon.geometry import camera_centers

    gt = load_ground_truth(data_root, seq.patient, seq.name.split("/")[-1])
    reference = reference or gt.mesh_path
    if reference is None:
        return None
    ok = np.isfinite(cam_from_world).all(axis=(1, 2))
    centers = camera_centers(torch.from_numpy(cam_from_world[ok])).numpy()
    gt_centers = camera_centers(torch.from_numpy(gt.cam_from_world[ok])).numpy()
    return evaluate_mesh(mesh_path, reference, out_dir, cam_centers=centers, gt_cam_centers=gt_centers,
                         cam_rotations=cam_from_world[ok, :3, :3], gt_cam_rotations=gt.cam_from_world[ok, :3, :3])


def evaluate_depth(data_root: Path, seq: Sequence, depth: torch.Tensor, std: torch.Tensor,
                   caps_mm: tuple[float | None, ...] = (None,)) -> list[dict]:
    """Network depth of a phantom sequence against its GT depth: the SCARED metric set with per-frame median
    scaling, the Spearman correlation of the predicted std with the actual error (both after scaling), and
    ``by_relative_depth``: the signed error per band of depth relative to the frame's median
    (:func:`~endorecon.evaluation.depth_metrics.depth_error_by_range`).

    Args:
        seq: the sequence at the network's resolution (GT depth is area-averaged down to it).
        depth, std: (N, 1, h, w).
        caps_mm: depth caps (SCARED style: pixels with GT deeper than the cap are left out and predictions
            are clamped to it; None: no cap).
    Returns:
        one metric dict per cap, in order (the GT is loaded and resampled once for all).
    """
    import torch.nn.functional as F

    from endorecon.data.dataset import load_ground_truth
    from endorecon.evaluation.depth_metrics import depth_error_by_range, depth_metrics, std_error_spearman

    gt = load_ground_truth(data_root, seq.patient, seq.name.split("/")[-1])
    g = torch.from_numpy(gt.depth_mm).float()[:, None]
    v = (g > 0).float()
    h, w = depth.shape[-2:]
    g_small = F.interpolate(g, size=(h, w), mode="area")
    v_small = F.interpolate(v, size=(h, w), mode="area") > 0.999  # only pixels whose whole footprint is valid
    # depth_metrics scores a non-finite / non-positive prediction at its floor and counts it: not left out here
    valid = v_small & torch.from_numpy(seq.mask)[None, None]
    pred_ok = torch.isfinite(depth) & (depth > 0) & torch.isfinite(std)  # what a rank or a ratio can use
    results = []
    for cap_mm in caps_mm:
        out = depth_metrics(depth, g_small, valid, median_scaling=True, cap=cap_mm)
        mask = (valid if cap_mm is None else valid & (g_small <= cap_mm)) & pred_ok
        # Per-frame median scale, then rank-correlate std with |error| over all pixels.
        errs, stds = torch.zeros_like(depth), torch.zeros_like(std)
        for i in range(len(depth)):
            m = mask[i]
            if m.any():
                s = g_small[i][m].median() / depth[i][m].median()
                errs[i] = (depth[i] * s - g_small[i]).abs()
                stds[i] = std[i] * s
        out["std_error_spearman"] = std_error_spearman(stds, errs, mask)
        out["by_relative_depth"] = depth_error_by_range(depth, g_small, mask)
        results.append(out)
    return results


def evaluate_depth_with_cap(data_root: Path, seq: Sequence, depth: torch.Tensor, std: torch.Tensor,
                            cap_mm: float | None) -> tuple[dict, dict | None]:
    """:func:`evaluate_depth` without a cap and, when ``cap_mm`` is set (``bootstrap.depth_cap_mm``),
    with it; returns (uncapped, capped or None)."""
    uncapped, *capped = evaluate_depth(data_root, seq, depth, std, (None,) if cap_mm is None else (None, float(cap_mm)))
    return uncapped, (capped[0] if capped else None)
