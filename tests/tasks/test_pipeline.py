"""Pipeline steps of the bootstrapping loop on a tiny phantom with ground truth."""

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from endorecon.data.dataset import load_dataset, load_ground_truth
from endorecon.phantom import generate
from endorecon.tasks import pipeline


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    root = generate(tmp_path_factory.mktemp("ph") / "ph", patients=1, frames=6, height=64, width=80, seed=3)
    seq = load_dataset(root)[0]
    return root, seq, load_ground_truth(root, 0, "seq_00")


def test_simulated_depth_of_gt_mesh_at_gt_poses_is_gt_depth(tiny):
    root, seq, gt = tiny
    sim, valid = pipeline.render_simulated(gt.mesh_path, seq, gt.cam_from_world)
    gt_valid = gt.depth_mm > 0
    assert valid.sum() > 0.9 * gt_valid.sum()
    both = valid & gt_valid
    assert np.abs(sim[both] - gt.depth_mm[both]).max() < 1e-3  # mm (GT depth is stored as float32)
    assert not valid[~seq.mask[None].repeat(len(seq), 0)].any()  # nothing outside the endoscope mask


def test_fusing_gt_depth_at_gt_poses_lands_on_the_gt_mesh(tiny):
    from endorecon.rendering import MeshRenderer

    root, seq, gt = tiny
    cfg = OmegaConf.create({"name": "adaptive", "c1": 0.1, "c2": 0.8, "voxel_size": None, "voxel_fraction": 0.02,
                            "compile": False, "device": "CPU:0"})
    depth = torch.from_numpy(gt.depth_mm)[:, None]
    colors = np.stack([seq.load_frame(i) for i in range(len(seq))]).astype(np.float32) / 255
    volume = pipeline.fuse_sequence(cfg, seq, depth, depth * 0.01, colors, gt.cam_from_world, np.ones(len(seq), bool))
    mesh = volume.extract_mesh()
    v = mesh.vertex.positions.numpy()
    voxel = 0.02 * float(np.median(gt.depth_mm[gt.depth_mm > 0]))
    d = MeshRenderer(gt.mesh_path).distance(v)
    assert len(v) > 100 and np.median(d) < 0.5 * voxel
    with pytest.raises(Exception, match="no registered, unflagged frame"):
        pipeline.fuse_sequence(cfg, seq, depth, depth * 0.01, colors, gt.cam_from_world, np.zeros(len(seq), bool))


def test_a_volume_that_is_not_saved_keeps_no_frames_for_the_free_space_check(tiny):
    root, seq, gt = tiny
    cfg = OmegaConf.create({"name": "adaptive", "voxel_size": None, "voxel_fraction": 0.02, "compile": False,
                            "device": "CPU:0", "free_space_max_fraction": 0.5, "free_space_tau": 0.1})
    depth = torch.from_numpy(gt.depth_mm)[:, None]
    colors = np.stack([seq.load_frame(i) for i in range(len(seq))]).astype(np.float32) / 255
    use = np.ones(len(seq), bool)
    saved = pipeline.fuse_sequence(cfg, seq, depth, depth * 0.01, colors, gt.cam_from_world, use)
    assert saved.free_space_max_fraction == 0.5 and len(saved._seen) == len(seq)
    extracted = pipeline.fuse_sequence(cfg, seq, depth, depth * 0.01, colors, gt.cam_from_world, use, saved=False)
    assert extracted.free_space_max_fraction is None and extracted._seen == []
    assert cfg.free_space_max_fraction == 0.5  # the caller's config is not changed
    assert len(extracted.extract_mesh().triangle.indices) == len(saved.extract_mesh().triangle.indices)


