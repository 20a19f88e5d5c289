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

def test_sfm_cache_is_found_through_a_symlinked_data_root(tmp_path):
    """The same data through a symlink (another output root, another working directory) must reuse its SfM:
    a second SfM run would put the video in another world frame.  A cache keyed the old way (the path as
    given) is reused where it exists."""
    from endorecon.tasks.pipeline import config_hash, sfm_cache_dir

    data = tmp_path / "real" / "phantom"
    data.mkdir(parents=True)
    (data / "dataset.json").write_text('{"patients": 1}')
    (tmp_path / "link").symlink_to(tmp_path / "real")
    cfg = OmegaConf.create({"sfm": {"num_threads": -1}, "paths": {"cache_dir": str(tmp_path / "cache")}})
    real, linked = sfm_cache_dir(cfg, data), sfm_cache_dir(cfg, tmp_path / "link" / "phantom")
    assert real == linked and real.parent == tmp_path / "cache" / "sfm"
    other = OmegaConf.create({**OmegaConf.to_container(cfg), "sfm": {"num_threads": 1}})
    assert sfm_cache_dir(other, data) != real  # other SfM settings: another model
    legacy = tmp_path / "cache" / "sfm" / config_hash(cfg.sfm, '{"patients": 1}', str(tmp_path / "link" / "phantom"))
    legacy.mkdir(parents=True)
    assert sfm_cache_dir(cfg, tmp_path / "link" / "phantom") == legacy
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
