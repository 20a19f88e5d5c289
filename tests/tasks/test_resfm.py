"""SfM reruns of repeatedly flagged ranges (endorecon.tasks.resfm), with the SfM rerun replaced by a segment
made from GT poses in a known similarity frame; one slow test runs pycolmap on a tiny phantom."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

import endorecon.sfm.stage as stage
from endorecon.data.sequence import Sequence, read_poses_txt
from endorecon.failure import METRICS, FailureReport
from endorecon.geometry import camera_centers, invert_pose, se3_exp, so3_exp
from endorecon.tasks import resfm

N = 30
ATTEMPTS = [{"name": "a0"}, {"name": "a1"}, {"name": "a2"}]


def make_cfg(**rerun):
    return OmegaConf.create({
        "failure": {"enabled": True, "interval": 5, "rerun": {"enabled": True, "pad": 5, "first_attempt": 1,
                                                               "min_anchor_frames": 3, "replace_radius": None,
                                                               **rerun}},
        "sfm": {"attempts": ATTEMPTS},
        "pgo": {"enabled": False},
        "fusion": {},
    })


def gt_poses(n=N, straight=False) -> np.ndarray:
    """cam_from_world (n, 4, 4) float64 of a camera moving along a curve (or a straight line) while turning."""
    T = torch.zeros(n, 4, 4, dtype=torch.float64)
    for i in range(n):
        w = torch.tensor([0.02 * i, 0.03 * i, -0.01 * i], dtype=torch.float64)
        c = (torch.tensor([0.0, 0.0, 0.5 * i], dtype=torch.float64) if straight else
             torch.tensor([3 * math.sin(0.1 * i), 0.2 * i, 3 * math.cos(0.1 * i)], dtype=torch.float64))
        wfc = torch.eye(4, dtype=torch.float64)
        wfc[:3, :3] = so3_exp(w[None])[0]
        wfc[:3, 3] = c
        T[i] = invert_pose(wfc[None])[0]
    return T.numpy()


def make_seq(tmp_path: Path, poses: np.ndarray) -> Sequence:
    K = np.array([[40.0, 0, 39.5], [0, 40.0, 31.5], [0, 0, 1]])
    return Sequence(name="p0/seq_00", frame_paths=[tmp_path / f"{i:06d}.png" for i in range(len(poses))],
                    intrinsics=K, height=64, width=80, mask=np.ones((64, 80), bool), cam_from_world=poses)


def make_report(flagged: list[int], n=N, interval=5) -> FailureReport:
    frames = np.arange(0, n, interval)
    fl = np.isin(frames, flagged)
    metrics = {m: np.where(fl, 5.0, 0.0) for m in METRICS}
    exceeded = {m: fl.copy() for m in METRICS}
    return FailureReport(frames, metrics, exceeded, fl, ["dense_simulation" if f else "" for f in fl],
                         interval=interval, n_frames=n)


# Segment world -> current world: x_w = S_SCALE R x_seg + t.
S_SCALE = 7.5
S_R = so3_exp(torch.tensor([[0.3, -1.1, 0.7]], dtype=torch.float64))[0].numpy()
S_T = np.array([4.0, -2.0, 9.0])


def segment_from_gt(gt: np.ndarray, first: int, last: int, noise=0.0, seed=0) -> np.ndarray:
    """The GT poses of frames first..last as an SfM rerun would give them: in the segment's world and units.

    cam_seg_from_seg = D(1/s) @ cam_from_world @ [s R | t] (camera coordinates scaled into segment units)."""
    S = np.eye(4)
    S[:3, :3] = S_SCALE * S_R
    S[:3, 3] = S_T
    D = np.diag([1 / S_SCALE] * 3 + [1.0])
    seg = np.stack([D @ gt[i] @ S for i in range(first, last + 1)])
    if noise:
        xi = torch.from_numpy(np.random.default_rng(seed).normal(0, noise, (len(seg), 6)))
        seg = (se3_exp(xi) @ torch.from_numpy(seg)).numpy()
    return seg


def corrupt(gt: np.ndarray, frames) -> np.ndarray:
    bad = gt.copy()
    for k, f in enumerate(frames):
        xi = torch.tensor([[0.3, -0.2, 0.4, 0.1, 0.05, -0.08]], dtype=torch.float64) * (1 + 0.3 * k)
        bad[f] = (se3_exp(xi)[0] @ torch.from_numpy(gt[f])).numpy()
    return bad


@pytest.fixture
def fake_rerun(monkeypatch):
    """Replace the SfM rerun by GT poses in the segment's own similarity frame; records its calls."""
    calls = []

    def fake(cfg_sfm, seq, segment, attempt, out_dir):
        first, last = segment
        calls.append(dict(segment=tuple(segment), attempt=attempt, out_dir=Path(out_dir), frames=len(seq)))
        seg = segment_from_gt(fake.gt, first, last, noise=fake.noise)
        for f in fake.unregistered:
            seg[f - first] = np.nan
        return seq.replace(frame_paths=seq.frame_paths[first:last + 1], cam_from_world=seg, units="sfm")

    fake.gt, fake.noise, fake.unregistered, fake.calls = None, 0.0, (), calls
    monkeypatch.setattr(stage, "rerun", fake)
    return fake