def test_ablation_variant_outputs_follow_their_checkpoint_and_settings(tmp_path):
    """A variant's cached outputs are kept only for the checkpoint and the settings they were made from."""
    import json

    from endorecon.tasks.ablation import _reset_if_other_source
    from endorecon.utils.io import file_id

    ckpt = tmp_path / "last.ckpt"
    ckpt.write_bytes(b"weights v1")
    settings = {"fusion": {"mask_erode_px": 2}, "failure": {}, "pgo": {}}
    src = {"checkpoint": file_id(ckpt), "settings": settings}
    vdir = tmp_path / "plain_fusion" / "patient_00__seq_00"
    _reset_if_other_source(vdir, src)
    (vdir / "summary.json").write_text("{}")
    _reset_if_other_source(vdir, src)  # same checkpoint and settings: kept
    assert (vdir / "summary.json").is_file() and json.loads((vdir / "source.json").read_text()) == src
    ckpt.write_bytes(b"weights v2, retrained")  # another size (and mtime)
    src2 = {"checkpoint": file_id(ckpt), "settings": settings}
    assert src2 != src
    _reset_if_other_source(vdir, src2)
    assert not (vdir / "summary.json").exists() and json.loads((vdir / "source.json").read_text()) == src2
    legacy = tmp_path / "adapted" / "x"  # outputs of a run before source.json existed: unknown origin
    legacy.mkdir(parents=True)
    (legacy / "summary.json").write_text("{}")
    _reset_if_other_source(legacy, src2)
    assert not (legacy / "summary.json").exists() and (legacy / "source.json").is_file()

    # other fusion settings, same checkpoint: made again, but what depends on the checkpoint alone stays
    adapted = tmp_path / "adapted" / "y"
    _reset_if_other_source(adapted, src2, keep=("adaptation",))
    (adapted / "adaptation").mkdir()
    (adapted / "adaptation" / "adapted.ckpt").write_text("w")
    (adapted / "mesh.ply").write_text("m")
    src3 = {"checkpoint": src2["checkpoint"], "settings": {**settings, "fusion": {"mask_erode_px": 0}}}
    _reset_if_other_source(adapted, src3, keep=("adaptation",))
    assert (adapted / "adaptation" / "adapted.ckpt").is_file() and not (adapted / "mesh.ply").exists()
    assert json.loads((adapted / "source.json").read_text()) == src3
    _reset_if_other_source(adapted, {"checkpoint": {"path": "other"}, "settings": settings}, keep=("adaptation",))
    assert not (adapted / "adaptation").exists()  # another checkpoint: nothing kept
    # a record of the checkpoint alone (written before settings were recorded) keeps the adaptation
    old = tmp_path / "adapted" / "z"
    (old / "adaptation").mkdir(parents=True)
    (old / "mesh.ply").write_text("m")
    (old / "source.json").write_text(json.dumps(src2["checkpoint"]))
    _reset_if_other_source(old, src2, keep=("adaptation",))
    assert (old / "adaptation").is_dir() and not (old / "mesh.ply").exists()


def test_settings_diff_names_what_changed():
    from omegaconf import OmegaConf

    from endorecon.tasks.ablation import settings_diff
    from endorecon.tasks.pipeline import refine_settings as settings_of

    a = OmegaConf.create({"fusion": {"c1": 0.1, "compile": True}, "failure": {"enabled": True},
                          "pgo": {"enabled": True, "progress": True}})
    b = OmegaConf.create({"fusion": {"c1": 0.1, "compile": False, "mask_erode_px": 2, "boundary_trim_rings": 1},
                          "failure": {"enabled": True}, "pgo": {"enabled": True, "progress": False}})
    # keys that say how the stage runs (compile, progress), not what it computes, do not count; a key the
    # old record lacks is what build_fusion used without it; the trim is re-applied to any mesh
    assert settings_diff(settings_of(a), settings_of(b)) == ["fusion.mask_erode_px: 0 -> 2"]
    assert settings_diff(settings_of(a), settings_of(b), ignore=()) == ["fusion.boundary_trim_rings: 0 -> 1",
                                                                        "fusion.mask_erode_px: 0 -> 2"]
    same = OmegaConf.create({"fusion": {"c1": 0.1, "mask_erode_px": 0}, "failure": {"enabled": True},
                             "pgo": {"enabled": True}})
    assert settings_diff(settings_of(a), settings_of(same)) == []  # an explicit default is no change
    assert settings_diff(settings_of(a), settings_of(a)) == []
    assert settings_diff(None, settings_of(a)) == ["settings unrecorded"]
    # failure.keep_excluded came later: a record without it ran as it does at false
    kept = OmegaConf.create({"fusion": {"c1": 0.1}, "failure": {"enabled": True, "keep_excluded": True},
                             "pgo": {"enabled": True}})
    off = OmegaConf.merge(same, {"failure": {"keep_excluded": False}})
    assert settings_diff(settings_of(a), settings_of(off)) == []
    assert settings_diff(settings_of(a), settings_of(kept)) == ["failure.keep_excluded: False -> True"]
    # so did the hysteresis: a record without it ran with none
    low = OmegaConf.merge(same, {"failure": {"low_thresholds": {"dense_simulation": 1.0}}})
    assert settings_diff(settings_of(a), settings_of(low)) == [
        "failure.low_thresholds: None -> {'dense_simulation': 1.0}"]
    assert settings_diff(settings_of(a), settings_of(OmegaConf.merge(same, {"failure": {"low_thresholds": None}}))) == []

