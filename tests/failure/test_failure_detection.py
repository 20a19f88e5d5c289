"""Failure detection on an analytic scene (camera inside an ellipsoid, 21 frames, 64x80)."""

import math

import numpy as np
import pytest
import torch

from endorecon.failure import METRICS, FailureReport, detect_failures, run
from endorecon.geometry import se3_exp
from endorecon.utils.errors import InputError
from synthetic_scene import make_scene

N = 21
D = torch.float64
BAD_POSE, BAD_DEPTH = 10, 5


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    # Two cores shared by many jobs: OpenMP spin-waiting makes 2 threads far slower than 1 here.
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def scene():
    return make_scene(n_frames=N)


def corrupt_pose(T, k, xi):
    T = T.clone()
    T[k] = se3_exp(torch.tensor([xi], dtype=D))[0] @ T[k]
    return T


def flow_fn(scene, noise_px=0.2):
    return lambda i, j: scene.sparse_flow_fn(i, j, noise_px=noise_px)


def detect(scene, depth, sim, T, rel_std=0.05, cfg=None, noise_px=0.2):
    valid = sim > 0
    return detect_failures(depth, rel_std * depth, sim, valid, scene.K, T, scene.mask, flow_fn(scene, noise_px), cfg or {})


def test_clean_sequence_is_not_flagged(scene):
    sim = scene.render(scene.cam_from_world)
    r = detect(scene, scene.depth, sim, scene.cam_from_world)
    assert list(r.frames) == [0, 5, 10, 15, 20]
    assert r.flagged_frames == []
    for m in METRICS:
        assert np.isfinite(r.metrics[m]).all(), m
    # Exact depths: the dense metrics sit at their minimum 0.5·log σ² (σ = 5 % of depth ~ 1).
    assert (r.metrics["dense_simulation"] < -2.0).all()


@pytest.mark.parametrize("render_at", ["true_pose", "corrupted_pose"])
def test_corrupted_pose_and_depth_are_flagged(scene, render_at):
    T = corrupt_pose(scene.cam_from_world, BAD_POSE, [0.04, 0.0, 0.02, 0.0, 0.04, 0.0])  # ~2.3°, 4.5 % of depth
    # The mesh rendered at the true pose (refined pose) or at the wrong one (as the loop would).
    sim = scene.render(scene.cam_from_world if render_at == "true_pose" else T)
    depth = scene.depth.clone()
    depth[BAD_DEPTH] *= 1.2  # a frame whose network depth is 20 % off
    r = detect(scene, depth, sim, T)
    assert r.flagged_frames == [BAD_DEPTH, BAD_POSE]
    reasons = dict(zip(r.frames.tolist(), r.reasons))
    assert "dense_simulation" in reasons[BAD_DEPTH]
    assert "sparse_flow" in reasons[BAD_POSE]
    assert all(reasons[f] == "" for f in (0, 15, 20))


def test_the_last_frame_is_checked_too():
    """24 frames at interval 5: frame 23 lies 3 frames after frame 20, beyond its exclusion radius, so nobody
    judged it; now the last frame is checked, and a bad one is flagged."""
    n = 24
    sc = make_scene(n_frames=n)
    depth = sc.depth.clone()
    depth[n - 1] *= 1.2
    sim = sc.render(sc.cam_from_world)
    r = detect(sc, depth, sim, sc.cam_from_world)
    assert list(r.frames) == [0, 5, 10, 15, 20, n - 1]
    assert r.flagged_frames == [n - 1] and r.excluded_frames(2) == [n - 3, n - 2, n - 1]
    old = detect(sc, depth, sim, sc.cam_from_world, cfg={"check_last_frame": False})
    assert list(old.frames) == [0, 5, 10, 15, 20] and old.flagged_frames == [] and old.excluded_frames(2) == []


