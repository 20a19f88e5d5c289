"""Tests that mutations of endorecon/tasks/pipeline.py (depth evaluation) survived before (a review ran single-point mutations): each fails under its mutation."""

import types

import numpy as np
import torch


def _patch_gt(monkeypatch, gt):
    import endorecon.data.dataset as dataset

    monkeypatch.setattr(dataset, "load_ground_truth", lambda root, p, name: types.SimpleNamespace(depth_mm=gt))


def test_depth_evaluation_keeps_only_pixels_whose_whole_gt_footprint_is_valid(monkeypatch):
    from endorecon.tasks import pipeline

    gt = np.full((1, 16, 16), 50.0, np.float32)
    gt[0, 0, 0] = 0.0  # one missing GT pixel: the 8x8 pixel covering it has a diluted (37.5) area average
    _patch_gt(monkeypatch, gt)
    seq = types.SimpleNamespace(patient=0, name="patient_00/seq_00", mask=np.ones((8, 8), bool))
    depth = torch.full((1, 1, 8, 8), 50.0) + 0.01 * torch.arange(64.0).reshape(1, 1, 8, 8)
    out = pipeline.evaluate_depth(None, seq, depth, torch.rand(1, 1, 8, 8) + 0.1)[0]
    assert out["n_pixels"] == 63 and out["abs_rel"] < 0.01


def test_depth_evaluation_with_cap_returns_uncapped_then_capped(monkeypatch):
    from endorecon.tasks import pipeline

    gt = np.full((1, 8, 8), 30.0, np.float32)
    gt[0, :, 4:] = 60.0  # half the pixels beyond a 40 mm cap
    _patch_gt(monkeypatch, gt)
    seq = types.SimpleNamespace(patient=0, name="patient_00/seq_00", mask=np.ones((8, 8), bool))
    depth = torch.from_numpy(gt)[:, None] * (1 + 0.01 * torch.rand(1, 1, 8, 8, generator=torch.Generator().manual_seed(0)))
    uncapped, capped = pipeline.evaluate_depth_with_cap(None, seq, depth, torch.rand(1, 1, 8, 8) + 0.1, 40.0)
    assert uncapped["n_pixels"] == 64 and capped["n_pixels"] == 32


def test_refine_sequence_redoes_a_summary_that_other_weights_made(tmp_path, monkeypatch):
    """refine_sequence's own check of ``made_by`` (the end-of-iteration stage checks it too): a summary written
    for other weights is not returned as done; one for these weights is."""
    import json

    from endorecon.tasks import pipeline

    class Refining(Exception):
        pass

    def fuse(*a, **k):
        raise Refining

    monkeypatch.setattr(pipeline, "fuse_sequence", fuse)
    class Seq(types.SimpleNamespace):
        def __len__(self):
            return 3

    seq = Seq(name="p/s", cam_from_world=np.tile(np.eye(4), (3, 1, 1)))
    (tmp_path / "summary.json").write_text(json.dumps({"sequence": "p/s", "made_by": "aaaa"}))
    assert pipeline.refine_sequence(None, seq, None, None, None, None, None, tmp_path, made_by="aaaa")["made_by"] == "aaaa"
    assert pipeline.refine_sequence(None, seq, None, None, None, None, None, tmp_path)["made_by"] == "aaaa"
    import pytest

    with pytest.raises(Refining):
        pipeline.refine_sequence(types.SimpleNamespace(fusion=None), seq, None, None, None, None, None, tmp_path,
                                 made_by="bbbb")