def test_sfm_cache_is_found_through_a_symlinked_data_root(tmp_path):
    """The same data through a symlink (another output root, another working directory) must reuse its SfM:
    a second SfM run would put the video in another world frame.  A cache keyed the old way (the path as
    given) is reused where it exists."""
    from endorecon.tasks.pipeline import config_hash, sfm_cache_dir

    data = tmp_path / "real" / "phantom"
    data.mkdir(parents=True)
    (data / "dataset.json").write_text('{"patients": 1}')
    (tmp_path / "link").symlink_to(tmp_path / "real")
    cfg = OmegaConf.create({"sfm": {"max_size": 960, "num_threads": -1, "colmap_verbose": False},
                            "paths": {"cache_dir": str(tmp_path / "cache")}})
    real, linked = sfm_cache_dir(cfg, data), sfm_cache_dir(cfg, tmp_path / "link" / "phantom")
    assert real == linked and real.parent == tmp_path / "cache" / "sfm"
    other = OmegaConf.create({**OmegaConf.to_container(cfg), "sfm": {"max_size": 640, "num_threads": -1}})
    assert sfm_cache_dir(other, data) != real  # other SfM settings: another model
    # COLMAP's log and threads change nothing kept: the same cache (a new one ran COLMAP on every sequence)
    quiet = OmegaConf.create({**OmegaConf.to_container(cfg), "sfm": {"max_size": 960, "num_threads": 1,
                                                                     "colmap_verbose": True}})
    assert sfm_cache_dir(quiet, data) == real
    # an unset seed (a key added since) keys as before it existed; a seed is another model
    def seeded(seed):
        return OmegaConf.create({**OmegaConf.to_container(cfg), "sfm": {**cfg.sfm, "seed": seed}})

    assert sfm_cache_dir(seeded(None), data) == real and sfm_cache_dir(seeded(0), data) != real
    legacy = tmp_path / "cache" / "sfm" / config_hash(cfg.sfm, '{"patients": 1}', str(tmp_path / "link" / "phantom"))
    legacy.mkdir(parents=True)
    assert sfm_cache_dir(cfg, tmp_path / "link" / "phantom") == legacy
    assert sfm_cache_dir(quiet, tmp_path / "link" / "phantom") == legacy  # keyed with every setting, defaults
    assert sfm_cache_dir(cfg, data) == real  # its own key for the path it was made under


def test_ablation_variants_follow_the_sfm_model_and_ignore_settings_added_since(tmp_path):
    """A variant made from another SfM model is made again; one whose record lacks a setting added to the
    config since (at the value the old run used) or differs in the boundary trim alone is kept."""
    import json

    from endorecon.fusion.run import FUSION_DEFAULTS
    from endorecon.tasks.ablation import _reset_if_other_source

    settings = {"fusion": {**FUSION_DEFAULTS, "boundary_trim_rings": 1}, "failure": {}, "pgo": {}}
    src = {"checkpoint": {"path": "a"}, "settings": settings, "sfm": "0123"}
    vdir = tmp_path / "plain_fusion" / "x"
    recorded = {k: v for k, v in settings["fusion"].items() if k != "block_search"}  # before block_search existed
    vdir.mkdir(parents=True)
    (vdir / "source.json").write_text(json.dumps({**src, "settings": {**settings, "fusion": recorded}}))
    (vdir / "summary.json").write_text("{}")
    _reset_if_other_source(vdir, src)
    assert (vdir / "summary.json").is_file()
    _reset_if_other_source(vdir, {**src, "settings": {**settings, "fusion": {**settings["fusion"], "boundary_trim_rings": 2}}})
    assert (vdir / "summary.json").is_file()
    _reset_if_other_source(vdir, {**src, "settings": {**settings, "fusion": {**settings["fusion"], "c1": 0.2}}})
    assert not (vdir / "summary.json").exists()  # a setting that changes the mesh
    (vdir / "summary.json").write_text("{}")
    _reset_if_other_source(vdir, {**src, "sfm": "4567"})
    assert not (vdir / "summary.json").exists()  # SfM ran again
    adapted = tmp_path / "adapted" / "x"
    _reset_if_other_source(adapted, src, keep=("adaptation",))
    (adapted / "adaptation").mkdir()
    _reset_if_other_source(adapted, {**src, "sfm": "4567"}, keep=("adaptation",))
    assert not (adapted / "adaptation").exists()  # adapted on the other model's sparse depth: not kept
    legacy = tmp_path / "no_failure_pgo" / "x"  # recorded before the SfM model was: unknown, made again
    legacy.mkdir(parents=True)
    (legacy / "source.json").write_text(json.dumps({k: v for k, v in src.items() if k != "sfm"}))
    (legacy / "summary.json").write_text("{}")
    _reset_if_other_source(legacy, src)
    assert not (legacy / "summary.json").exists()