def test_neighbor_reduction_min_blames_only_the_bad_frame(scene):
    T = corrupt_pose(scene.cam_from_world, BAD_POSE, [0.04, 0.0, 0.02, 0.0, 0.04, 0.0])
    sim = scene.render(scene.cam_from_world)
    assert detect(scene, scene.depth, sim, T).flagged_frames == [BAD_POSE]
    # With "max" the good neighbours 5 and 15 are dragged in through their pair with frame 10.
    assert detect(scene, scene.depth, sim, T, cfg={"neighbor_reduction": "max"}).flagged_frames == [5, 10, 15]


def test_depth_consistency_on_simulated_depth_reacts_to_pose_error(scene):
    sim = scene.render(scene.cam_from_world)  # rendered at the true poses, checked at a wrong one
    clean = detect(scene, scene.depth, sim, scene.cam_from_world, rel_std=0.01)
    T = corrupt_pose(scene.cam_from_world, BAD_POSE, [0.0, 0.0, 0.2, 0.0, 0.0, 0.0])  # 20 % along the axis
    bad = detect(scene, scene.depth, sim, T, rel_std=0.01)
    k = list(bad.frames).index(BAD_POSE)
    assert clean.metrics["depth_consistency"][k] < 0 < 2.0 < bad.metrics["depth_consistency"][k]
    assert "depth_consistency" in bad.reasons[k]
    # A depth error does not change simulated depth: only the "network" source sees it in this metric.
    depth = scene.depth.clone()
    depth[BAD_DEPTH] *= 1.3
    kd = list(bad.frames).index(BAD_DEPTH)
    sim_src = detect(scene, depth, sim, scene.cam_from_world, rel_std=0.01)
    net_src = detect(scene, depth, sim, scene.cam_from_world, rel_std=0.01, cfg={"depth_consistency_source": "network"})
    assert sim_src.metrics["depth_consistency"][kd] == pytest.approx(clean.metrics["depth_consistency"][kd], abs=0.2)
    assert net_src.metrics["depth_consistency"][kd] > 2.0


def test_a_neighbour_without_simulated_depth_does_not_hide_a_failure(scene):
    # A pair without overlap used to score 0 (not NaN), and the min over neighbours took it.
    sim = scene.render(scene.cam_from_world)
    T = corrupt_pose(scene.cam_from_world, BAD_POSE, [0.0, 0.0, 0.2, 0.0, 0.0, 0.0])
    sim_empty = sim.clone()
    sim_empty[BAD_POSE + 5] = 0.0
    with_all = detect(scene, scene.depth, sim, T, rel_std=0.01)
    one_empty = detect(scene, scene.depth, sim_empty, T, rel_std=0.01)
    k = list(with_all.frames).index(BAD_POSE)
    assert list(one_empty.frames) == list(with_all.frames)
    assert one_empty.metrics["depth_consistency"][k] > 2.0
    assert one_empty.metrics["depth_consistency"][k] == pytest.approx(with_all.metrics["depth_consistency"][k], rel=0.2)
    assert BAD_POSE in one_empty.flagged_frames


def test_metrics_are_scale_invariant_with_normalisation(scene):
    s = 50.0  # e.g. millimetres instead of normalised SfM units
    T = corrupt_pose(scene.cam_from_world, BAD_POSE, [0.04, 0.0, 0.02, 0.0, 0.04, 0.0])
    sim = scene.render(scene.cam_from_world)
    Ts = T.clone()
    Ts[:, :3, 3] *= s
    ref = detect(scene, scene.depth, sim, T, noise_px=0.0)
    scaled = detect(scene, s * scene.depth, s * sim, Ts, noise_px=0.0)
    raw = detect(scene, s * scene.depth, s * sim, Ts, cfg={"normalize_depth": False}, noise_px=0.0)
    assert scaled.depth_scale == pytest.approx(s * ref.depth_scale)
    for m in METRICS:
        np.testing.assert_allclose(scaled.metrics[m], ref.metrics[m], rtol=1e-6, atol=1e-6)
    # Without normalisation the depth NLLs shift by log(s / median) (NLL(s·d, s·σ) = NLL(d, σ) + log s).
    np.testing.assert_allclose(
        raw.metrics["dense_simulation"], ref.metrics["dense_simulation"] + math.log(scaled.depth_scale), atol=1e-4
    )  # (not exact: eps = 1e-8 is added to σ², whose size changes with the scale)