# ------------------------------------------------------------------ geometry
def test_align_segment_poses_inverts_the_similarity():
    gt = gt_poses()
    seg = segment_from_gt(gt, 3, 9)
    back = resfm.align_segment_poses(seg, S_SCALE, S_R, S_T)
    np.testing.assert_allclose(back, gt[3:10], atol=1e-10)
    # Camera centres map by the similarity itself: C_w = s R C_seg + t.
    c_seg = camera_centers(torch.from_numpy(seg)).numpy()
    c_w = camera_centers(torch.from_numpy(back)).numpy()
    np.testing.assert_allclose(c_w, S_SCALE * c_seg @ S_R.T + S_T, atol=1e-9)
    # NaN rows (unregistered) stay NaN.
    seg[2] = np.nan
    assert np.isnan(resfm.align_segment_poses(seg, S_SCALE, S_R, S_T)[2]).all()


@pytest.mark.parametrize("straight", [False, True])
def test_fit_sim3_recovers_similarity_even_on_a_straight_trajectory(straight):
    # On a straight line, camera centres alone leave the rotation about the line free; the axes fix it.
    gt = gt_poses(straight=straight)
    seg = segment_from_gt(gt, 0, 9)
    s, R, t = resfm.fit_segment_sim3(seg[[0, 1, 2, 8, 9]], gt[[0, 1, 2, 8, 9]])
    assert s == pytest.approx(S_SCALE, rel=1e-9)
    np.testing.assert_allclose(R, S_R, atol=1e-9)
    np.testing.assert_allclose(t, S_T, atol=1e-8)


def test_fit_sim3_rejects_coinciding_centres():
    T = np.repeat(gt_poses()[:1], 3, axis=0)
    with pytest.raises(ValueError, match="coincide"):
        resfm.fit_segment_sim3(T, T)


# ------------------------------------------------------------------ the step
def test_rerun_restores_flagged_poses(tmp_path, fake_rerun):
    gt = gt_poses()
    fake_rerun.gt = gt
    cur = corrupt(gt, range(13, 18))
    seq = make_seq(tmp_path, cur)
    new, info = resfm.rerun_repeated_failures(make_cfg(), seq, make_report([15]), make_report([15]), cur, tmp_path)
    assert fake_rerun.calls[0]["segment"] == (10, 20)
    assert fake_rerun.calls[0]["attempt"] == 1
    rec = info["ranges"][0]
    assert rec["status"] == "replaced"
    assert rec["anchors"] == [10, 11, 12, 18, 19, 20]
    assert info["replaced_frames"] == [13, 14, 15, 16, 17]
    np.testing.assert_allclose(new[13:18], gt[13:18], atol=1e-6)
    np.testing.assert_array_equal(new[:13], cur[:13])
    np.testing.assert_array_equal(new[18:], cur[18:])
    assert rec["sim3"]["scale"] == pytest.approx(S_SCALE, rel=1e-9)
    assert rec["anchor_rms"] < 1e-8
    # The recorded change is the corruption's size.
    assert all(c["rotation_deg"] > 1.0 and c["translation"] > 0.05 for c in rec["pose_change"].values())