@pytest.mark.parametrize("first_stands", [False, True])
def test_refused_stages_start_from_the_refused_previous_iteration(tmp_path, monkeypatch, first_stands):
    """A fold trained with other failure settings: iteration 2's stage must start from an iteration 1 made with
    the current ones (whose left-out frames those settings decide), and that one from iteration 0's; an
    iteration whose recorded settings match stands as trained (its report copied beside the refused ones).
    Run again, nothing is made again."""
    import json
    import types
    from pathlib import Path

    import endorecon.tasks.reconstruct as rc
    import endorecon.tasks.train as tr
    from endorecon.data.sequence import write_poses_txt
    from endorecon.tasks import ablation as ab

    new = OmegaConf.create({"fusion": {}, "failure": {"enabled": True, "keep_excluded": True}, "pgo": {}})
    old = OmegaConf.create({"fusion": {}, "failure": {"enabled": True}, "pgo": {}})
    fold_dir, out = tmp_path / "fold", tmp_path / "out"
    seq = types.SimpleNamespace(name="p1/seq_00")
    slug = pipeline._slug(seq.name)
    for k in range(3):
        it_dir = fold_dir / f"iteration={k}"
        (it_dir / ".hydra").mkdir(parents=True)
        OmegaConf.save(new if (k == 0 and first_stands) else old, it_dir / ".hydra" / "config.yaml")
        (it_dir / "checkpoints").mkdir()
        (it_dir / "checkpoints" / "last.ckpt").write_text(f"net {k}")
        sd = it_dir / "sequences" / slug
        sd.mkdir(parents=True)
        (sd / "failures.csv").write_text(f"report {k}")
        (sd / "summary.json").write_text("{}")
    prevs, made = [], []

    def refine(cfg, s, cache, d, st, col, exc, vdir):
        made.append(Path(vdir))
        Path(vdir).mkdir(parents=True, exist_ok=True)
        write_poses_txt(Path(vdir) / "poses.txt", ["f0"], np.eye(4)[None])
        (Path(vdir) / "failures.csv").write_text("refused report")
        (Path(vdir) / "summary.json").write_text(json.dumps({"made": str(vdir)}))

    monkeypatch.setattr(tr, "prepare_sequences",
                        lambda c, s, p: prevs.append(p) or [types.SimpleNamespace(seq=s[0], cache=None, excluded=None)])
    monkeypatch.setattr(rc, "load_module", lambda p: (p.read_text(), None))
    monkeypatch.setattr(pipeline, "infer_depth", lambda *a: (None, None, None))
    monkeypatch.setattr(pipeline, "refine_sequence", refine)
    monkeypatch.setattr(pipeline, "evaluate_against_ct", lambda root, s, mesh, poses, o: {"mesh": Path(mesh)})
    monkeypatch.setattr(ab, "sfm_fingerprint", lambda s: "x")
    monkeypatch.setattr(ab, "configured_mesh", lambda c, m, o: m)
    info = types.SimpleNamespace(root=tmp_path)
    ev = ab.refuse_iteration(new, info, fold_dir, 2, seq, out, ["failure.keep_excluded: False -> True"])
    stage = lambda k: out / f"iteration={k}" / "sequences" / slug  # noqa: E731
    assert ev["mesh"] == stage(2) / "mesh.ply"
    if first_stands:
        assert made == [stage(1), stage(2)]
        assert prevs == [fold_dir / "iteration=0", out / "iteration=1"]
        assert (stage(0) / "failures.csv").read_text() == "report 0"  # for the SfM rerun's look back
    else:
        assert made == [stage(0), stage(1), stage(2)]
        assert prevs == [None, out / "iteration=0", out / "iteration=1"]
    made.clear()
    ab.refuse_iteration(new, info, fold_dir, 2, seq, out, [])
    assert made == []
    # iteration 1 made again (another network): iteration 2's stage, which started from it, too
    (fold_dir / "iteration=1" / "checkpoints" / "last.ckpt").write_text("net 1, retrained")
    ab.refuse_iteration(new, info, fold_dir, 2, seq, out, [])
    assert made == [stage(1), stage(2)]