def test_unregistered_frame_is_flagged_and_skipped_as_neighbour(scene):
    T = scene.cam_from_world.clone()
    T[BAD_POSE] = float("nan")
    sim = scene.render(scene.cam_from_world)
    r = detect(scene, scene.depth, sim, T)
    assert r.flagged_frames == [BAD_POSE]
    k = list(r.frames).index(BAD_POSE)
    assert r.reasons[k] == "unregistered" and all(np.isnan(r.metrics[m][k]) for m in METRICS)
    # Frame 5 and 15 still have their other neighbour.
    assert np.isfinite(r.metrics["sparse_flow"][[1, 3]]).all()


def test_bad_input(scene):
    sim = scene.render(scene.cam_from_world)
    with pytest.raises(ValueError, match="sim_depth"):
        detect_failures(scene.depth, scene.depth, sim[:, :, :10], sim > 0, scene.K, scene.cam_from_world,
                        scene.mask, flow_fn(scene), {})
    with pytest.raises(ValueError, match="depth_consistency_source"):
        detect(scene, scene.depth, sim, scene.cam_from_world, cfg={"depth_consistency_source": "mesh"})
    with pytest.raises(ValueError, match="interval"):
        detect(scene, scene.depth, sim, scene.cam_from_world, cfg={"interval": 0})


def _report(flagged_frames, n=40, interval=5):
    frames = np.arange(0, n, interval)
    flagged = np.isin(frames, flagged_frames)
    metrics = {m: np.where(flagged, 3.0, -1.0) for m in METRICS}
    exceeded = {m: flagged.copy() if m == "sparse_flow" else np.zeros_like(flagged) for m in METRICS}
    reasons = ["sparse_flow" if f else "" for f in flagged]
    return FailureReport(frames, metrics, exceeded, flagged, reasons, interval=interval, n_frames=n)


def test_ranges_and_repeats():
    r = _report([5, 10, 25, 35])
    assert r.flagged_ranges() == [(5, 10), (25, 25), (35, 35)]
    assert r.flagged_ranges(min_gap=10) == [(5, 10), (25, 35)]
    assert r.flagged_ranges(pad=3) == [(2, 13), (22, 28), (32, 38)]
    assert r.excluded_frames() == [3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 23, 24, 25, 26, 27, 33, 34, 35, 36, 37]
    assert r.excluded_frames(radius=0) == [5, 10, 25, 35]
    prev = _report([10, 15, 30])
    assert r.repeat_ranges(prev) == [(5, 10)]
    assert r.repeat_ranges(_report([])) == []


def test_csv_roundtrip_and_stage(tmp_path, scene):
    r = _report([5, 10, 25])
    path = r.to_csv(tmp_path / "failures.csv")
    header = path.read_text().splitlines()[0]
    assert header == "frame,dense_simulation,sparse_flow,depth_consistency,flagged,reason"
    back = FailureReport.read_csv(path)
    assert back.flagged_frames == [5, 10, 25]
    np.testing.assert_allclose(back.metrics["sparse_flow"], r.metrics["sparse_flow"])
    assert (back.exceeded["sparse_flow"] == r.exceeded["sparse_flow"]).all()
    assert "3/8 checked frames flagged" in r.summary()
    with pytest.raises(InputError, match="missing"):
        FailureReport.read_csv(tmp_path / "nope.csv")
    (tmp_path / "bad.csv").write_text("a,b\n1,2\n")
    with pytest.raises(InputError, match="not a failure report"):
        FailureReport.read_csv(tmp_path / "bad.csv")
    (tmp_path / "short.csv").write_text("frame,dense_simulation,sparse_flow,depth_consistency,flagged,reason\n"
                                        "0,1,2,3,0,\n5,1,2,3,1\n")  # a row without its reason: AttributeError
    with pytest.raises(InputError, match="not a failure report"):
        FailureReport.read_csv(tmp_path / "short.csv")
    # Stage: writes failures.csv, then skips the complete output.
    sim = scene.render(scene.cam_from_world)
    out = run({}, scene.depth, 0.05 * scene.depth, sim, sim > 0, scene.K, scene.cam_from_world, scene.mask,
              flow_fn(scene), tmp_path / "it0")
    assert FailureReport.read_csv(out).flagged_frames == []
    mtime = out.stat().st_mtime_ns
    assert run({}, None, None, None, None, None, None, None, None, tmp_path / "it0") == out
    assert out.stat().st_mtime_ns == mtime