def test_rerun_with_noise_is_close(tmp_path, fake_rerun):
    gt = gt_poses()
    fake_rerun.gt, fake_rerun.noise = gt, 1e-3
    cur = corrupt(gt, range(13, 18))
    seq = make_seq(tmp_path, cur)
    new, _ = resfm.rerun_repeated_failures(make_cfg(), seq, make_report([15]), make_report([15]), cur, tmp_path)
    def centre_err(T):
        return (camera_centers(torch.from_numpy(T[13:18])) - camera_centers(torch.from_numpy(gt[13:18]))).norm(dim=1)

    err_before, err_after = centre_err(cur), centre_err(new)
    assert err_after.max() < 0.05 * err_before.min()


def test_too_few_anchors_keeps_poses(tmp_path, fake_rerun):
    gt = gt_poses()
    fake_rerun.gt = gt
    cur = corrupt(gt, range(13, 18))
    seq = make_seq(tmp_path, cur)
    # pad 3 with replace radius 2: one anchor each side.
    new, info = resfm.rerun_repeated_failures(make_cfg(pad=3), seq, make_report([15]), make_report([15]), cur,
                                              tmp_path)
    rec = info["ranges"][0]
    assert rec["status"] == "not_aligned" and "anchor" in rec["reason"]
    assert rec["anchors"] == [12, 18]
    np.testing.assert_array_equal(new, cur)
    assert info["replaced_frames"] == []


def test_flagged_neighbours_are_not_anchors(tmp_path, fake_rerun):
    gt = gt_poses()
    fake_rerun.gt = gt
    cur = corrupt(gt, range(13, 18))
    seq = make_seq(tmp_path, cur)
    # Frame 25 flagged too, in a range of its own (not repeated): its excluded frames 23..27 are not in 10..20.
    new, info = resfm.rerun_repeated_failures(make_cfg(), seq, make_report([15, 25]), make_report([15]), cur,
                                              tmp_path)
    assert [r["range"] for r in info["ranges"]] == [[15, 15]]
    assert info["ranges"][0]["anchors"] == [10, 11, 12, 18, 19, 20]
    new, info = resfm.rerun_repeated_failures(make_cfg(), seq, make_report([15, 20]), make_report([15]), cur,
                                              tmp_path)
    # 15 and 20 merge into one range (gap <= interval): segment 10..25, replaced 13..22.
    rec = info["ranges"][0]
    assert rec["range"] == [15, 20] and rec["segment"] == [10, 25] and rec["anchors"] == [10, 11, 12, 23, 24, 25]
    np.testing.assert_allclose(new[13:23], gt[13:23], atol=1e-6)


def test_unregistered_rerun_frames_keep_their_pose(tmp_path, fake_rerun):
    gt = gt_poses()
    fake_rerun.gt, fake_rerun.unregistered = gt, (14,)
    cur = corrupt(gt, range(13, 18))
    new, info = resfm.rerun_repeated_failures(make_cfg(), make_seq(tmp_path, cur), make_report([15]),
                                              make_report([15]), cur, tmp_path)
    assert info["ranges"][0]["not_registered"] == [14]
    np.testing.assert_array_equal(new[14], cur[14])
    np.testing.assert_allclose(new[[13, 15, 16, 17]], gt[[13, 15, 16, 17]], atol=1e-6)


def test_noop_without_previous_report_or_repeat(tmp_path, fake_rerun):
    gt = gt_poses()
    fake_rerun.gt = gt
    seq = make_seq(tmp_path, gt)
    new, info = resfm.rerun_repeated_failures(make_cfg(), seq, make_report([15]), None, gt, tmp_path)
    assert info["skipped"] == "no previous failure report" and info["ranges"] == []
    np.testing.assert_array_equal(new, gt)
    new, info = resfm.rerun_repeated_failures(make_cfg(), seq, make_report([15]), make_report([0]), gt, tmp_path)
    assert "no range" in info["skipped"]
    np.testing.assert_array_equal(new, gt)
    assert fake_rerun.calls == []


def test_attempt_counts_earlier_reruns_and_is_capped(tmp_path, fake_rerun):
    gt = gt_poses()
    fake_rerun.gt = gt
    seq = make_seq(tmp_path, gt)
    history = [{"ranges": [{"range": [14, 16], "status": "replaced"}]}]
    resfm.rerun_repeated_failures(make_cfg(), seq, make_report([15]), make_report([15]), gt, tmp_path,
                                  history=history)
    assert fake_rerun.calls[-1]["attempt"] == 2
    resfm.rerun_repeated_failures(make_cfg(), seq, make_report([15]), make_report([15]), gt, tmp_path,
                                  history=history * 3)
    assert fake_rerun.calls[-1]["attempt"] == len(ATTEMPTS) - 1
    # A rerun of another range does not count.
    resfm.rerun_repeated_failures(make_cfg(), seq, make_report([15]), make_report([15]), gt, tmp_path,
                                  history=[{"ranges": [{"range": [0, 5], "status": "replaced"}]}])
    assert fake_rerun.calls[-1]["attempt"] == 1
    assert fake_rerun.calls[-1]["out_dir"] == tmp_path / "resfm" / "00010_00020_attempt1"