def _stub_fold_inputs(monkeypatch, tmp_path, seqs):
    """ablation.run_fold's inputs stubbed: the held-out ``seqs`` (SfM as they are), a network, a CT per video;
    a prepared sequence's ``cache`` is the iteration dir it was prepared from."""
    import types

    import endorecon.data.dataset as ds
    import endorecon.tasks.reconstruct as rc
    import endorecon.tasks.train as tr
    from endorecon.tasks import ablation as ab

    monkeypatch.setattr(pipeline, "load_sequences", lambda c: types.SimpleNamespace(sequences=seqs, root=tmp_path))
    monkeypatch.setattr(pipeline, "run_sfm", lambda c, s, r: s)
    monkeypatch.setattr(tr, "prepare_sequences",
                        lambda c, s, p: [types.SimpleNamespace(seq=x, cache=p, excluded=None) for x in s])
    monkeypatch.setattr(rc, "load_module", lambda p: (None, None))
    monkeypatch.setattr(ds, "load_ground_truth",
                        lambda root, p, n: types.SimpleNamespace(mesh_path="ct.ply", cam_from_world=np.eye(4)[None]))
    monkeypatch.setattr(ab, "sfm_fingerprint", lambda s: "x")
    monkeypatch.setattr(ab, "configured_mesh", lambda c, m, o: m)
    monkeypatch.setattr(ab, "fuse_ground_truth", lambda *a: tmp_path / "gt.ply")
    monkeypatch.setattr(pipeline, "infer_depth", lambda *a: (None, None, None))


def test_ablation_rows_of_each_held_out_video_use_that_videos_mesh(tmp_path, monkeypatch):
    """Two held-out videos of one patient: the iteration dir's mesh.ply / poses.txt are the first video's copies,
    so each video's full / iteration0 row must read its own sequences/<slug>/ files."""
    import json
    import types
    from pathlib import Path

    from endorecon.data.sequence import write_poses_txt
    from endorecon.tasks import ablation as ab

    fold_dir = tmp_path / "fold"
    cfg = OmegaConf.create({"fold": 1, "fusion": {"boundary_trim_rings": 0}, "failure": {}, "pgo": {},
                            "adapt": {"enabled": False}})
    seqs = [types.SimpleNamespace(patient=1, name=n) for n in ("p1/videoA", "p1/videoB")]
    for it in (0, 1):
        it_dir = fold_dir / f"iteration={it}"
        (it_dir / ".hydra").mkdir(parents=True)
        OmegaConf.save(cfg, it_dir / ".hydra" / "config.yaml")
        (it_dir / "metrics.json").write_text(json.dumps({"depth_evaluation": {"abs_rel": 0.1}}))
        (it_dir / "checkpoints").mkdir()
        (it_dir / "checkpoints" / "last.ckpt").write_text("x")
        (it_dir / "mesh.ply").write_text("the first video's copy")
        write_poses_txt(it_dir / "poses.txt", ["a0"], np.eye(4)[None])
        for s in seqs:
            sd = it_dir / "sequences" / pipeline._slug(s.name)
            sd.mkdir(parents=True)
            (sd / "mesh.ply").write_text(s.name)
            (sd / "summary.json").write_text("{}")
            write_poses_txt(sd / "poses.txt", ["f0"], np.eye(4)[None])
    seen = []
    _stub_fold_inputs(monkeypatch, tmp_path, seqs)
    monkeypatch.setattr(pipeline, "refine_sequence",
                        lambda c, seq, cache, d, s, col, exc, vdir: write_poses_txt(Path(vdir) / "poses.txt", ["f0"],
                                                                                   np.eye(4)[None]))
    monkeypatch.setattr(pipeline, "evaluate_against_ct",
                        lambda root, seq, mesh, poses, out: seen.append((seq.name, Path(mesh))) or {})
    rows = ab.run_fold(cfg, fold_dir, tmp_path / "out")
    from_fold = [(name, mesh.read_text()) for name, mesh in seen if fold_dir in mesh.parents]
    assert from_fold == [("p1/videoA", "p1/videoA")] * 2 + [("p1/videoB", "p1/videoB")] * 2
    abs_rel = {(r["sequence"], r["variant"]): r["abs_rel"] for r in rows}
    assert abs_rel[("p1/videoA", "full")] == 0.1 and abs_rel[("p1/videoB", "full")] is None


