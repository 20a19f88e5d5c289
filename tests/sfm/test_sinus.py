"""SfM on the real sinus_example clip (35 frames, 1080p -> 960x540) against its shipped SfM solution."""

from pathlib import Path

import pytest
from omegaconf import OmegaConf

from endorecon.sfm import stage
from endorecon.sfm.metrics import trajectory_error

ROOT = Path(__file__).resolve().parents[2]
SINUS = ROOT.parent / "shared" / "data" / "sinus_example"


@pytest.mark.slow
def test_sinus_example_all_registered_and_motion_agrees(tmp_path):
    if not SINUS.is_dir():
        pytest.skip(f"{SINUS} not available")
    from endorecon.data.original import load_original

    ref = load_original(SINUS)
    cfg = OmegaConf.load(ROOT / "conf" / "sfm" / "default.yaml")
    # Unseeded, a run now and then lands in a poorer solution here (centre error 0.026 instead of 0.007-0.010:
    # 1 of 106 runs on the dev machine, and stop 43's CI run): the test pins COLMAP's random numbers and threads
    # so that it measures one repeatable run.
    cfg.num_threads = 1
    cfg.seed = 0
    res = stage.load_result(stage.run(cfg, ref, tmp_path / "sfm"))
    assert res.registered.all()
    err = trajectory_error(res.cam_from_world, ref.cam_from_world)
    assert err["center_rmse_rel"] < 0.02, err
    assert err["rel_rotation_deg"] < 0.5, err
