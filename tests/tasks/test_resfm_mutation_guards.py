"""Tests that mutations of endorecon/tasks/resfm.py survived before (a review ran single-point mutations): each fails under its mutation."""

import numpy as np

from endorecon.tasks import resfm
from test_resfm import corrupt, fake_rerun, gt_poses, make_cfg, make_report, make_seq  # noqa: F401 (fixture)


def test_frames_excluded_around_another_flagged_frame_are_not_anchors(tmp_path, fake_rerun):
    gt = gt_poses()
    fake_rerun.gt = gt
    cur = corrupt(gt, [13, 14, 15, 16, 17, 23, 24, 25, 26, 27])
    seq = make_seq(tmp_path, cur)
    # pad 8: segment 7..23; frame 25 (flagged now, not before) excludes 23..27, so 23 is no anchor
    new, info = resfm.rerun_repeated_failures(make_cfg(pad=8), seq, make_report([15, 25]), make_report([15]), cur,
                                              tmp_path)
    rec = info["ranges"][0]
    assert rec["segment"] == [7, 23]
    assert rec["anchors"] == [7, 8, 9, 10, 11, 12, 18, 19, 20, 21, 22]
    np.testing.assert_allclose(new[13:18], gt[13:18], atol=1e-6)


def test_exactly_min_anchor_frames_are_enough(tmp_path, fake_rerun):
    gt = gt_poses()
    fake_rerun.gt = gt
    cur = corrupt(gt, range(13, 18))
    new, info = resfm.rerun_repeated_failures(make_cfg(pad=4, min_anchor_frames=4), make_seq(tmp_path, cur),
                                              make_report([15]), make_report([15]), cur, tmp_path)
    rec = info["ranges"][0]
    assert rec["anchors"] == [11, 12, 18, 19] and rec["status"] == "replaced"
    np.testing.assert_allclose(new[13:18], gt[13:18], atol=1e-6)


def test_a_rerun_that_was_not_run_does_not_count_as_an_attempt(tmp_path, fake_rerun):
    gt = gt_poses()
    fake_rerun.gt = gt
    history = [{"ranges": [{"range": [14, 16], "status": "not_run"}]}]
    resfm.rerun_repeated_failures(make_cfg(), make_seq(tmp_path, gt), make_report([15]), make_report([15]), gt,
                                  tmp_path, history=history)
    assert fake_rerun.calls[-1]["attempt"] == 1