@pytest.mark.parametrize("trained_as_now", [False, True])
def test_ablations_start_where_the_full_rows_last_stage_started(tmp_path, monkeypatch, trained_as_now):
    """plain_fusion and no_failure_pgo fuse from the poses and left-out frames `full`'s last stage started from:
    for a fold trained with other failure settings, iteration 1's stage as made again for `full`, not the
    training run's (which may fuse frames the current settings leave out); else the training run's."""
    import json
    import types
    from pathlib import Path

    from endorecon.data.sequence import write_poses_txt
    from endorecon.tasks import ablation as ab

    cfg = OmegaConf.create({"fold": 1, "fusion": {"boundary_trim_rings": 0}, "pgo": {}, "adapt": {"enabled": False},
                            "failure": {"enabled": True, "keep_excluded": True}})
    old = OmegaConf.merge(cfg, {"failure": {"keep_excluded": False}})
    fold_dir, out = tmp_path / "fold", tmp_path / "out"
    seq = types.SimpleNamespace(patient=1, name="p1/seq_00")
    slug = pipeline._slug(seq.name)
    for it in range(3):
        it_dir = fold_dir / f"iteration={it}"
        (it_dir / ".hydra").mkdir(parents=True)
        OmegaConf.save(cfg if trained_as_now else old, it_dir / ".hydra" / "config.yaml")
        (it_dir / "metrics.json").write_text("{}")
        (it_dir / "checkpoints").mkdir()
        (it_dir / "checkpoints" / "last.ckpt").write_text(f"net {it}")
        sd = it_dir / "sequences" / slug
        sd.mkdir(parents=True)
        for name in ("mesh.ply", "summary.json", "failures.csv"):
            (sd / name).write_text("{}")
        write_poses_txt(sd / "poses.txt", ["f0"], np.eye(4)[None])
    started = {}

    def refine(c, s, cache, d, st, col, exc, vdir):  # `cache` carries the dir the sequence was prepared from
        started[Path(vdir)] = cache
        Path(vdir).mkdir(parents=True, exist_ok=True)
        write_poses_txt(Path(vdir) / "poses.txt", ["f0"], np.eye(4)[None])
        (Path(vdir) / "summary.json").write_text("{}")

    _stub_fold_inputs(monkeypatch, tmp_path, [seq])
    monkeypatch.setattr(pipeline, "refine_sequence", refine)
    monkeypatch.setattr(pipeline, "evaluate_against_ct", lambda *a: {})
    rows = ab.run_fold(cfg, fold_dir, out)
    assert {r["variant"]: bool(r.get("refused")) for r in rows}["full"] is not trained_as_now
    start = fold_dir / "iteration=1" if trained_as_now else out / "full" / "iteration=1"
    if not trained_as_now:
        assert started[out / "full" / "iteration=2" / "sequences" / slug] == start
    assert started[out / "plain_fusion" / slug] == start
    assert started[out / "no_failure_pgo" / slug] == start
    recorded = json.loads((out / "plain_fusion" / slug / "source.json").read_text())["previous"]
    assert recorded["path"] == str((start / "sequences" / slug / "summary.json").resolve())


def test_results_table_means_over_patients_and_quotes_the_csv(tmp_path):
    import csv

    from endorecon.tasks.ablation import COLUMNS, write_table

    def row(patient, seq, mean):
        return {"patient": patient, "sequence": seq, "variant": "full", "abs_rel": None,
                **{k: None for k in COLUMNS}, "mean_mm": mean, "median_mm": mean, "p95_mm": mean, "max_mm": mean,
                "frac_below_1mm": 1.0}

    rows = [row(1, "p1/a,b", 1.0), row(1, "p1/c", 1.0), row(2, "p2/a", 4.0)]
    csv_path, md_path = write_table(rows, tmp_path)
    md = md_path.read_text()
    assert "| **mean** |  | full | 2.500 |" in md  # (1 + 4) / 2, not (1 + 1 + 4) / 3
    assert "| 1 | p1/a,b | full | 1.000 |" in md  # two videos of patient 1: a sequence column
    rows[0]["frac_below_1mm"] = 0.9952  # rounded down: 100 % only when every point is under 1 mm
    md = write_table(rows, tmp_path)[1].read_text()
    assert "| 99.5% |" in md and "| 100.0% |" in md and "| 100% |" not in md
    got = list(csv.DictReader(csv_path.open()))
    assert [r["sequence"] for r in got] == ["p1/a,b", "p1/c", "p2/a"]