def test_sfm_failure_is_recorded_not_raised(tmp_path, monkeypatch):
    def failing(cfg_sfm, seq, segment, attempt, out_dir):
        raise stage.SfMError("SfM found no acceptable model for 11 frames", fix="try more")

    monkeypatch.setattr(stage, "rerun", failing)
    gt = gt_poses()
    cur = corrupt(gt, range(13, 18))
    new, info = resfm.rerun_repeated_failures(make_cfg(), make_seq(tmp_path, cur), make_report([15]),
                                              make_report([15]), cur, tmp_path)
    assert info["ranges"][0]["status"] == "sfm_failed" and info["ranges"][0]["error_type"] == "SfMError"
    np.testing.assert_array_equal(new, cur)


def test_previous_iteration_dir_layout(tmp_path):
    d = tmp_path / "fold=0" / "iteration=2" / "sequences" / "p0__seq_00"
    assert resfm.previous_iteration_dir(d) == tmp_path / "fold=0" / "iteration=1" / "sequences" / "p0__seq_00"
    assert resfm.previous_iteration_dir(tmp_path / "fold=0" / "iteration=0" / "sequences" / "x") is None
    assert resfm.previous_iteration_dir(tmp_path / "reconstruction") is None
    assert resfm.previous_iteration_dir(tmp_path / "iteration=x" / "sequences" / "s") is None


def test_bad_config_is_rejected():
    with pytest.raises(Exception, match="min_anchor_frames"):
        resfm.rerun_cfg(make_cfg(min_anchor_frames=1))


# ------------------------------------------------------------------ in refine_sequence
@pytest.fixture
def light_pipeline(monkeypatch):
    """refine_sequence without fusion and rendering (a stub volume), with a scripted failure report."""
    from endorecon import failure
    from endorecon.tasks import pipeline

    class Volume:
        def extract_mesh(self):
            return None

        def save_mesh(self, path):
            Path(path).write_text("ply stub\n")

    monkeypatch.setattr(pipeline, "fuse_sequence", lambda *a, **k: Volume())
    monkeypatch.setattr(pipeline, "render_simulated",
                        lambda mesh, seq, poses: (np.zeros((len(seq), seq.height, seq.width), np.float32),
                                                  np.zeros((len(seq), seq.height, seq.width), bool)))
    flagged = {"frames": [15]}
    monkeypatch.setattr(failure, "detect_failures", lambda *a, **k: make_report(flagged["frames"]))
    return pipeline, flagged


def _refine(pipeline, cfg, seq, out_dir):
    n = len(seq)
    depth = torch.ones(n, 1, seq.height, seq.width)
    colors = np.zeros((n, seq.height, seq.width, 3), np.float32)
    return pipeline.refine_sequence(cfg, seq, None, depth, 0.1 * depth, colors, None, out_dir)


def test_refine_sequence_reruns_a_range_flagged_twice(tmp_path, fake_rerun, light_pipeline):
    pipeline, _ = light_pipeline
    gt = gt_poses()
    fake_rerun.gt = gt
    cur = corrupt(gt, range(13, 18))
    seq = make_seq(tmp_path, cur)
    run = tmp_path / "train" / "fold=0"
    s0 = _refine(pipeline, make_cfg(), seq, run / "iteration=0" / "sequences" / "p0__seq_00")
    assert s0["resfm"]["skipped"] == "no previous iteration's failures.csv" and fake_rerun.calls == []
    out1 = run / "iteration=1" / "sequences" / "p0__seq_00"
    s1 = _refine(pipeline, make_cfg(), seq, out1)
    assert s1["resfm"]["replaced_frames"] == [13, 14, 15, 16, 17]
    assert json.loads((out1 / "resfm.json").read_text())["ranges"][0]["status"] == "replaced"
    assert json.loads((out1 / "summary.json").read_text())["resfm"]["ranges"][0]["attempt"] == 1
    _, poses = read_poses_txt(out1 / "poses.txt")  # PGO off: the rerun's poses are what is written
    np.testing.assert_allclose(poses[13:18], gt[13:18], atol=1e-6)
    np.testing.assert_allclose(poses[:13], cur[:13], atol=1e-9)
    # Resumable: a second call returns the summary without rerunning.
    n_calls = len(fake_rerun.calls)
    assert _refine(pipeline, make_cfg(), seq, out1) == s1 and len(fake_rerun.calls) == n_calls
    # Iteration 2 of the same range: the next hyperparameter set.
    s2 = _refine(pipeline, make_cfg(), seq, run / "iteration=2" / "sequences" / "p0__seq_00")
    assert s2["resfm"]["ranges"][0]["attempt"] == 2


