"""Mutation guards for the train task's settings check, iteration skipping and resume (endorecon/tasks/train.py).

Helpers come from test_train.py."""

import json
import types

import numpy as np
import pytest
from omegaconf import OmegaConf

from endorecon.utils.errors import InputError

from test_train import _four_frame_sequence, _previous_iteration, train_cfg


def _record(cfg, it=0):
    from endorecon.tasks.train import iteration_dir

    path = iteration_dir(cfg, it) / ".hydra" / "config.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(OmegaConf.to_yaml(cfg))
    return path


@pytest.mark.parametrize("key, value", [("seed", 7), ("model.net.growth_rate", 12),
                                        ("trainer.gradient_clip_val", 0.25), ("pgo.iterations", 3),
                                        ("bootstrap.epochs_per_iteration", 9)])
def test_every_result_making_group_is_compared(tmp_path, key, value):
    """The seed, the network, the trainer and the PGO make an iteration's results as much as the data and
    loss do: an iteration recorded with another value must not be skipped as this configuration's."""
    from endorecon.tasks.train import check_same_settings, config_differences

    cfg = train_cfg(tmp_path, "fold=0", "iteration=1")
    rec = _record(cfg)
    other = cfg.copy()
    OmegaConf.update(other, key, value, merge=False)
    assert config_differences(OmegaConf.load(rec), other) == [f"{key}: {OmegaConf.select(cfg, key)!r} -> {value!r}"]
    with pytest.raises(InputError, match="made with other settings"):
        check_same_settings(other)


def test_a_group_missing_from_an_old_record_does_not_hide_the_later_groups(tmp_path):
    from endorecon.tasks.train import config_differences

    cfg = train_cfg(tmp_path, "fold=0", "iteration=1")
    recorded = OmegaConf.load(_record(cfg))
    del recorded["failure"]  # a group an older version did not record
    other = cfg.copy()
    other.seed = int(cfg.seed) + 1
    assert config_differences(recorded, other) == [f"seed: {cfg.seed} -> {cfg.seed + 1}"]


def test_the_requested_iteration_itself_is_checked(tmp_path):
    """iteration=0 over a complete iteration 0 made with other settings: refused, not reported as this one's."""
    from endorecon.tasks.train import check_same_settings

    cfg = train_cfg(tmp_path, "fold=0", "iteration=0")
    _record(cfg)
    other = train_cfg(tmp_path, "fold=0", "iteration=0", f"data.height={cfg.data.height + 16}")
    with pytest.raises(InputError, match="iteration 0 of fold 0 was made with other settings"):
        check_same_settings(other)


def _fake_run(monkeypatch, tmp_path, *overrides, complete=()):
    """train.run with the data, SfM and iterations replaced: returns the (iteration, resume) calls."""
    from endorecon.tasks import pipeline, train

    cfg = train_cfg(tmp_path, "fold=0", *overrides)
    for it in complete:
        d = train.iteration_dir(cfg, it)
        d.mkdir(parents=True)
        (d / "metrics.json").write_text(json.dumps({"evaluation": {"mean_mm": 1.0}}))
    monkeypatch.setattr(train, "check_same_settings", lambda cfg: None)
    monkeypatch.setattr(pipeline, "load_sequences",
                        lambda cfg: types.SimpleNamespace(patients_with_ct=[0, 1], sequences=[], root=tmp_path))
    monkeypatch.setattr(pipeline, "check_fold", lambda fold, patients: None)
    monkeypatch.setattr(pipeline, "run_sfm", lambda cfg, seqs, root: [])
    calls = []

    def fake_iteration(cfg, it, sfm_seqs, info, resume=True):
        calls.append((it, resume))
        return {"evaluation": {"mean_mm": 2.0}}

    monkeypatch.setattr(train, "run_iteration", fake_iteration)
    return cfg, calls


def test_complete_iterations_are_skipped_and_the_first_missing_one_alone_resumes(tmp_path, monkeypatch):
    from endorecon.tasks import train

    cfg, calls = _fake_run(monkeypatch, tmp_path, "iteration=3", "ckpt_path=/x/last.ckpt", complete=(0,))
    assert train.run(cfg) == 2.0
    assert calls == [(1, True), (2, False), (3, False)]


def test_a_missing_earlier_iteration_stops_without_run_missing(tmp_path, monkeypatch):
    from endorecon.tasks import train

    cfg, calls = _fake_run(monkeypatch, tmp_path, "iteration=2", "bootstrap.run_missing=false", complete=(0,))
    with pytest.raises(InputError, match="iteration 2 needs iteration 1, which is missing") as e:
        train.run(cfg)
    assert calls == [] and "iteration=1" in e.value.fix


def test_fixed_frame_replaced_by_an_sfm_rerun_is_not_refused(tmp_path):
    """A summary from before the points' digest, whose first registered frame the SfM rerun of repeated
    failures replaced: the fixed frame moved legitimately, so it cannot tell; the poses are used."""
    from endorecon.tasks.train import prepare_sequences

    cfg = OmegaConf.create({"data": {"height": 64, "width": 80}, "paths": {"cache_dir": str(tmp_path / "cache")}})
    seq = _four_frame_sequence(tmp_path)
    prev = _previous_iteration(tmp_path, seq, record_fingerprint=False, resfm={"replaced_frames": [0]})
    other = _four_frame_sequence(tmp_path, rot_deg=5.0)
    prep = prepare_sequences(cfg, [other], prev)[0]
    assert np.allclose(prep.seq.cam_from_world[1:, :3, 3], seq.cam_from_world[1:, :3, 3] + 1e-3)