def test_trimmed_mesh_follows_its_source_mesh(tmp_path):
    """The table's boundary-trimmed copy of a run's mesh is made again when that mesh changes (a retrained fold)."""
    import open3d as o3d

    from endorecon.fusion import read_mesh_ply, write_mesh_ply
    from endorecon.tasks.ablation import configured_mesh

    def grid(z):
        m = o3d.t.geometry.TriangleMesh.from_legacy(o3d.geometry.TriangleMesh.create_sphere(1.0, 20).translate((0, 0, z)))
        # an open mesh: the sphere without its upper cap
        keep = m.vertex.positions.numpy()[m.triangle.indices.numpy()][:, :, 2].max(1) < z + 0.5
        m.triangle.indices = o3d.core.Tensor(m.triangle.indices.numpy()[keep])
        return m

    src = tmp_path / "run" / "mesh.ply"
    src.parent.mkdir()
    write_mesh_ply(src, grid(0.0), boundary_trim_rings=0)
    cfg = OmegaConf.create({"fusion": {"boundary_trim_rings": 1}})
    first = configured_mesh(cfg, src, tmp_path / "out")
    z0 = read_mesh_ply(first).vertex.positions.numpy()[:, 2].mean()
    write_mesh_ply(src, grid(5.0), boundary_trim_rings=0)
    again = configured_mesh(cfg, src, tmp_path / "out")
    assert again == first and read_mesh_ply(again).vertex.positions.numpy()[:, 2].mean() > z0 + 4


def test_held_out_depth_evaluation_scores_invalid_predictions(monkeypatch):
    """Half of each frame's prediction NaN / negative: the held-out depth evaluation must count those pixels
    and score them at the floor (they were dropped from its mask, so the other half alone gave AbsRel 0)."""
    import types

    import endorecon.data.dataset as dataset
    from endorecon.tasks import pipeline

    n, h, w = 2, 8, 8
    gt = np.full((n, h, w), 50.0, np.float32)
    monkeypatch.setattr(dataset, "load_ground_truth", lambda root, p, name: types.SimpleNamespace(depth_mm=gt))
    seq = types.SimpleNamespace(patient=0, name="patient_00/seq_00", mask=np.ones((h, w), bool))
    depth = 50.0 + torch.randn(n, 1, h, w, generator=torch.Generator().manual_seed(0))
    depth[0, :, :4] = float("nan")
    depth[1, :, :4] = -1.0
    std = torch.rand(n, 1, h, w) + 0.1
    out = pipeline.evaluate_depth(None, seq, depth, std)[0]
    assert out["n_pixels"] == n * h * w and out["n_invalid_pred"] == n * h * w // 2
    assert out["abs_rel"] > 0.4
    assert np.isfinite(out["std_error_spearman"])  # ranked over the valid predictions


def test_sfm_cache_made_from_another_working_directory(tiny, tmp_path, monkeypatch):
    """The SfM cache is shared by every working directory that reads the data (keyed by its resolved path);
    frame paths it recorded relative to another directory must not make every frame "missing", and a cache
    that lists other frames is an error naming it."""
    import endorecon.sfm.stage as stage

    root, seq, _ = tiny
    relative = seq.replace(frame_paths=[p.relative_to(root.parent) for p in seq.frame_paths])
    monkeypatch.setattr(stage, "run", lambda cfg, s, out_dir: out_dir)
    monkeypatch.setattr(stage, "load_result", lambda out_dir: relative)
    monkeypatch.chdir(tmp_path)  # the recorded relative paths do not resolve from here
    cfg = OmegaConf.create({"sfm": {"max_size": 320}, "paths": {"cache_dir": str(tmp_path / "cache")}})
    got = pipeline.run_sfm(cfg, [seq], root)[0]
    assert got.frame_paths == seq.frame_paths and got.load_frame(0).shape[:2] == (seq.height, seq.width)
    other = relative.replace(frame_paths=relative.frame_paths[::-1])
    monkeypatch.setattr(stage, "load_result", lambda out_dir: other)
    with pytest.raises(pipeline.InputError, match="SfM cache .* other frames"):
        pipeline.run_sfm(cfg, [seq], root)


def test_empty_fused_mesh_names_the_fusion_setting(tiny):
    import open3d as o3d

    _, seq, gt = tiny
    with pytest.raises(pipeline.InputError, match="mesh_weight_threshold") as e:
        pipeline.render_simulated(o3d.t.geometry.TriangleMesh(), seq, gt.cam_from_world)
    assert seq.name in str(e.value)