def test_refine_sequence_survives_a_crashing_rerun(tmp_path, monkeypatch, light_pipeline):
    pipeline, _ = light_pipeline

    def crash(*a, **k):
        raise RuntimeError("pycolmap exploded")

    monkeypatch.setattr(stage, "rerun", crash)
    seq = make_seq(tmp_path, gt_poses())
    run = tmp_path / "fold=0"
    _refine(pipeline, make_cfg(), seq, run / "iteration=0" / "sequences" / "s")
    s1 = _refine(pipeline, make_cfg(), seq, run / "iteration=1" / "sequences" / "s")
    assert "pycolmap exploded" in s1["resfm"]["error"]
    assert json.loads((run / "iteration=1" / "sequences" / "s" / "resfm.json").read_text())["error"]
    assert (run / "iteration=1" / "sequences" / "s" / "summary.json").is_file()


def test_refine_sequence_rerun_disabled(tmp_path, fake_rerun, light_pipeline):
    pipeline, _ = light_pipeline
    fake_rerun.gt = gt_poses()
    seq = make_seq(tmp_path, fake_rerun.gt)
    run = tmp_path / "fold=0"
    _refine(pipeline, make_cfg(enabled=False), seq, run / "iteration=0" / "sequences" / "s")
    s1 = _refine(pipeline, make_cfg(enabled=False), seq, run / "iteration=1" / "sequences" / "s")
    assert "enabled is false" in s1["resfm"]["skipped"] and fake_rerun.calls == []


@pytest.mark.parametrize("radius, left_out", [(None, [13, 14, 15, 16, 17]), (1, [14, 15, 16]), (0, [15])])
def test_refine_sequence_leaves_out_the_flagged_frames_neighbours(tmp_path, monkeypatch, light_pipeline, radius,
                                                                  left_out):
    """Only every 5th frame is checked; the frames within failure.exclude_radius of a flagged one take its verdict:
    left out of the final fusion and listed for the next iteration (only the checked frame was)."""
    pipeline, _ = light_pipeline
    uses = []

    class Volume:
        def extract_mesh(self):
            return None

        def save_mesh(self, path):
            Path(path).write_text("ply stub\n")

    monkeypatch.setattr(pipeline, "fuse_sequence", lambda cfg, seq, d, s, c, poses, use, **k: (uses.append(use), Volume())[1])
    cfg = make_cfg(enabled=False)
    cfg.failure.exclude_radius = radius
    seq = make_seq(tmp_path, gt_poses())
    summary = _refine(pipeline, cfg, seq, tmp_path / "fold=0" / "iteration=0" / "sequences" / "s")
    assert np.flatnonzero(~uses[-1]).tolist() == left_out and uses[0].all()
    assert summary["flagged"] == [15] and summary["n_flagged"] == 1 and summary["excluded"] == left_out
    assert summary["fused"] == N - len(left_out)


def test_refine_sequence_with_every_frame_flagged_fuses_all_and_excludes_none(tmp_path, monkeypatch,
                                                                               light_pipeline):
    """Every checked frame flagged: fusion falls back to all registered frames, so the summary must not list
    them all as left out (the report said both; the next iteration would have trained on no frame)."""
    pipeline, flagged = light_pipeline
    flagged["frames"] = list(range(0, N, 5))
    cfg = make_cfg(enabled=False)
    cfg.failure.exclude_radius = 4  # the checked frames 0, 5, ..., 25 and their neighbours cover all 30
    summary = _refine(pipeline, cfg, make_seq(tmp_path, gt_poses()), tmp_path / "fold=0" / "iteration=0" / "sequences" / "s")
    assert summary["fused"] == N and summary["excluded"] == [] and summary["all_flagged_fused"]
    assert summary["n_flagged"] == len(flagged["frames"])


