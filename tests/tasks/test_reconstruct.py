"""The reconstruct task: inputs, checkpoint checks, bad input errors, resumability, and a video end to end."""

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from endorecon.utils.errors import InputError

ROOT = Path(__file__).resolve().parents[2]
H, W = 64, 80
TINY_NET = dict(_target_="endorecon.networks.FCDenseNet", in_channels=3, first_conv_channels=8, growth_rate=4,
                down_layers=[2, 2], bottleneck_layers=2)


def compose(*overrides: str):
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    import endorecon.utils.resolvers  # noqa: F401

    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        return hydra_compose(config_name="reconstruct", overrides=list(overrides))


def recon_cfg(run_dir: Path, *extra: str):
    return compose(f"paths.root_dir='{run_dir.parent}'", f"paths.run_dir='{run_dir}'", "fusion.compile=false",
                   "pgo.iterations=3", "pgo.progress=false", "adapt.epochs=1", "adapt.batches_per_epoch=2",
                   "adapt.eval_batches=1", "data.num_workers=0", *extra)


def save_ckpt(path: Path, net: dict, weights_of: dict | None = None, train_hw=None) -> Path:
    """A checkpoint as train.py writes it (state_dict + hyper_parameters); ``weights_of`` builds the weights
    from another net config (a mismatching checkpoint)."""
    from endorecon.module import DepthModule

    torch.manual_seed(0)
    hp_model = dict(net=net)
    weights = DepthModule(dict(net=weights_of or net)).state_dict()
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(dict(state_dict=weights, hyper_parameters=dict(model=hp_model, loss={}),
                    **({"pytorch-lightning_version": "2"})), path)
    if train_hw is not None:
        (path.parent.parent / ".hydra").mkdir(exist_ok=True)
        (path.parent.parent / ".hydra" / "config.yaml").write_text(
            f"data:\n  height: {train_hw[0]}\n  width: {train_hw[1]}\n")
    return path


@pytest.fixture(scope="module")
def tiny_ckpt(tmp_path_factory):
    return save_ckpt(tmp_path_factory.mktemp("ckpt") / "run" / "checkpoints" / "last.ckpt", TINY_NET,
                     train_hw=(64, 80))