def test_file_lock_makes_jobs_take_turns(tmp_path):
    """Folds run in parallel share the phantom and the SfM cache (COLMAP aborted on the shared database): a
    second job waits for the first's lock."""
    import subprocess
    import sys
    import time

    from endorecon.utils.io import file_lock

    lock, log = tmp_path / ".seq.lock", tmp_path / "log.txt"
    code = ("import sys, time; sys.path.insert(0, sys.argv[3]); from endorecon.utils.io import file_lock\n"
            "from pathlib import Path\n"
            "with file_lock(sys.argv[1]):\n"
            "    Path(sys.argv[2]).write_text('held\\n'); time.sleep(1.5)\n"
            "    Path(sys.argv[2]).write_text('held\\nreleased\\n')\n")
    from pathlib import Path

    other = subprocess.Popen([sys.executable, "-c", code, str(lock), str(log), str(Path(__file__).parents[2])])
    t0 = time.monotonic()
    while not log.exists() and time.monotonic() - t0 < 30:
        time.sleep(0.02)
    with file_lock(lock):
        seen = log.read_text()
    other.wait(timeout=30)
    assert seen == "held\nreleased\n"


def test_results_table_of_some_folds_keeps_the_other_folds_rows(tmp_path, monkeypatch):
    """benchmarks/paper_table.py folds=1 replaced a four-fold table with a one-fold one; it now keeps the rows of
    the other held-out patients, read back exactly as written."""
    import importlib.util

    from endorecon.tasks import ablation
    from endorecon.tasks import train as train_task

    def row(patient, variant, mean, refused=()):
        return {"patient": patient, "sequence": f"patient_{patient:02d}/seq_00", "variant": variant,
                **{k: None for k in ablation.COLUMNS}, "mean_mm": mean, "median_mm": mean / 2, "p95_mm": mean,
                "max_mm": 2 * mean, "frac_below_1mm": 0.5, "abs_rel": 0.123456, "refused": list(refused)}

    table_dir = tmp_path / "out" / "benchmarks" / "paper_table"
    first = [row(p, v, 0.1 * p + 0.01 * i + 0.0001234) for p in (0, 1, 2) for i, v in enumerate(("full", "adapted"))]
    first[1]["refused"] = ["model.x: 1 -> 2", "loss.y: a -> b"]
    ablation.write_table(first, table_dir)
    assert ablation.read_table(table_dir / "results.csv") == first
    md_before = (table_dir / "results.md").read_text()

    monkeypatch.setattr(train_task, "run", lambda cfg: None)
    monkeypatch.setattr(ablation, "run_fold", lambda cfg, fold_dir, out: [row(1, "full", 9.0), row(1, "adapted", 8.0)])
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    spec = importlib.util.spec_from_file_location("paper_table", root / "benchmarks" / "paper_table.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    mod.main(["folds=1", f"paths.output_root={tmp_path / 'out'}"])
    after = ablation.read_table(table_dir / "results.csv")
    assert [(r["patient"], r["variant"]) for r in after] == [(r["patient"], r["variant"]) for r in first]
    assert [r for r in after if r["patient"] != 1] == [r for r in first if r["patient"] != 1]
    assert [r["mean_mm"] for r in after if r["patient"] == 1] == [9.0, 8.0]
    assert md_before.splitlines()[2] == (table_dir / "results.md").read_text().splitlines()[2]  # patient 0 as before


def test_evaluate_against_ct_uses_a_given_reference_surface(monkeypatch, tmp_path):
    """A train-only patient (no CT) is not evaluated unless an analysis passes its surface explicitly."""
    import types
    from pathlib import Path

    import endorecon.data.dataset as dataset
    import endorecon.evaluation as evaluation

    poses = np.tile(np.eye(4), (2, 1, 1))
    monkeypatch.setattr(dataset, "load_ground_truth",
                        lambda root, patient, seq: types.SimpleNamespace(mesh_path=None, cam_from_world=poses))
    monkeypatch.setattr(evaluation, "evaluate_mesh", lambda mesh, ref, out, **k: {"reference": Path(ref)})
    seq = types.SimpleNamespace(patient=9, name="patient_09/seq_00")
    assert pipeline.evaluate_against_ct(tmp_path, seq, tmp_path / "m.ply", poses, tmp_path / "ev") is None
    got = pipeline.evaluate_against_ct(tmp_path, seq, tmp_path / "m.ply", poses, tmp_path / "ev", tmp_path / "s.ply")
    assert got == {"reference": tmp_path / "s.ply"}
