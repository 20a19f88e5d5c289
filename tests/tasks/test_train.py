"""The train task end to end: ``python train.py fold=0 iteration=1 debug=fast`` on CPU."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

from endorecon.utils.errors import InputError

ROOT = Path(__file__).resolve().parents[2]


def _compose(name, overrides):
    from hydra import compose, initialize_config_dir

    import endorecon.utils.resolvers  # noqa: F401

    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        return compose(config_name=name, overrides=overrides)


def train_cfg(root: Path, *extra: str):
    return _compose(
        "train",
        ["debug=fast", f"paths.root_dir={root}", f"paths.run_dir='{root}/outputs/train/fold=0'", *extra],
    )


@pytest.fixture(scope="session")
def debug_run(debug_root):
    from endorecon.tasks.train import run

    cfg = train_cfg(debug_root, "fold=0", "iteration=1")
    mean_mm = run(cfg)
    return debug_root / "outputs" / "train" / "fold=0", mean_mm


@pytest.mark.slow
def test_two_iterations_end_to_end(debug_run):
    fold_dir, mean_mm = debug_run
    for it in (0, 1):
        d = fold_dir / f"iteration={it}"
        for name in ("metrics.json", "mesh.ply", "poses.txt", "failures.csv", "checkpoints/last.ckpt",
                     ".hydra/config.yaml"):
            assert (d / name).is_file(), f"{d / name} missing"
        seq_dirs = sorted((d / "sequences").iterdir())
        assert len(seq_dirs) == 2  # both debug patients, the held-out one included
        for s in seq_dirs:
            z = np.load(s / "simulated_depth.npz")
            assert z["valid"].mean() > 0.2, f"{s}: simulated depth mostly invalid"
        assert any((d / "tensorboard").rglob("events.out.tfevents*"))
    m0 = json.loads((fold_dir / "iteration=0" / "metrics.json").read_text())
    m1 = json.loads((fold_dir / "iteration=1" / "metrics.json").read_text())
    # Iteration 0 has no simulated depth; iteration 1 trains with iteration 0's.
    assert m0["train"]["train/dense_simulation_active"] == 0.0
    assert m1["train"]["train/dense_simulation_active"] == 1.0
    assert m1["train"]["train/dense_simulation_weighted"] != 0.0
    summaries = list((fold_dir / "iteration=0" / "sequences").glob("*/summary.json"))
    assert summaries and all(json.loads(p.read_text())["sfm_fingerprint"] for p in summaries)  # checked by iteration 1
    for m in (m0, m1):
        assert all(np.isfinite(v) for v in m["train"].values() if v is not None), "non-finite training metric"
        assert m["train"]["train/skipped_batches"] == 0.0
    # The held-out patient's mesh against its CT, after Sim(3) registration: a loose bound for the tiny
    # debug schedule (4 batches of a 64x80 network); the default schedule is measured in the README.
    ev = m1["evaluation"]
    assert ev is not None and ev["n_points"] == 40000
    assert ev["mean_mm"] < 3.0, ev
    assert mean_mm == pytest.approx(ev["mean_mm"])
    # Depth of the held-out patient against GT depth (SCARED set, per-frame median scaling).
    de = m1["depth_evaluation"]
    assert 0 < de["abs_rel"] < 0.5 and 0 < de["a1"] <= 1 and de["n_frames"] == 20
    assert -1 <= de["std_error_spearman"] <= 1
    capped = m1["depth_evaluation_capped"]  # same metrics without GT deeper than bootstrap.depth_cap_mm
    assert 0 < capped["abs_rel"] < 0.5 and 0 < capped["n_pixels"] <= de["n_pixels"]
    # ... and which end of the depth range the error is at: every valid pixel in one band
    bins = de["by_relative_depth"]
    assert sum(b["n_pixels"] for b in bins) == de["n_pixels"] and sum(b["share"] for b in bins) == pytest.approx(1)
    assert all(b["log_error"] is None or np.isfinite(b["log_error"]) for b in bins) and bins[-1]["hi"] is None
    assert (fold_dir / "iteration=1" / "evaluation" / "depth_error_by_range.png").is_file()


@pytest.mark.slow
def test_a_complete_fold_reports_its_held_out_results_again(debug_run, caplog):
    """python train.py on a finished fold does no work but says again how the held-out patient did."""
    import logging

    from endorecon.tasks.train import run

    fold_dir, mean_mm = debug_run
    m1 = json.loads((fold_dir / "iteration=1" / "metrics.json").read_text())
    with caplog.at_level(logging.INFO, logger="endorecon"):
        assert run(train_cfg(fold_dir.parents[2], "fold=0", "iteration=1", "bootstrap.targets.max_mm=0.001")) == mean_mm
    text = caplog.text
    assert "all iterations up to 1 of fold 0 are complete" in text
    assert f"AbsRel {m1['depth_evaluation']['abs_rel']:.3f}" in text and f"{m1['evaluation']['max_mm']:.3f} mm" in text
    assert "by depth / frame median" in text
    assert "held-out patient 0 misses:" in text and "(target < 0.001)" in text  # the debug mesh is not that good


@pytest.mark.slow
def test_iteration_whose_end_stage_stopped_resumes_from_last(debug_root, tmp_path, monkeypatch):
    """The end-of-iteration stage (fusion, failure detection, PGO) stops after the last epoch's last.ckpt was
    saved: ``ckpt_path=last`` must make that stage, not tell the user to resume with ckpt_path=last again
    (Lightning restores a finished checkpoint and ends without on_train_end)."""
    from endorecon.callbacks import BootstrapCallback
    from endorecon.tasks.train import run

    real = BootstrapCallback.on_train_end
    calls = []

    def stops_once(self, trainer, module):
        calls.append(trainer.current_epoch)
        if len(calls) == 1:
            raise KeyboardInterrupt("stopped during fusion")
        return real(self, trainer, module)

    monkeypatch.setattr(BootstrapCallback, "on_train_end", stops_once)
    run_dir = f"paths.run_dir='{tmp_path}/fold=0'"
    cfg = train_cfg(debug_root, "fold=0", "iteration=0", run_dir)
    with pytest.raises((KeyboardInterrupt, SystemExit, InputError)):
        run(cfg)
    it0 = tmp_path / "fold=0" / "iteration=0"
    assert (it0 / "checkpoints" / "last.ckpt").is_file() and not (it0 / "metrics.json").exists()
    assert run(train_cfg(debug_root, "fold=0", "iteration=0", run_dir, "ckpt_path=last")) is not None
    assert (it0 / "metrics.json").is_file() and len(calls) == 2


def test_iteration_without_a_logger(tmp_path, monkeypatch):
    """logger=none: the default callbacks' learning-rate monitor made Lightning refuse to train (after SfM and
    the data preparation); the iteration must run (tiny module and data, no sequences)."""
    import importlib
    import types

    sys.path.insert(0, str(Path(__file__).parent))
    run_script = importlib.import_module("ddp_iterations_run")
    import endorecon.data.datamodule as datamodule
    import endorecon.module as module
    import endorecon.tasks.train as train

    monkeypatch.setattr(datamodule, "EndoDataModule", run_script.TinyData)
    monkeypatch.setattr(module, "DepthModule", run_script.TinyModule)
    monkeypatch.setattr(train, "prepare_sequences", lambda cfg, seqs, prev: [])
    cfg = _compose("train", ["logger=none", "bootstrap.epochs_per_iteration=1", "callbacks.progress_bar=null",
                             f"paths.root_dir={tmp_path}", f"paths.run_dir='{tmp_path}/run'"])
    assert cfg.callbacks.lr_monitor is not None
    metrics = train.run_iteration(cfg, 0, [], types.SimpleNamespace(root=tmp_path, patients_with_ct=[0]))
    assert (tmp_path / "run" / "iteration=0" / "metrics.json").is_file() and metrics["iteration"] == "iteration=0"


@pytest.mark.slow
def test_iterations_under_ddp_finish_on_every_rank(tmp_path):
    """trainer=ddp: the end-of-iteration stage runs on rank 0 alone; the other ranks must take its metrics, not
    stop with "iteration 0 did not finish" (which then broke rank 0's next iteration)."""
    import os

    script = Path(__file__).with_name("ddp_iterations_run.py")
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    run = subprocess.run([sys.executable, str(script), str(tmp_path)], capture_output=True, text=True, timeout=600,
                         env=env, cwd=tmp_path)
    import re

    done = sorted(re.findall(r"RANK \d+ iteration \d+ done", run.stdout))  # the ranks' lines can run together
    assert run.returncode == 0 and done == ["RANK 0 iteration 0 done", "RANK 0 iteration 1 done",
                                            "RANK 1 iteration 0 done", "RANK 1 iteration 1 done"], \
        run.stdout[-2000:] + run.stderr[-3000:]


@pytest.mark.slow
def test_last_checkpoint_is_the_network_the_iteration_evaluated(debug_run):
    """reconstruct.py, the next iteration's warm start and the results table load last.ckpt: it must hold
    the weights whose held-out depth metrics.json reports (Lightning >= 2.6's save_last could lag)."""
    from endorecon.tasks import pipeline
    from endorecon.tasks.reconstruct import load_module
    from endorecon.tasks.train import prepare_sequences

    fold_dir, _ = debug_run
    cfg = train_cfg(fold_dir.parents[2], "fold=0", "iteration=1")
    info = pipeline.load_sequences(cfg)
    sfm = pipeline.run_sfm(cfg, info.sequences, info.root)  # cached by the run
    for it in (0, 1):
        # the iteration's own inputs: poses refined by the previous one move the sparse depth maps, and the
        # local scaling (unlike a per-frame scale, which the median scaling of the metrics cancels) sees that
        prev = fold_dir / f"iteration={it - 1}" if it else None
        prep = [p for p in prepare_sequences(cfg, sfm, prev) if p.seq.patient == 0][0]
        module, _ = load_module(fold_dir / f"iteration={it}" / "checkpoints" / "last.ckpt")
        depth, std, _ = pipeline.infer_depth(module, prep.seq, prep.cache)
        got = pipeline.evaluate_depth(info.root, prep.seq, depth, std)[0]
        recorded = json.loads((fold_dir / f"iteration={it}" / "metrics.json").read_text())["depth_evaluation"]
        assert got["abs_rel"] == pytest.approx(recorded["abs_rel"], rel=1e-5), it


@pytest.mark.slow
def test_results_table_of_the_debug_fold(debug_run, tmp_path):
    """benchmarks/paper_table.py's per-fold work on the debug run: every variant, the adapted one included."""
    from endorecon.tasks import ablation

    fold_dir, _ = debug_run
    cfg = train_cfg(fold_dir.parents[2], "fold=0", "iteration=1")
    rows = ablation.run_fold(cfg, fold_dir, tmp_path / "fold=0")
    assert [r["variant"] for r in rows] == ["full", "iteration0", "plain_fusion", "no_failure_pgo", "adapted",
                                           "gt_upper_bound"]
    for r in rows:
        assert r["patient"] == 0 and r["mean_mm"] is not None and 0 <= r["mean_mm"] <= r["max_mm"], r
    by = {r["variant"]: r for r in rows}
    assert by["gt_upper_bound"]["mean_mm"] < 0.2  # GT depth at GT poses fuses almost exactly
    assert by["gt_upper_bound"]["abs_rel"] is None and 0 < by["adapted"]["abs_rel"] < 1
    # The adaptive fusion's meshes carry a std, so the table says how well it ranks their residuals.
    for v in ("full", "iteration0", "no_failure_pgo", "adapted"):
        assert -1 <= by[v]["std_residual_spearman"] <= 1, by[v]
    a = json.loads((tmp_path / "fold=0" / "adapted" / "patient_00__seq_00" / "adaptation" / "adapt.json").read_text())
    assert a["steps"] == 2 and np.isfinite(a["loss_before"])  # debug: 1 epoch x 2 batches
    csv_path, md_path = ablation.write_table(rows, tmp_path)
    md = md_path.read_text()
    assert "| **mean** | adapted |" in md and "depth AbsRel" in md and "mesh std ρ" in md
    assert len(csv_path.read_text().splitlines()) == 1 + len(rows)


@pytest.mark.slow
def test_results_table_runs_again_the_last_stage_of_iterations_trained_with_other_settings(debug_run, tmp_path):
    """A fold trained before a fusion setting changed: its full / iteration0 rows are fused again from the
    iterations' networks with the current settings, marked in the table, and reused the next time."""
    from endorecon.tasks import ablation

    fold_dir, _ = debug_run
    cfg = train_cfg(fold_dir.parents[2], "fold=0", "iteration=1", "fusion.mask_erode_px=3", "adapt.enabled=false")
    rows = ablation.run_fold(cfg, fold_dir, tmp_path / "fold=0")
    by = {r["variant"]: r for r in rows}
    for v, it in (("full", 1), ("iteration0", 0)):
        assert by[v]["refused"] == ["fusion.mask_erode_px: 0 -> 3"], by[v]
        sdir = tmp_path / "fold=0" / v / f"iteration={it}" / "sequences" / "patient_00__seq_00"
        assert (sdir / "mesh.ply").is_file() and by[v]["mean_mm"] is not None
    # iteration 1's stage started from iteration 0's made again (its report where the SfM rerun looks back)
    assert (tmp_path / "fold=0" / "full" / "iteration=0" / "sequences" / "patient_00__seq_00" / "failures.csv").is_file()
    assert "refused" not in by["plain_fusion"]
    md = ablation.write_table(rows, tmp_path)[1].read_text()
    assert "| 0 | full* |" in md and "fusion.mask_erode_px: 0 -> 3" in md
    stamp = (tmp_path / "fold=0" / "full" / "iteration=1" / "sequences" / "patient_00__seq_00" / "summary.json").stat()
    again = {r["variant"]: r for r in ablation.run_fold(cfg, fold_dir, tmp_path / "fold=0")}
    assert again["full"]["mean_mm"] == pytest.approx(by["full"]["mean_mm"])
    assert (tmp_path / "fold=0" / "full" / "iteration=1" / "sequences" / "patient_00__seq_00" / "summary.json").stat().st_mtime_ns == stamp.st_mtime_ns


@pytest.mark.slow
def test_complete_iterations_are_skipped(debug_run, monkeypatch):
    from endorecon.tasks import train

    def boom(*a, **k):
        raise AssertionError("a complete iteration was run again")

    monkeypatch.setattr(train, "run_iteration", boom)
    fold_dir, mean_mm = debug_run
    before = (fold_dir / "iteration=1" / "metrics.json").stat().st_mtime
    assert train.run(train_cfg(fold_dir.parents[2], "fold=0", "iteration=1")) == pytest.approx(mean_mm)
    assert (fold_dir / "iteration=1" / "metrics.json").stat().st_mtime == before


@pytest.mark.slow
def test_missing_iteration_stops_with_command(debug_run):
    from endorecon.tasks.train import run

    fold_dir, _ = debug_run
    root = fold_dir.parents[2]
    cfg = _compose("train", ["debug=fast", f"paths.root_dir={root}", f"paths.run_dir='{root}/outputs/train/fold=1'",
                                "fold=1", "iteration=1", "bootstrap.run_missing=false"])
    with pytest.raises(InputError, match=r"python train.py fold=1 iteration=0"):
        run(cfg)


@pytest.mark.slow
def test_unknown_fold_is_a_clear_error(debug_run):
    from endorecon.tasks.train import run

    root = debug_run[0].parents[2]
    with pytest.raises(InputError, match=r"unknown fold 5.*\[0, 1\]"):
        run(train_cfg(root, "fold=5"))


@pytest.mark.parametrize("cap", ["0", "-5", "abc"])
def test_bad_depth_cap_is_a_clear_error_before_any_work(tmp_path, cap):
    from endorecon.tasks.train import run

    cfg = _compose("train", ["debug=fast", f"paths.root_dir={tmp_path}", f"bootstrap.depth_cap_mm={cap}"])
    with pytest.raises(InputError, match="depth_cap_mm"):
        run(cfg)
    assert not any(tmp_path.iterdir())  # nothing generated or trained


@pytest.mark.parametrize("override, match", [
    ("bootstrap.targets.max_mm=abc", "bootstrap.targets"), ("+bootstrap.targets.rmse=1", "bootstrap.targets"),
    ("failure.low_thresholds.dense_simulation=3", "failure.low_thresholds"),
    ("+failure.low_thresholds.x=1", "failure.low_thresholds"),
])
def test_bad_target_or_low_threshold_is_a_clear_error_before_any_work(tmp_path, override, match):
    from endorecon.tasks.train import run

    cfg = _compose("train", ["debug=fast", f"paths.root_dir={tmp_path}", override])
    with pytest.raises(InputError, match=match):
        run(cfg)
    assert not any(tmp_path.iterdir())


def test_held_out_report_names_each_missed_target(tmp_path):
    """The log lines an iteration ends with: the summary, the error by relative depth, one warning for misses."""
    import logging

    from endorecon.callbacks.bootstrap import held_out_report

    bins = [dict(lo=0.0, hi=0.5, share=0.2, n_pixels=2, log_error=0.05, abs_rel=0.05),
            dict(lo=0.5, hi=None, share=0.8, n_pixels=8, log_error=-0.43, abs_rel=0.35)]
    metrics = dict(iteration="iteration=2", fold=1, n_flagged=3,
                   depth_evaluation=dict(abs_rel=0.120, a1=0.836, std_error_spearman=0.65, by_relative_depth=bins),
                   evaluation=dict(mean_mm=0.910, median_mm=0.608, p95_mm=2.822, max_mm=5.575, frac_below_1mm=0.69))
    targets = dict(abs_rel=0.10, std_spearman=0.3, mean_mm=1.0, max_mm=1.5)
    lines = held_out_report(metrics, targets, tmp_path)
    assert [lvl for lvl, _ in lines] == [logging.INFO, logging.INFO, logging.WARNING]
    assert "AbsRel 0.120" in lines[0][1] and "5.575 mm" in lines[0][1] and "3 frame(s) flagged" in lines[0][1]
    assert "<0.5x +0.05 (20%) | >0.5x -0.43 (80%)" in lines[1][1]
    warn = lines[2][1]
    assert "depth AbsRel 0.120 (target <= 0.1)" in warn and "mesh max residual (mm) 5.575 (target < 1.5)" in warn
    assert "Spearman" not in warn and "mean residual" not in warn and "residual_heatmap.png" in warn
    # all met, or unchecked (null), or nothing evaluated: no warning
    assert len(held_out_report(metrics, dict(targets, abs_rel=0.2, max_mm=None), tmp_path)) == 2
    assert len(held_out_report(dict(metrics, depth_evaluation=None, evaluation=None), targets, tmp_path)) == 1
    # a NaN never passes
    nan = dict(metrics, evaluation=dict(metrics["evaluation"], mean_mm=float("nan")))
    assert "mesh mean residual (mm) nan" in held_out_report(nan, targets, tmp_path)[-1][1]


def test_cli_shows_composed_config():
    out = subprocess.run([sys.executable, "train.py", "fold=3", "iteration=2", "--cfg", "job"], cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "\nfold: 3\n" in out.stdout and "\niteration: 2\n" in out.stdout
    assert "c1: 0.1" in out.stdout and "c2: 0.8" in out.stdout
    assert "sparse_flow: 100.0" in out.stdout


def test_cli_bad_fold_exits_2_without_traceback(tmp_path):
    out = subprocess.run(
        [sys.executable, "train.py", "fold=abc", f"paths.root_dir={tmp_path}"], cwd=ROOT,
        capture_output=True, text=True, timeout=120,
    )
    assert out.returncode != 0
    assert "fold" in out.stderr


def test_every_config_group_composes():
    for overrides in (["experiment=paper"], ["experiment=cpu"], ["fusion=plain"], ["trainer=gpu"],
                      ["debug=fast"], ["logger=none"]):
        cfg = _compose("train", overrides)
        assert cfg.fusion.name in ("adaptive", "plain")
    cfg = _compose("train", ["experiment=paper"])
    assert cfg.bootstrap.epochs_per_iteration == 20 and cfg.data.height == 256 and cfg.iteration == 2
    # experiment=cpu spells the default schedule out: it must not drift from train.yaml's defaults
    default, cpu = _compose("train", []), _compose("train", ["experiment=cpu"])
    for key in ("iteration", "bootstrap.epochs_per_iteration", "data.height", "data.width", "trainer.max_epochs"):
        assert OmegaConf.select(cpu, key) == OmegaConf.select(default, key), key


def _four_frame_sequence(tmp_path, rot_deg: float = 0.0, seed: int = 0):
    """Four frames looking down +z at 50 points; ``rot_deg`` turns the whole SfM world about y (another
    SfM run of the same video: same images, another world frame)."""
    from endorecon.data.sequence import Sequence

    rng = np.random.default_rng(seed)
    pts = np.c_[rng.uniform(-1, 1, (50, 2)), rng.uniform(4, 6, 50)]
    poses = np.tile(np.eye(4), (4, 1, 1))
    poses[:, 0, 3] = -0.1 * np.arange(4)
    a = np.radians(rot_deg)
    world_from_new = np.array([[np.cos(a), 0, np.sin(a), 0], [0, 1, 0, 0], [-np.sin(a), 0, np.cos(a), 0], [0, 0, 0, 1]])
    poses = poses @ world_from_new  # cam_from_new = cam_from_world @ world_from_new
    pts = (np.linalg.inv(world_from_new)[:3, :3] @ pts.T).T
    K = np.array([[40.0, 0, 39.5], [0, 40.0, 31.5], [0, 0, 1]])
    return Sequence(name="patient_00/seq_00", frame_paths=[tmp_path / f"{i:06d}.jpg" for i in range(4)],
                    intrinsics=K, height=64, width=80, mask=np.ones((64, 80), bool), cam_from_world=poses,
                    points_xyz=pts, visibility=[np.arange(4)] * 50, units="sfm", source="colmap", patient=0)


def _previous_iteration(tmp_path, seq, record_fingerprint: bool = True, **summary_keys) -> Path:
    """An iteration dir as refine_sequence leaves it for ``seq`` (poses nudged as dense PGO would, with the
    first frame fixed)."""
    from endorecon.data.sequence import sfm_fingerprint, write_poses_txt
    from endorecon.tasks import pipeline

    prev = tmp_path / "fold=0" / "iteration=0"
    sdir = prev / "sequences" / "patient_00__seq_00"
    sdir.mkdir(parents=True)
    refined = seq.cam_from_world.copy()
    refined[1:, :3, 3] += 1e-3
    write_poses_txt(sdir / "poses.txt", [p.name for p in seq.frame_paths], refined)
    pipeline.save_simulated(sdir / "simulated_depth.npz", np.zeros((4, 64, 80), np.float32), np.zeros((4, 64, 80), bool))
    summary = {"flagged": [], "resfm": {"replaced_frames": []}, **summary_keys}
    if record_fingerprint:
        summary["sfm_fingerprint"] = sfm_fingerprint(seq)
    (sdir / "summary.json").write_text(json.dumps(summary))
    return prev


@pytest.mark.parametrize("recorded", [True, False])
def test_poses_of_another_sfm_model_are_refused(tmp_path, recorded):
    """The next iteration projects the *current* SfM's points with the previous iteration's poses: poses
    refined from another SfM run of the video (another world frame) must stop it, naming the file, not
    train and fuse on garbage.  Runs from before the points' digest was recorded are checked by the frame
    that dense PGO holds fixed."""
    from omegaconf import OmegaConf

    from endorecon.tasks.train import prepare_sequences

    cfg = OmegaConf.create({"data": {"height": 64, "width": 80}, "paths": {"cache_dir": str(tmp_path / "cache")}})
    seq = _four_frame_sequence(tmp_path)
    prev = _previous_iteration(tmp_path, seq, record_fingerprint=recorded)
    prep = prepare_sequences(cfg, [seq], prev)[0]  # the model it was refined from: accepted
    assert np.allclose(prep.seq.cam_from_world[1:, :3, 3], seq.cam_from_world[1:, :3, 3] + 1e-3)
    assert prep.cache.depth_map(0)[1].sum() > 20  # the points project into the frame with those poses
    other = _four_frame_sequence(tmp_path, rot_deg=5.0)  # SfM ran again: the same scene in another frame
    with pytest.raises(InputError, match="another SfM model") as e:
        prepare_sequences(cfg, [other], prev)
    assert "poses.txt" in str(e.value) and "iteration=0" in str(e.value)


@pytest.mark.parametrize("keys, excluded", [({"flagged": [2], "excluded": [1, 2, 3]}, [1, 2, 3]),
                                            ({"flagged": [2]}, [2])])  # a summary from before "excluded"
def test_next_iteration_leaves_out_the_previous_exclusions(tmp_path, keys, excluded):
    from omegaconf import OmegaConf

    from endorecon.tasks.train import prepare_sequences

    cfg = OmegaConf.create({"data": {"height": 64, "width": 80}, "paths": {"cache_dir": str(tmp_path / "cache")}})
    seq = _four_frame_sequence(tmp_path)
    prep = prepare_sequences(cfg, [seq], _previous_iteration(tmp_path, seq, **keys))[0]
    assert np.flatnonzero(prep.excluded).tolist() == excluded


def test_iterations_made_with_other_settings_are_refused(tmp_path):
    """The fold's run dir does not encode the overrides: an iteration recorded with another resolution or loss
    weight must not be skipped (and its mesh reported) as this configuration's; settings that do not make the
    results (workers, targets, accelerator) and keys only one side has are not compared."""
    from endorecon.tasks.train import check_same_settings, config_differences, iteration_dir

    cfg = train_cfg(tmp_path, "fold=0", "iteration=1")
    it0 = iteration_dir(cfg, 0) / ".hydra" / "config.yaml"
    it0.parent.mkdir(parents=True)
    it0.write_text(OmegaConf.to_yaml(cfg))
    check_same_settings(cfg)  # the same settings: accepted
    harmless = train_cfg(tmp_path, "fold=0", "iteration=1", "data.num_workers=0", "bootstrap.targets.max_mm=0.5",
                         "trainer.accelerator=cpu", "pgo.progress=false", "paths.output_root=/elsewhere")
    assert config_differences(OmegaConf.load(it0), harmless) == []
    recorded = OmegaConf.load(it0)
    recorded.bootstrap.removed_key = 3  # a key this version no longer has
    del recorded.fusion.c1  # a key added since
    assert config_differences(recorded, cfg) == []
    other = train_cfg(tmp_path, "fold=0", "iteration=1", f"data.height={cfg.data.height + 16}", "loss.sparse_flow=1.0")
    assert config_differences(OmegaConf.load(it0), other) == [
        f"data.height: {cfg.data.height} -> {cfg.data.height + 16}", "loss.sparse_flow: 100.0 -> 1.0"]
    with pytest.raises(InputError, match="iteration 0 of fold 0 was made with other settings") as e:
        check_same_settings(other)
    assert "data.height" in str(e.value) and "loss.sparse_flow" in str(e.value) and str(it0) in str(e.value)
    it0.write_text("data: [unclosed")
    with pytest.raises(InputError, match="unreadable config"):
        check_same_settings(cfg)


def test_explicit_checkpoint_resumes_the_first_missing_iteration_only(tmp_path):
    from endorecon.tasks.train import resume_checkpoint

    it1, it2 = tmp_path / "iteration=1", tmp_path / "iteration=2"
    given = train_cfg(tmp_path, "ckpt_path=/x/last.ckpt")
    assert resume_checkpoint(given, it1, resume=True) == "/x/last.ckpt"
    assert resume_checkpoint(given, it2, resume=False) is None  # trained from its start, not skipped
    last = train_cfg(tmp_path, "ckpt_path=last")
    assert resume_checkpoint(last, it1, resume=False) is None
    (it1 / "checkpoints").mkdir(parents=True)
    (it1 / "checkpoints" / "last.ckpt").write_bytes(b"x")
    assert resume_checkpoint(last, it1, resume=False) == str(it1 / "checkpoints" / "last.ckpt")
    assert resume_checkpoint(train_cfg(tmp_path), it1, resume=True) is None


def test_missing_iteration_command_keeps_the_users_overrides(monkeypatch):
    import types

    from hydra.core.hydra_config import HydraConfig

    from endorecon.tasks.train import _command_for_iteration

    task = ["debug=fast", "iteration=2", "bootstrap.run_missing=false", "paths.output_root=/tmp/o", "fold=1"]
    monkeypatch.setattr(HydraConfig, "get", staticmethod(
        lambda: types.SimpleNamespace(overrides=types.SimpleNamespace(task=task))))
    assert _command_for_iteration(OmegaConf.create({"fold": 1}), 1) == \
        "python train.py debug=fast paths.output_root=/tmp/o fold=1 iteration=1"


@pytest.mark.parametrize("damage", ["truncated", "missing", "not_an_object"])
def test_damaged_summary_of_previous_iteration_names_the_file(tmp_path, damage):
    """A previous iteration's summary.json that is cut short, gone or not a JSON object stops the next
    iteration with an InputError naming that file and the iteration dir to delete, not a bare JSONDecodeError,
    and leaves the file as it was."""
    from omegaconf import OmegaConf

    from endorecon.tasks.train import prepare_sequences

    cfg = OmegaConf.create({"data": {"height": 64, "width": 80}, "paths": {"cache_dir": str(tmp_path / "cache")}})
    seq = _four_frame_sequence(tmp_path)
    prev = _previous_iteration(tmp_path, seq)
    summary = prev / "sequences" / "patient_00__seq_00" / "summary.json"
    if damage == "truncated":
        summary.write_text(summary.read_text()[:10])
    elif damage == "missing":
        summary.unlink()
    else:
        summary.write_text("[1, 2]")
    before = summary.read_bytes() if summary.exists() else None
    with pytest.raises(InputError) as e:
        prepare_sequences(cfg, [seq], prev)
    msg = str(e.value)
    assert str(summary) in msg and f"delete {prev}" in msg
    assert (summary.read_bytes() if summary.exists() else None) == before


def test_read_json(tmp_path):
    from endorecon.utils.io import read_json

    p = tmp_path / "a.json"
    p.write_text('{"x": 1}')
    assert read_json(p, "fix it") == {"x": 1}
    p.write_text('{"x": ')
    with pytest.raises(InputError, match="cannot read it as JSON") as e:
        read_json(p, "delete it")
    assert str(p) in str(e.value) and "fix: delete it" in str(e.value)
    with pytest.raises(InputError, match="missing"):
        read_json(tmp_path / "b.json", "make it")


def test_debug_runs_have_their_own_outputs():
    """A debug run in outputs/train/fold=0 made the default run there refuse its settings (after ~2 min)."""
    default, debug = _compose("train", []), _compose("train", ["debug=fast"])
    assert debug.paths.output_root != default.paths.output_root
    assert _compose("train", ["debug=fast", "paths.output_root=/tmp/o"]).paths.output_root == "/tmp/o"


def test_end_stage_refines_again_sequences_other_weights_made(tmp_path, monkeypatch):
    """An iteration whose end stage was interrupted and which then trained again from scratch (a plain rerun,
    no ckpt_path=last) must not keep the sequences the earlier network refined: summaries record the weights'
    digest, and only the same weights' are reused."""
    import types

    import torch

    from endorecon.callbacks.bootstrap import BootstrapCallback
    from endorecon.tasks import pipeline

    cfg = _compose("train", ["fold=0", "bootstrap.evaluate=false", f"paths.run_dir='{tmp_path}/fold=0'"])
    it_dir = tmp_path / "fold=0" / "iteration=0"
    net = torch.nn.Linear(2, 2)
    refined = []

    def fake_refine(cfg, seq, cache, depth, std, colors, excluded, out_dir, made_by=None):
        refined.append(seq.name)
        summary = dict(sequence=seq.name, n_flagged=0, made_by=made_by)
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "failures.csv").write_text("frame,dense_simulation,sparse_flow,depth_consistency,flagged,reason\n")
        (out_dir / "summary.json").write_text(json.dumps(summary))
        return summary

    monkeypatch.setattr(pipeline, "infer_depth", lambda module, seq, cache: (None, None, None))
    monkeypatch.setattr(pipeline, "refine_sequence", fake_refine)
    preps = [types.SimpleNamespace(seq=types.SimpleNamespace(name=f"patient_0{p}/seq_00", patient=p), cache=None,
                                   excluded=None) for p in (1, 2)]
    trainer = types.SimpleNamespace(is_global_zero=True, callback_metrics={}, logger=None, global_step=0)

    def end_stage():
        BootstrapCallback(cfg, preps, it_dir, types.SimpleNamespace(root=tmp_path)).on_train_end(trainer, net)

    end_stage()
    assert refined == ["patient_01/seq_00", "patient_02/seq_00"]
    refined.clear()
    end_stage()  # the same weights (ckpt_path=last): both kept
    assert refined == []
    # an earlier network refined patient 1 before the interruption; new weights now
    with torch.no_grad():
        net.weight += 1
    (it_dir / "sequences" / "patient_02__seq_00" / "summary.json").write_text(
        json.dumps(dict(sequence="patient_02/seq_00", n_flagged=0, made_by=pipeline.weights_digest(net))))
    end_stage()
    assert refined == ["patient_01/seq_00"]
    metrics = json.loads((it_dir / "metrics.json").read_text())
    assert {s["made_by"] for s in metrics["sequences"]} == {pipeline.weights_digest(net)}


def test_data_default_is_a_clear_error(tmp_path):
    """`--help` offers data=default (the training keys data=phantom builds on); choosing it crashed with an
    omegaconf traceback."""
    from endorecon.tasks import pipeline

    cfg = _compose("train", ["data=default", f"paths.output_root={tmp_path}"])
    with pytest.raises(InputError, match="data=default holds only the training keys") as e:
        pipeline.load_sequences(cfg)
    assert "data=phantom" in e.value.fix


def test_end_stage_evaluates_the_held_out_sequence_again_after_an_interruption(tmp_path, monkeypatch):
    """The held-out sequence is never taken from an earlier summary while bootstrap.evaluate is on: its depth
    evaluation (metrics.json's depth_evaluation) is made from the network's depth each time."""
    import types

    import torch

    from endorecon.callbacks.bootstrap import BootstrapCallback
    from endorecon.tasks import pipeline

    cfg = _compose("train", ["fold=1", "bootstrap.evaluate=true", f"paths.run_dir='{tmp_path}/fold=1'"])
    it_dir = tmp_path / "fold=1" / "iteration=0"
    inferred = []

    def fake_refine(cfg, seq, cache, depth, std, colors, excluded, out_dir, made_by=None):
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "failures.csv").write_text("frame,dense_simulation,sparse_flow,depth_consistency,flagged,reason\n")
        for name in ("poses.txt", "mesh.ply"):
            (out_dir / name).write_text("x")
        summary = dict(sequence=seq.name, n_flagged=0, made_by=made_by)
        (out_dir / "summary.json").write_text(json.dumps(summary))
        return summary

    monkeypatch.setattr(pipeline, "infer_depth", lambda module, seq, cache: inferred.append(seq.name) or (1, 2, 3))
    monkeypatch.setattr(pipeline, "refine_sequence", fake_refine)
    depth_eval = {"abs_rel": 0.1, "a1": 0.9, "std_error_spearman": 0.5}
    monkeypatch.setattr(pipeline, "evaluate_depth_with_cap", lambda *a: (depth_eval, None))
    monkeypatch.setattr(BootstrapCallback, "_evaluate", lambda self, seq, sdir: None)
    preps = [types.SimpleNamespace(seq=types.SimpleNamespace(name=f"patient_0{p}/seq_00", patient=p), cache=None,
                                   excluded=None) for p in (1, 2)]
    trainer = types.SimpleNamespace(is_global_zero=True, callback_metrics={}, logger=None, global_step=0)
    net = torch.nn.Linear(2, 2)
    for _ in range(2):
        BootstrapCallback(cfg, preps, it_dir, types.SimpleNamespace(root=tmp_path)).on_train_end(trainer, net)
    assert inferred == ["patient_01/seq_00", "patient_02/seq_00", "patient_01/seq_00"]
    assert json.loads((it_dir / "metrics.json").read_text())["depth_evaluation"] == depth_eval