def circle_frames(folder: Path, n: int = 5, texture: bool = True) -> Path:
    """n textured frames with a dark border (a circular field of view), as PNG files."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[:H, :W]
    inside = (yy - 31.5) ** 2 + (xx - 39.5) ** 2 < 28**2
    for k in range(n):
        img = (rng.random((H, W, 3)) * 200 + 30).astype(np.uint8) if texture else np.full((H, W, 3), 120, np.uint8)
        img[~inside] = 0
        Image.fromarray(img).save(folder / f"{k:04d}.png")
    return folder


def k_file(path: Path) -> Path:
    path.write_text("60 60 40 32\n")
    return path


# ------------------------------------------------------------------ units
def test_quote_path_overrides():
    from endorecon.utils.cli import quote_path_overrides

    got = quote_path_overrides(["ckpt=/a/fold=0/iteration=1/last.ckpt", "input=/x/it's", "mask=null",
                                "pgo.iterations=3", "input='/q=1'"], ("input", "ckpt", "intrinsics", "mask"))
    assert got == ["ckpt='/a/fold=0/iteration=1/last.ckpt'", "input='/x/it\\'s'", "mask=null", "pgo.iterations=3",
                   "input='/q=1'"]
    # a multirun sweeps over comma-separated paths: each quoted on its own (one job with "a,b" before)
    keys = ("input", "mask")
    assert quote_path_overrides(["-m", "input=/v/a.mp4,/v/f=1/b.mp4", "mask=null,/m.png", "input=choice(a,b)"], keys) \
        == ["-m", "input='/v/a.mp4','/v/f=1/b.mp4'", "mask=null,'/m.png'", "input=choice(a,b)"]
    assert quote_path_overrides(["input=/v/a,b.mp4"], keys) == ["input='/v/a,b.mp4'"]  # one run: one path
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parsed = OverridesParser.create().parse_overrides(["input='/v/a.mp4','/v/f=1/b.mp4'"])[0]
    assert parsed.is_sweep_override() and [v.text for v in parsed.value().list] == ["/v/a.mp4", "/v/f=1/b.mp4"]
    # Hydra reads back the very path (a backslash inside a path was doubled before)
    parser = OverridesParser.create()
    for path in ["/tmp/a\\b/c.ply", "/x/it's", "/x/a\\'b", "/x/end\\", "/q=1/x"]:
        arg = quote_path_overrides([f"input={path}"], keys)[0]
        assert parser.parse_overrides([arg])[0].value() == path, (path, arg)


def test_network_size_keeps_area_aspect_and_stride():
    from endorecon.tasks.reconstruct import network_size

    assert network_size((256, 320), (256, 320), 32) == (256, 320)
    h, w = network_size((540, 960), (128, 160), 32)
    assert h % 32 == 0 and w % 32 == 0
    assert abs(np.log((h / w) / (540 / 960))) < 0.2 and abs(np.log(h * w / (128 * 160))) < 0.3


def test_load_module_and_training_resolution(tiny_ckpt):
    from endorecon.tasks.reconstruct import load_module

    module, hw = load_module(tiny_ckpt)
    assert hw == (64, 80) and not module.training
    d, s = module.predict(torch.rand(1, 3, 32, 32), torch.ones(1, 1, 32, 32, dtype=torch.bool))
    assert d.shape == s.shape == (1, 1, 32, 32)


def test_checkpoint_of_another_model_config(tmp_path):
    from endorecon.tasks.reconstruct import load_module

    other = dict(TINY_NET, first_conv_channels=12, down_layers=[2, 2, 2])
    bad = save_ckpt(tmp_path / "mismatch.ckpt", TINY_NET, weights_of=other)
    with pytest.raises(InputError) as e:
        load_module(bad)
    msg = str(e.value)
    assert e.value.path == bad and "do not fit" in msg and "shape mismatch" in msg and "unexpected" in msg
    assert "first_conv_channels=8" in msg and e.value.fix


@pytest.mark.parametrize("kind", ["junk", "plain_state_dict", "missing"])
def test_not_a_checkpoint(tmp_path, kind):
    from endorecon.tasks.reconstruct import load_module

    p = tmp_path / "x.ckpt"
    if kind == "junk":
        p.write_bytes(b"not a checkpoint at all" * 10)
    elif kind == "plain_state_dict":
        torch.save({"weight": torch.zeros(3)}, p)
    with pytest.raises(InputError) as e:
        load_module(p)
    assert e.value.path == p and "ckpt=" in e.value.fix


# ------------------------------------------------------------------ bad input through the task (no SfM, no model)
def test_missing_intrinsics(tmp_path, tiny_ckpt):
    from endorecon.tasks.reconstruct import run

    frames = circle_frames(tmp_path / "frames")
    with pytest.raises(InputError, match="no intrinsics") as e:
        run(recon_cfg(tmp_path / "run", f"input={frames}", f"ckpt={tiny_ckpt}"))
    assert "intrinsics=" in e.value.fix


def test_mask_of_wrong_size(tmp_path, tiny_ckpt):
    from endorecon.tasks.reconstruct import run

    frames = circle_frames(tmp_path / "frames")
    mask = tmp_path / "mask.png"
    Image.fromarray(np.full((H + 1, W, 3), 255, np.uint8)).save(mask)
    with pytest.raises(InputError, match="mask is 80x65") as e:
        run(recon_cfg(tmp_path / "run", f"input={frames}", f"intrinsics={k_file(tmp_path / 'K.txt')}",
                      f"mask={mask}", f"ckpt={tiny_ckpt}"))
    assert e.value.path == mask


def test_unreadable_video_through_task(tmp_path, tiny_ckpt):
    from endorecon.tasks.reconstruct import run

    bad = tmp_path / "clip.mp4"
    bad.write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(500))
    with pytest.raises(InputError) as e:
        run(recon_cfg(tmp_path / "run", f"input={bad}", f"intrinsics={k_file(tmp_path / 'K.txt')}",
                      f"ckpt={tiny_ckpt}"))
    assert e.value.path == bad and "decode" in str(e.value)


def test_textureless_frames_stop_before_sfm(tmp_path, tiny_ckpt):
    from endorecon.tasks.reconstruct import run

    frames = circle_frames(tmp_path / "frames", texture=False)
    with pytest.raises(InputError, match="no texture"):
        run(recon_cfg(tmp_path / "run", f"input={frames}", f"intrinsics={k_file(tmp_path / 'K.txt')}",
                      f"ckpt={tiny_ckpt}"))
    assert not (tmp_path / "run" / "sfm").exists()


def test_bad_checkpoint_fails_before_sfm_and_keeps_the_input_stage(tmp_path):
    from endorecon.tasks.reconstruct import run

    frames = circle_frames(tmp_path / "frames")
    bad = save_ckpt(tmp_path / "bad.ckpt", TINY_NET, weights_of=dict(TINY_NET, growth_rate=6))
    run_dir = tmp_path / "run"
    with pytest.raises(InputError, match="do not fit"):
        run(recon_cfg(run_dir, f"input={frames}", f"intrinsics={k_file(tmp_path / 'K.txt')}", f"ckpt={bad}"))
    assert (run_dir / "mask.png").is_file() and not (run_dir / "sfm").exists()


def test_a_run_dir_is_not_resumed_with_another_input(tmp_path):
    """The run dir is named by the input's stem: another clip of the same name, other intrinsics or another mask
    must not reuse its frames / SfM / depth.  (A bad checkpoint stops each run right after the input stage.)"""
    from endorecon.tasks.reconstruct import run

    bad = save_ckpt(tmp_path / "bad.ckpt", TINY_NET, weights_of=dict(TINY_NET, growth_rate=6))
    a = circle_frames(tmp_path / "a" / "frames")
    b = circle_frames(tmp_path / "b" / "frames", n=6)
    K = k_file(tmp_path / "K.txt")
    run_dir = tmp_path / "run"
    with pytest.raises(InputError, match="do not fit"):
        run(recon_cfg(run_dir, f"input={a}", f"intrinsics={K}", f"ckpt={bad}"))
    record = (run_dir / "input.json").read_text()
    with pytest.raises(InputError, match="another video / frames folder") as e:
        run(recon_cfg(run_dir, f"input={b}", f"intrinsics={K}", f"ckpt={bad}"))
    assert e.value.path == run_dir / "input.json" and "name=" in e.value.fix
    K2 = tmp_path / "K2.txt"
    K2.write_text("70 70 40 32\n")
    with pytest.raises(InputError, match="other intrinsics or another mask"):
        run(recon_cfg(run_dir, f"input={a}", f"intrinsics={K2}", f"ckpt={bad}"))
    box = tmp_path / "box.png"
    m = np.zeros((H, W), np.uint8)
    m[8:56, 10:70] = 255
    Image.fromarray(m).save(box)
    with pytest.raises(InputError, match="other intrinsics or another mask"):
        run(recon_cfg(run_dir, f"input={a}", f"intrinsics={K}", f"mask={box}", f"ckpt={bad}"))
    assert (run_dir / "input.json").read_text() == record  # nothing was overwritten
    with pytest.raises(InputError, match="do not fit"):  # the same input again passes the check
        run(recon_cfg(run_dir, f"input={a}", f"intrinsics={K}", f"ckpt={bad}"))
    # a first run stopped by the input checks (no intrinsics) still records its input: another input of the
    # same name is refused next time (it was not, and a video's frames/ were the stopped run's)
    fresh = tmp_path / "run2"
    with pytest.raises(InputError, match="no intrinsics"):
        run(recon_cfg(fresh, f"input={a}", f"ckpt={bad}"))
    with pytest.raises(InputError, match="another video / frames folder"):
        run(recon_cfg(fresh, f"input={b}", f"intrinsics={K}", f"ckpt={bad}"))


def test_sequence_folder_whose_camera_is_for_another_size(tmp_path, tiny_ckpt):
    from endorecon.data.sequence import write_camera_json
    from endorecon.tasks.reconstruct import run

    seq = tmp_path / "seq"
    circle_frames(seq / "frames")
    write_camera_json(seq / "camera.json", np.array([[120.0, 0, 79.5], [0, 120.0, 63.5], [0, 0, 1]]), 2 * H, 2 * W)
    Image.fromarray(np.full((2 * H, 2 * W), 255, np.uint8)).save(seq / "mask.png")
    with pytest.raises(InputError, match=f"camera.json is for {2 * W}x{2 * H} frames but the frames are {W}x{H}") as e:
        run(recon_cfg(tmp_path / "run", f"input={seq}", f"ckpt={tiny_ckpt}"))
    assert e.value.path == seq / "camera.json"


def test_original_format_folder_without_sfm_files_is_an_input(tmp_path):
    from endorecon.tasks.reconstruct import run

    d = tmp_path / "orig"
    frames = sorted(circle_frames(tmp_path / "frames").iterdir())
    d.mkdir()
    for k, f in enumerate(frames):
        Image.open(f).convert("RGB").save(d / f"{100 + k:08d}.jpg", quality=95)
    (d / "camera_intrinsics_per_view").write_text("60\n60\n40\n32\n")
    Image.fromarray(np.full((H, W), 255, np.uint8)).save(d / "undistorted_mask.bmp")
    bad = save_ckpt(tmp_path / "bad.ckpt", TINY_NET, weights_of=dict(TINY_NET, growth_rate=6))
    with pytest.raises(InputError, match="do not fit"):  # past the input stage: the SfM files are not needed
        run(recon_cfg(tmp_path / "run", f"input={d}", f"ckpt={bad}"))
    assert (tmp_path / "run" / "mask.png").is_file()


def test_damaged_depth_npz_is_inferred_again(tmp_path, monkeypatch):
    from endorecon.tasks import reconstruct as R

    seq = type("S", (), {"registered": np.ones(2, bool)})()
    (tmp_path / "depth.npz").write_bytes(b"PK\x03\x04" + bytes(64))
    got = (torch.ones(2, 1, 4, 4), torch.ones(2, 1, 4, 4), np.zeros((2, 4, 4, 3), np.uint8))
    monkeypatch.setattr(R.pipeline, "infer_depth", lambda module, seq, cache, frames: got)
    depth, std, colors, skipped = R.infer_stage(None, seq, None, "stamp", tmp_path)
    assert not skipped and depth.shape == (2, 1, 4, 4)
    assert str(np.load(tmp_path / "depth.npz")["stamp"]) == "stamp"


def test_cli_exit_code_2_and_no_traceback(tmp_path):
    """A path with '=' (like train.py's run dirs) passes through the CLI; bad input is one message, status 2."""
    frames = circle_frames(tmp_path / "fold=0" / "frames")
    r = subprocess.run(
        [sys.executable, "reconstruct.py", f"input={frames}", f"ckpt={tmp_path}/iteration=0/last.ckpt",
         f"paths.root_dir={tmp_path}"],
        cwd=ROOT, capture_output=True, text=True, timeout=120, env={**os.environ, "COLUMNS": "400"},
    )
    assert r.returncode == 2, r.stderr[-2000:]
    assert "error:" in r.stderr and "no intrinsics" in r.stderr and "fix: pass intrinsics=" in r.stderr
    assert "Traceback" not in r.stderr and str(frames) in r.stderr


# ------------------------------------------------------------------ SfM failure (fast: tiny blank-ish video)
def _video(path: Path, frames: list[np.ndarray]) -> Path:
    """Encode frames to H.264 with the imageio-ffmpeg binary."""
    ffmpeg = pytest.importorskip("imageio_ffmpeg")
    src = path.parent / f".{path.stem}_src"
    src.mkdir(exist_ok=True)
    for k, f in enumerate(frames):
        Image.fromarray(f).save(src / f"{k:04d}.png")
    subprocess.run([ffmpeg.get_ffmpeg_exe(), "-y", "-loglevel", "error", "-framerate", "10", "-i",
                    str(src / "%04d.png"), "-c:v", "libx264", "-pix_fmt", "yuv444p", "-crf", "12", str(path)],
                   check=True)
    return path


def test_video_without_texture_fails_in_sfm_clearly(tmp_path, tiny_ckpt):
    """With the texture pre-check off, constant frames reach SfM: it must fail with SfM's own clear error,
    and the decoded frames stay on disk."""
    from endorecon.sfm.stage import SfMError
    from endorecon.tasks.reconstruct import run

    video = _video(tmp_path / "grey.mp4", [np.full((H, W, 3), 100 + k, np.uint8) for k in range(6)])
    run_dir = tmp_path / "run"
    with pytest.raises(SfMError, match="no acceptable model") as e:
        run(recon_cfg(run_dir, f"input={video}", f"intrinsics={k_file(tmp_path / 'K.txt')}", f"ckpt={tiny_ckpt}",
                      "input_checks.min_texture=0", "sfm.attempts=[{name: default, peak_threshold: 0.003}]"))
    assert "textured tissue" in e.value.fix
    assert (run_dir / "frames" / "decode.json").is_file()
    assert json.loads((run_dir / "sfm" / "attempts.json").read_text())["status"] == "failed"


# ------------------------------------------------------------------ end to end on a phantom video
@pytest.fixture(scope="module")
def phantom_video(tmp_path_factory):
    from endorecon.phantom.generate import generate

    root = tmp_path_factory.mktemp("phantom")
    generate(root / "ph", patients=1, frames=20, height=128, width=160, seed=3)
    seq = root / "ph" / "patient_00" / "seq_00"
    frames = [np.asarray(Image.open(p).convert("RGB")) for p in sorted((seq / "frames").iterdir())]
    return _video(root / "ph.mp4", frames), seq / "camera.json"


@pytest.mark.slow
def test_video_end_to_end_and_resume(phantom_video, tiny_ckpt, tmp_path, monkeypatch):
    from endorecon.tasks import reconstruct as R

    video, camera = phantom_video
    run_dir = tmp_path / "run"
    cfg = recon_cfg(run_dir, f"input={video}", f"intrinsics={camera}", f"ckpt={tiny_ckpt}", "sfm.allow_partial=true")
    R.run(cfg)
    for name in ("frames/decode.json", "mask.png", "sfm/sequence.npz", "adaptation/adapted.ckpt",
                 "adaptation/adapt.json", "depth.npz", "mesh.ply", "report.md",
                 "depth_std.png", "mesh_preview.png", "timings.json", "reconstruction/poses.txt",
                 "reconstruction/failures.csv", "reconstruction/summary.json"):
        assert (run_dir / name).is_file(), name
    from endorecon.fusion.ply import read_mesh_ply

    mesh = read_mesh_ply(run_dir / "mesh.ply")
    assert len(mesh.triangle.indices) > 100 and "std" in mesh.vertex and "colors" in mesh.vertex
    report = (run_dir / "report.md").read_text()
    for stage in ("input", "sfm", "adaptation", "inference", "dense PGO", "fusion again", "**total**"):
        assert stage in report
    assert "test-time adaptation: 2 steps" in report
    assert re.search(r"dense PGO: objective -?[\d.e+-]+ -> -?[\d.e+-]+; pose updates [\d.e+-]+° median", report)
    # on by default: what the free-space check removed is in the report and the refine summary
    assert re.search(r"free-space check: \d+ of \d+ triangles \([\d.]+ %\) removed", report)
    rec_summary = json.loads((run_dir / "reconstruction/summary.json").read_text())
    assert rec_summary["free_space"]["triangles"] > 0 and rec_summary["uncertain"]["triangles"] > 0
    assert re.search(r"uncertainty trim: \d+ of \d+ triangles \([\d.]+ %\) removed: fused std over 2x", report)  # on by default
    assert rec_summary["far_only"]["triangles"] > 0 and rec_summary["far_only"]["ratio"] == 1.4  # on by default
    assert re.search(r"nearest-view check: \d+ of \d+ triangles \([\d.]+ %\) removed: surface no fused frame sees "
                     r"nearer than 1.4x", report)
    first = json.loads((run_dir / "timings.json").read_text())["stages"]
    assert not any(s["skipped"] for s in first.values())
    mesh_bytes = (run_dir / "mesh.ply").read_bytes()

    # Second run: every completed stage must be skipped; calling its work fails the test.
    def forbidden(*a, **k):
        raise AssertionError("a completed stage ran again")

    import endorecon.data.video as video_mod
    import endorecon.pgo
    import endorecon.sfm.colmap

    monkeypatch.setattr(video_mod, "_decoder", forbidden)
    monkeypatch.setattr(endorecon.sfm.colmap, "run_mapping", forbidden)
    monkeypatch.setattr(R.pipeline, "infer_depth", forbidden)
    import endorecon.tasks.adapt

    monkeypatch.setattr(endorecon.tasks.adapt, "adapt_module", forbidden)
    fuse, pgo = R.pipeline.fuse_sequence, endorecon.pgo.optimize_poses
    monkeypatch.setattr(R.pipeline, "fuse_sequence", forbidden)
    monkeypatch.setattr(endorecon.pgo, "optimize_poses", forbidden)
    R.run(cfg)
    second = json.loads((run_dir / "timings.json").read_text())["stages"]
    for name in ("input", "sfm", "adaptation", "inference", "failure detection + PGO + fusion"):
        assert second[name]["skipped"], name
        assert second[name]["seconds"] == pytest.approx(first[name]["seconds"])  # the report keeps the real cost
    assert (run_dir / "mesh.ply").read_bytes() == mesh_bytes

    # Third run with another fusion setting: the mesh is made again, the network stages are not run again.
    monkeypatch.setattr(R.pipeline, "fuse_sequence", fuse)
    monkeypatch.setattr(endorecon.pgo, "optimize_poses", pgo)
    R.run(recon_cfg(run_dir, f"input={video}", f"intrinsics={camera}", f"ckpt={tiny_ckpt}", "sfm.allow_partial=true",
                    "fusion.mask_erode_px=4", "fusion.max_std_ratio=3", "fusion.max_nearest_view_ratio=null"))
    third = json.loads((run_dir / "timings.json").read_text())["stages"]
    assert re.search(r"uncertainty trim: \d+ of \d+ triangles \([\d.]+ %\) removed: fused std over 3x the mesh's median",
                     (run_dir / "report.md").read_text())
    assert "nearest-view check: off (fusion.max_nearest_view_ratio=null)" in (run_dir / "report.md").read_text()
    assert third["adaptation"]["skipped"] and third["inference"]["skipped"]
    assert not third["failure detection + PGO + fusion"]["skipped"]
    assert (run_dir / "mesh.ply").read_bytes() != mesh_bytes

    # Fourth run with other settings, stopped during fusion: the third run's reconstruction stays whole (it was
    # deleted before the new one started)
    third_summary = (run_dir / "reconstruction/summary.json").read_text()
    third_mesh = (run_dir / "reconstruction/mesh.ply").read_bytes()

    def stopped(*a, **k):
        raise KeyboardInterrupt("stopped during fusion")

    monkeypatch.setattr(R.pipeline, "fuse_sequence", stopped)
    with pytest.raises(KeyboardInterrupt):
        R.run(recon_cfg(run_dir, f"input={video}", f"intrinsics={camera}", f"ckpt={tiny_ckpt}",
                        "sfm.allow_partial=true", "fusion.mask_erode_px=4", "fusion.max_std_ratio=4"))
    assert (run_dir / "reconstruction/summary.json").read_text() == third_summary
    assert (run_dir / "reconstruction/mesh.ply").read_bytes() == third_mesh
    assert not [p.name for p in run_dir.iterdir() if p.name.startswith(".reconstruction")]
    # the stages it finished are timed on disk (a stage skipped on the next run keeps its real cost)
    partial = json.loads((run_dir / "timings.json").read_text())
    assert partial["partial"] and partial["stages"]["sfm"]["seconds"] == pytest.approx(first["sfm"]["seconds"])


def test_depth_stamp_follows_the_sfm_model(tmp_path):
    """Depth maps are scaled to the SfM's sparse points: an SfM made again (its run dir deleted) must not
    reuse the cached depth, adaptation or mesh made for the old one."""
    import numpy as np

    from endorecon.data.sequence import Sequence
    from endorecon.tasks.reconstruct import _stamp

    ckpt = tmp_path / "last.ckpt"
    ckpt.write_bytes(b"w")
    K = np.array([[50.0, 0, 39.5], [0, 50.0, 31.5], [0, 0, 1]])
    pts = np.arange(30, dtype=np.float64).reshape(10, 3)
    seq = Sequence("p/s", [f"{i}.png" for i in range(3)], K, 64, 80, np.ones((64, 80), bool),
                   np.tile(np.eye(4), (3, 1, 1)), pts, [np.arange(3)] * 10)
    assert _stamp(ckpt, seq) == _stamp(ckpt, seq.replace())
    assert _stamp(ckpt, seq) != _stamp(ckpt, seq.replace(points_xyz=pts * 1.01))
    # and everything else the depth maps depend on: the frames' size, the crop window, the frame count, the network
    before = _stamp(ckpt, seq)
    assert before != _stamp(ckpt, seq.replace(height=32, width=40, intrinsics=K / 2, mask=np.ones((32, 40), bool)))
    assert before != _stamp(ckpt, seq.replace(native_window=(0, 0, 80, 64)))
    assert before != _stamp(ckpt, seq.replace(frame_paths=seq.frame_paths[:2], cam_from_world=np.tile(np.eye(4), (2, 1, 1)),
                                              visibility=[np.arange(2)] * 10))
    ckpt.write_bytes(b"w2")
    assert before != _stamp(ckpt, seq)


def test_run_dir_name_of_relative_inputs(tmp_path, monkeypatch):
    """input=. or input=.. named the run dir '' or '..': the outputs landed in the output root itself."""
    from endorecon.utils.resolvers import _stem

    seq = tmp_path / "patient_07" / "frames"
    seq.mkdir(parents=True)
    monkeypatch.chdir(seq)
    assert _stem(".") == "frames" and _stem("..") == "patient_07" and _stem("../") == "patient_07"
    assert _stem("clip.mp4") == "clip" and _stem("/a/b/seq_00") == "seq_00" and _stem(None) == "unnamed"


def test_latest_checkpoint_finds_multiruns_and_skips_unfinished(tmp_path):
    import os

    from omegaconf import OmegaConf

    from endorecon.tasks.reconstruct import latest_checkpoint

    cfg = OmegaConf.create({"paths": {"output_root": str(tmp_path)}})
    with pytest.raises(InputError, match=str(tmp_path / "train")):
        latest_checkpoint(cfg)
    single = tmp_path / "train" / "fold=0" / "iteration=1"
    multi = tmp_path / "train" / "multirun" / "2026-12-06_10-00-00" / "fold=1" / "iteration=0"
    unfinished = tmp_path / "train" / "fold=2" / "iteration=0"
    for i, d in enumerate((single, multi, unfinished)):
        (d / "checkpoints").mkdir(parents=True)
        (d / "checkpoints" / "last.ckpt").write_bytes(b"x")
        os.utime(d / "checkpoints" / "last.ckpt", (1000 + i, 1000 + i))
        if d is not unfinished:
            (d / "metrics.json").write_text("{}")
    assert latest_checkpoint(cfg) == multi / "checkpoints" / "last.ckpt"  # the newest finished one
    os.utime(single / "checkpoints" / "last.ckpt", (2000, 2000))  # by time, not by path
    assert latest_checkpoint(cfg) == single / "checkpoints" / "last.ckpt"


def test_report_lines_of_a_plain_fusion_mesh(tmp_path):
    """fusion=plain writes no std: the report said "per-vertex std" and "its std in the mesh"."""
    import open3d as o3d

    from endorecon.fusion.ply import write_mesh_ply
    from endorecon.tasks.reconstruct import _mesh_has_std, _uncertain_line

    box = o3d.t.geometry.TriangleMesh.from_legacy(o3d.geometry.TriangleMesh.create_box())
    write_mesh_ply(tmp_path / "plain.ply", box)
    box.vertex["std"] = o3d.core.Tensor(np.ones((len(box.vertex.positions), 1), np.float32))
    write_mesh_ply(tmp_path / "adaptive.ply", box)
    assert not _mesh_has_std(tmp_path / "plain.ply") and _mesh_has_std(tmp_path / "adaptive.ply")
    assert "no std" in _uncertain_line(None, "plain") and "its std in the mesh" in _uncertain_line(None, "adaptive")


def test_report_of_a_run_without_failure_detection_and_an_unrecorded_skipped_stage(tmp_path, monkeypatch):
    """With failure.enabled=false the report said "flagged by failure detection: 0 []", as if it had run; a
    stage skipped after an interrupted run (no timings.json yet) was timed as ~0 s and counted in the total."""
    import types

    from omegaconf import OmegaConf

    from endorecon.tasks import reconstruct as R

    monkeypatch.setattr(R, "save_depth_std_png", lambda *a, **k: None)
    class Seq(types.SimpleNamespace):
        def __len__(self):
            return 60

    seq = Seq(name="v", width=8, height=8, native_window=None, intrinsics=None, cam_from_world=None, units="sfm")
    summary = dict(registered=60, fused=60, flagged=[], n_flagged=0, excluded=[], all_flagged_fused=False, pgo={},
                   times={"fusion_s": 1.2, "failure_s": 0.1, "resfm_s": 0.0, "pgo_s": 0.0, "fusion2_s": 1.5})
    stages = {"sfm": dict(seconds=None, skipped=True, run_seconds=0.01),
              "failure detection + PGO + fusion": dict(seconds=2.8, skipped=False, run_seconds=2.8)}
    cfg = OmegaConf.create({"failure": {"enabled": False}, "fusion": {"name": "adaptive"}})
    report = R.write_report(tmp_path, seq, summary, None, None, None, stages, "ck", cfg, None).read_text()
    assert "failure detection: off (failure.enabled=false)" in report and "flagged by failure" not in report
    assert "| sfm | n/a |" in report and "| **total** | **" in report
    total = float(report.split("| **total** | **")[1].split("**")[0])
    assert total == pytest.approx(2.8 + stages["report"]["seconds"], abs=0.06)
    assert "off: not acted on" in report