# Tests that a mutation of the code survived before (a review ran single-point mutations of this package):
# each fails under its mutation and passes on the code.


def test_configured_thresholds_are_used_and_strict(scene):
    sim = scene.render(scene.cam_from_world)
    base = detect(scene, scene.depth, sim, scene.cam_from_world)
    assert base.flagged_frames == []
    low = detect(scene, scene.depth, sim, scene.cam_from_world, cfg={"thresholds": {"dense_simulation": -1e9}})
    assert low.flagged_frames == [0, 5, 10, 15, 20] and all(r == "dense_simulation" for r in low.reasons)
    v = float(base.metrics["dense_simulation"][2])
    eq = detect(scene, scene.depth, sim, scene.cam_from_world, cfg={"thresholds": {"dense_simulation": v}})
    assert not eq.exceeded["dense_simulation"][2]  # equal to the threshold: not over

def test_nan_metric_does_not_flag(scene):
    sim = scene.render(scene.cam_from_world)
    sim[15] = 0.0
    r = detect(scene, scene.depth, sim, scene.cam_from_world)
    k = list(r.frames).index(15)
    assert np.isnan(r.metrics["dense_simulation"][k])
    assert r.flagged_frames == []

def test_dense_metric_ignores_zero_sim_depth_even_if_marked_valid(scene):
    sim = scene.render(scene.cam_from_world)
    sim[10, :, :10] = 0.0
    ref = detect_failures(scene.depth, 0.05 * scene.depth, sim, sim > 0, scene.K, scene.cam_from_world, scene.mask, flow_fn(scene), {})
    allv = detect_failures(scene.depth, 0.05 * scene.depth, sim, torch.ones_like(sim, dtype=torch.bool), scene.K, scene.cam_from_world, scene.mask, flow_fn(scene), {})
    np.testing.assert_allclose(allv.metrics["dense_simulation"], ref.metrics["dense_simulation"])

def test_tracks_outside_the_mask_are_ignored(scene):
    sim = scene.render(scene.cam_from_world)
    def junk(i, j):
        f, v = scene.sparse_flow_fn(i, j, noise_px=0.0)
        f = torch.where(scene.mask, f, torch.full_like(f, 1e3))
        return f, v | ~scene.mask
    ref = detect(scene, scene.depth, sim, scene.cam_from_world, noise_px=0.0)
    got = detect_failures(scene.depth, 0.05 * scene.depth, sim, sim > 0, scene.K, scene.cam_from_world, scene.mask, junk, {})
    np.testing.assert_allclose(got.metrics["sparse_flow"], ref.metrics["sparse_flow"])

def test_ranges_are_clipped_to_the_sequence_and_even_interval_exclusion():
    assert _report([35], n=40).flagged_ranges(pad=10) == [(25, 39)]
    assert _report([4], n=12, interval=4).excluded_frames() == [2, 3, 4, 5, 6]


# Hysteresis (failure.low_thresholds): the edge of a failed stretch is flagged at a lower threshold.

def _stretch(scene, moderate, bad=(15, 20), moderate_scale=1.05):
    """Network depth 20 % off on the `bad` frames (a failed stretch at the end) and 5 % off on `moderate`."""
    depth = scene.depth.clone()
    for f in bad:
        depth[f] *= 1.2
    for f in moderate:
        depth[f] *= moderate_scale
    return depth


