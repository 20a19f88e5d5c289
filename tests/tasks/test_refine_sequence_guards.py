"""Guards of refine_sequence / fuse_sequence / evaluate_depth (endorecon/tasks/pipeline.py) against mutations that a
single-point mutation review found surviving: each test fails under its mutation.  The heavy stages (fusion,
rendering, failure detection, PGO, SfM rerun) are replaced by small fakes that record what they receive."""

import types

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from endorecon.data.sequence import Sequence, read_poses_txt
from endorecon.tasks import pipeline

N, H, W = 4, 8, 8


def _seq(cam_from_world):
    K = np.array([[10.0, 0, 3.5], [0, 10.0, 3.5], [0, 0, 1]])
    return Sequence(name="patient_00/seq_00", frame_paths=[f"f{i:03d}.png" for i in range(N)], intrinsics=K,
                    height=H, width=W, mask=np.ones((H, W), bool), cam_from_world=cam_from_world)


def _poses(lost=()):
    p = np.tile(np.eye(4), (N, 1, 1))
    p[:, 2, 3] = np.arange(N)
    for i in lost:
        p[i] = np.nan
    return p


class _Volume:
    def extract_mesh(self):
        return "mesh"

    def save_mesh(self, path):
        path.write_text("")


class _Report:
    flagged_frames, checked_frames, low_flagged_frames = [], [0, 2], []

    def to_csv(self, path):
        path.write_text("frame\n")

    def excluded_frames(self, radius=None):
        return []


def _patch_stages(monkeypatch, pgo_poses=None, resfm_poses=None):
    """Fakes for the heavy stages; returns the list of (poses, use) each fuse_sequence call received."""
    import endorecon.failure as failure

    fused = []

    def fuse(cfg_fusion, seq, depth, std, colors, cam_from_world, use, saved=True):
        fused.append((np.array(cam_from_world, copy=True), np.array(use, copy=True)))
        return _Volume()

    monkeypatch.setattr(pipeline, "fuse_sequence", fuse)
    monkeypatch.setattr(pipeline, "render_simulated",
                        lambda mesh, seq, p: (np.zeros((N, H, W), np.float32), np.zeros((N, H, W), bool)))
    monkeypatch.setattr(failure, "detect_failures", lambda *a, **k: _Report())
    if pgo_poses is not None:
        monkeypatch.setattr(pipeline, "refine_poses", lambda cfg, seq, cache, d, s: types.SimpleNamespace(
            cam_from_world=torch.from_numpy(pgo_poses), loss_before=1.0, loss_after=0.5,
            update_rotation_deg=torch.zeros(N), update_translation=torch.zeros(N)))
    if resfm_poses is not None:
        from endorecon.tasks import resfm

        monkeypatch.setattr(resfm, "run", lambda cfg, seq, report, poses, out_dir: (
            resfm_poses.copy(), dict(ranges=[[0, N - 1]], replaced_frames=list(range(N)))))
    return fused


def _cfg(failure_enabled, pgo_enabled, **failure):
    return OmegaConf.create(dict(fusion={}, failure=dict(enabled=failure_enabled, exclude_radius=None, **failure),
                                 pgo=dict(enabled=pgo_enabled)))


def _tensors():
    return torch.ones(N, 1, H, W), torch.ones(N, 1, H, W), np.zeros((N, H, W, 3), np.float32)


def test_pgo_poses_of_unregistered_frames_are_not_written_nor_fused(tmp_path, monkeypatch):
    """Dense PGO returns a finite pose for every frame; a frame SfM never registered must stay NaN in poses.txt
    and in the poses of the final fusion and rendering."""
    fused = _patch_stages(monkeypatch, pgo_poses=_poses())  # PGO: finite everywhere, frame 1 included
    seq = _seq(_poses(lost=[1]))
    summary = pipeline.refine_sequence(_cfg(False, True), seq, None, *_tensors(), None, tmp_path)
    _, written = read_poses_txt(tmp_path / "poses.txt")
    assert np.isnan(written[1]).all() and np.isfinite(written[[0, 2, 3]]).all()
    final_poses, final_use = fused[-1]
    assert np.isnan(final_poses[1]).all() and not final_use[1]
    assert summary["registered"] == 3 and summary["fused"] == 3


def test_frames_the_sfm_rerun_registers_or_loses_follow_its_poses(tmp_path, monkeypatch):
    """The SfM rerun registers frame 1 (lost before) and loses frame 2: the final fusion uses frame 1, not 2."""
    fused = _patch_stages(monkeypatch, resfm_poses=_poses(lost=[2]))
    seq = _seq(_poses(lost=[1]))
    summary = pipeline.refine_sequence(_cfg(True, False), seq, None, *_tensors(), None, tmp_path)
    assert fused[0][1].tolist() == [True, False, True, True]  # before the rerun
    final_poses, final_use = fused[-1]
    assert np.isfinite(final_poses[1]).all() and np.isnan(final_poses[2]).all()
    assert final_use.tolist() == [True, True, False, True]
    assert summary["fused"] == 3 and summary["registered"] == 3