def test_a_negative_radius_is_refused_before_sfm(tmp_path, fake_rerun, light_pipeline):
    """A negative replace radius crashed after the SfM rerun (IndexError); it is refused before it."""
    from endorecon.utils.errors import InputError

    radius = -1

    fake_rerun.gt = gt_poses()
    seq = make_seq(tmp_path, fake_rerun.gt)
    run = tmp_path / "fold=0"
    _, flagged = light_pipeline
    prev = run / "iteration=0" / "sequences" / "s"
    prev.mkdir(parents=True)
    make_report([15]).to_csv(prev / "failures.csv")
    out = run / "iteration=1" / "sequences" / "s"
    with pytest.raises(InputError, match="must be >= 0"):
        resfm.run(make_cfg(replace_radius=radius), seq, make_report([15]), fake_rerun.gt.copy(), out)
    assert fake_rerun.calls == []


# ------------------------------------------------------------------ real pycolmap
@pytest.mark.slow
def test_real_rerun_restores_corrupted_poses_on_a_phantom(tmp_path):
    """pycolmap on an 11-frame segment of a phantom clip, called with the network-resolution record (frames
    resized on load): two corrupted GT poses (mm) come back to GT within a small error."""
    from endorecon.data.dataset import load_dataset, load_ground_truth
    from endorecon.data.transforms import resize_sequence
    from endorecon.phantom.generate import generate

    root = generate(tmp_path / "ph", patients=1, frames=20, height=192, width=240, step_mm=0.5)
    seq = load_dataset(root)[0]
    gt = load_ground_truth(root, 0).cam_from_world
    small = resize_sequence(seq, 96, 120).replace(cam_from_world=gt)
    assert small.native_window is not None
    cur = corrupt(gt, [9, 11])
    cfg = make_cfg()
    cfg.sfm = OmegaConf.load(Path(__file__).resolve().parents[2] / "conf" / "sfm" / "default.yaml")
    cfg.sfm.min_points = 50
    report = make_report([10], n=len(seq))
    new, info = resfm.rerun_repeated_failures(cfg, small, report, report, cur, tmp_path / "out")
    rec = info["ranges"][0]
    assert rec["status"] == "replaced", rec
    assert rec["segment"] == [5, 15] and rec["attempt"] == 1
    seg_dir = tmp_path / "out" / "resfm" / "00005_00015_attempt1"
    assert (seg_dir / "sequence.npz").is_file()
    from PIL import Image

    with Image.open(seg_dir / "images" / "000000.png") as im:  # SfM saw the frames at their native size
        assert im.size == (240, 192)
    for f in (9, 11):
        rot, trans = resfm.pose_change(gt[f], new[f])
        rot0, trans0 = resfm.pose_change(gt[f], cur[f])
        # mm, degrees (the step is 0.5 mm, the corruption 0.5-0.7 mm and 8-10 degrees); measured 0.03-0.05 mm,
        # 0.24-0.35 degrees
        assert trans < 0.1 and rot < 1.0, (f, rot, trans)
        assert trans < 0.2 * trans0 and rot < 0.1 * rot0
    for f in (8, 10, 12):  # replaced but not corrupted: stay close
        rot, trans = resfm.pose_change(gt[f], new[f])
        assert trans < 0.1 and rot < 1.0, (f, rot, trans)


def test_replaced_frames_follow_exclude_radius(tmp_path, fake_rerun):
    gt = gt_poses()
    fake_rerun.gt = gt
    cur = corrupt(gt, range(13, 18))
    cfg = make_cfg()
    cfg.failure.exclude_radius = 1
    new, info = resfm.rerun_repeated_failures(cfg, make_seq(tmp_path, cur), make_report([15]), make_report([15]),
                                              cur, tmp_path)
    assert info["replaced_frames"] == [14, 15, 16]
    assert info["ranges"][0]["anchors"] == [10, 11, 12, 13, 17, 18, 19, 20]
    np.testing.assert_array_equal(new[[13, 17]], cur[[13, 17]])