def test_hysteresis_flags_the_edge_of_a_failed_stretch_only(scene):
    sim = scene.render(scene.cam_from_world)
    depth = _stretch(scene, moderate=(0, 10))  # 0: moderate but alone; 10: moderate next to the failed 15
    off = detect(scene, depth, sim, scene.cam_from_world, cfg={"low_thresholds": None})
    assert off.flagged_frames == [15, 20] and off.low_flagged_frames == []
    ds = dict(zip(off.frames.tolist(), off.metrics["dense_simulation"]))
    assert ds[5] < ds[0] < 2.0 and ds[5] < ds[10] < 2.0  # the moderate ones are under the threshold
    low = min(ds[0], ds[10]) - 0.01  # over it: both moderate frames; under it: the clean ones
    on = detect(scene, depth, sim, scene.cam_from_world, cfg={"low_thresholds": {"dense_simulation": low}})
    assert on.flagged_frames == [10, 15, 20]  # frame 0 is over the low threshold but has no flagged neighbour
    assert on.low_flagged_frames == [10]
    reasons = dict(zip(on.frames.tolist(), on.reasons))
    assert reasons[10] == "low:dense_simulation" and reasons[0] == "" and reasons[15] == "dense_simulation"
    assert not on.exceeded["dense_simulation"][2]  # `exceeded` stays "over the threshold itself"
    assert "1 of them at a low threshold next to a flagged frame (10)" in on.summary()
    # A run of frames over the low threshold joins the failure through each other: 5 makes 0 a neighbour.
    chain = detect(scene, _stretch(scene, moderate=(0, 5, 10)), sim, scene.cam_from_world,
                   cfg={"low_thresholds": {"dense_simulation": low}})
    assert chain.flagged_frames == [0, 5, 10, 15, 20] and chain.low_flagged_frames == [0, 5, 10]
    # A metric without a low threshold (null, or left out) has no hysteresis; the default (no key) is none either.
    assert detect(scene, depth, sim, scene.cam_from_world,
                  cfg={"low_thresholds": {"dense_simulation": None}}).flagged_frames == [15, 20]
    other = detect(scene, depth, sim, scene.cam_from_world, cfg={"low_thresholds": {"depth_consistency": -1e9}})
    assert other.flagged_frames == [0, 5, 10, 15, 20]  # every frame is over that one: the failure spreads to all
    assert set(other.reasons[:3]) == {"low:depth_consistency"}
    assert detect(scene, depth, sim, scene.cam_from_world, cfg={}).flagged_frames == [15, 20]
    # Without a flagged frame nothing is flagged at the low threshold.
    clean = detect(scene, _stretch(scene, moderate=(0, 10), bad=()), sim, scene.cam_from_world,
                   cfg={"low_thresholds": {"dense_simulation": low}})
    assert clean.flagged_frames == []


def test_hysteresis_flags_survive_the_csv(tmp_path):
    r = _report([5, 10])
    r.reasons[1] = "low:dense_simulation"
    back = FailureReport.read_csv(r.to_csv(tmp_path / "failures.csv"))
    assert back.flagged_frames == [5, 10] and back.low_flagged_frames == [5]
    assert not back.exceeded["dense_simulation"][1]


@pytest.mark.parametrize("low, match", [
    ({"dense_simulation": 2.5}, "no higher than failure.thresholds.dense_simulation"),
    ({"dense_simulation": "x"}, "must be a number"),
    ({"dense_simulation": True}, "must be a number"),
    ({"dense_simulation": float("nan")}, "must be a number"),
    ({"photometric": 1.0}, "unknown metric"),
    (1.0, "must be a mapping"),
])
def test_bad_low_thresholds_are_clear_errors(low, match):
    from endorecon.failure import check_low_thresholds

    with pytest.raises(InputError, match=match):
        check_low_thresholds(low)
    assert check_low_thresholds(None) == {}
    assert check_low_thresholds({"dense_simulation": None, "sparse_flow": 0.1}) == {"sparse_flow": 0.1}
    # compared with the configured threshold, not the default
    assert check_low_thresholds({"dense_simulation": 2.5}, {"dense_simulation": 3.0}) == {"dense_simulation": 2.5}