@pytest.mark.slow
def test_paper_table_takes_a_fold_trained_with_other_stage_settings_as_it_is(debug_run):
    """train.py refuses a fold made with another failure setting; benchmarks/paper_table.py goes on to re-make
    its rows only when every iteration is there and nothing but fusion / failure / PGO settings differ."""
    import importlib.util

    from endorecon.tasks.train import check_same_settings

    spec = importlib.util.spec_from_file_location("paper_table", ROOT / "benchmarks" / "paper_table.py")
    pt = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(pt)
    root = debug_run[0].parents[2]
    assert pt.trained_with_other_stage_settings(train_cfg(root, "fold=0", "iteration=1")) is None
    stage = train_cfg(root, "fold=0", "iteration=1", "failure.keep_excluded=false")
    with pytest.raises(InputError, match="other settings"):
        check_same_settings(stage)
    assert pt.trained_with_other_stage_settings(stage) == ["failure.keep_excluded: True -> False"]
    # a training setting differs too: the networks are not this configuration's, so the table must not go on
    both = train_cfg(root, "fold=0", "iteration=1", "failure.keep_excluded=false", "loss.sparse_flow=50")
    assert pt.trained_with_other_stage_settings(both) is None
    # an iteration the fold does not have yet: train.py must make it
    assert pt.trained_with_other_stage_settings(train_cfg(root, "fold=0", "iteration=2",
                                                          "failure.keep_excluded=false")) is None