@pytest.mark.parametrize("keep", [False, True])
def test_frames_the_previous_iteration_left_out(tmp_path, monkeypatch, keep):
    """Frame 1 was left out by the previous iteration and this check flags nothing: it stays out of both fusions
    here; the next iteration gets it back unless failure.keep_excluded passes it on (``kept_out``)."""
    fused = _patch_stages(monkeypatch)
    excluded = np.array([False, True, False, False])
    summary = pipeline.refine_sequence(_cfg(True, False, keep_excluded=keep), _seq(_poses()), None, *_tensors(),
                                       excluded, tmp_path)
    assert [use.tolist() for _, use in fused] == [[True, False, True, True]] * 2
    assert summary["excluded"] == ([1] if keep else []) and summary["kept_out"] == ([1] if keep else [])
    assert summary["fused"] == 3


def test_frames_without_a_finite_pose_are_not_fused(monkeypatch):
    """fuse_sequence leaves out a frame whose pose is NaN even when ``use`` selects it."""
    import endorecon.fusion.run as fusion_run

    integrated = []

    class Volume:
        def integrate(self, depth, std, color, K, pose, mask):
            integrated.append(np.array(pose, copy=True))

    monkeypatch.setattr(fusion_run, "build_fusion", lambda cfg, med: Volume())
    poses = _poses(lost=[2])
    depth, std, colors = _tensors()
    pipeline.fuse_sequence({}, _seq(poses), depth, std, colors, poses, np.ones(N, bool))
    assert len(integrated) == N - 1 and all(np.isfinite(p).all() for p in integrated)


def _patch_gt(monkeypatch, gt):
    import endorecon.data.dataset as dataset

    monkeypatch.setattr(dataset, "load_ground_truth", lambda root, p, name: types.SimpleNamespace(depth_mm=gt))


def _seq_ns(h, w):
    return types.SimpleNamespace(patient=0, name="patient_00/seq_00", mask=np.ones((h, w), bool))


def test_capped_std_error_correlation_ranks_only_pixels_within_the_cap(monkeypatch):
    """With a 40 mm cap the std–error Spearman is over the pixels with GT within the cap: there std ranks the
    (median-scaled) error exactly; beyond it (GT 60 mm) the std is 0 and the error large, which would drag the
    correlation down if those pixels counted."""
    gt = np.full((1, 8, 8), 30.0, np.float32)
    gt[0, :, 4:] = 60.0
    _patch_gt(monkeypatch, gt)
    g = torch.from_numpy(gt)[:, None]
    e = torch.rand(1, 1, 8, 8, generator=torch.Generator().manual_seed(1)) * 0.2 - 0.1
    depth = g * (1 + e)
    depth[..., 4:] = 120.0 + 10 * torch.rand(1, 1, 8, 4, generator=torch.Generator().manual_seed(2))
    left = torch.zeros(1, 1, 8, 8, dtype=torch.bool)
    left[..., :4] = True
    s = g[left].median() / depth[left].median()
    std = (depth * s - g).abs()
    std[~left] = 0.0
    uncapped, capped = pipeline.evaluate_depth_with_cap(None, _seq_ns(8, 8), depth, std, 40.0)
    assert capped["std_error_spearman"] > 0.99


def test_std_error_correlation_uses_median_scaled_errors(monkeypatch):
    """The prediction is twice the GT times (1 + e): after per-frame median scaling the error grows with
    |e - median e|, and the std is exactly that error, so ρ = 1; unscaled, the error would grow with e."""
    gt = np.full((1, 8, 8), 50.0, np.float32)
    _patch_gt(monkeypatch, gt)
    g = torch.from_numpy(gt)[:, None]
    e = torch.rand(1, 1, 8, 8, generator=torch.Generator().manual_seed(0)) * 0.4 - 0.2
    depth = 2 * g * (1 + e)
    s = g.median() / depth.median()
    std = (depth * s - g).abs()
    out = pipeline.evaluate_depth(None, _seq_ns(8, 8), depth, std)[0]
    assert out["std_error_spearman"] > 0.99


@pytest.mark.parametrize("enabled", [True, False])
def test_frames_flagged_by_the_hysteresis_are_in_the_summary(tmp_path, monkeypatch, enabled):
    """``flagged_low``: the checked frames the low thresholds flagged (none recorded with failure detection off)."""
    _patch_stages(monkeypatch)
    monkeypatch.setattr(_Report, "flagged_frames", [0, 2])
    monkeypatch.setattr(_Report, "low_flagged_frames", [2])
    summary = pipeline.refine_sequence(_cfg(enabled, False), _seq(_poses()), None, *_tensors(), None, tmp_path)
    assert summary["flagged"] == ([0, 2] if enabled else []) and summary["flagged_low"] == ([2] if enabled else [])
