"""Mutation guards for the SfM stage's attempt loop, choice of the best attempt, settings checks and the
set-aside/restore of other settings' results (endorecon.sfm.stage).  No COLMAP run: the attempts and the
model loading are replaced where the choice is what is tested."""

import json
import os
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from PIL import Image

from endorecon.data.sequence import Sequence
from endorecon.sfm import colmap, stage


def _clip(tmp_path, n=4, h=24, w=32):
    d = tmp_path / "frames"
    d.mkdir(exist_ok=True)
    rng = np.random.default_rng(0)
    paths = []
    for i in range(n):
        p = d / f"{i:03d}.png"
        Image.fromarray(rng.integers(0, 255, (h, w, 3), dtype=np.uint8)).save(p)
        paths.append(p)
    K = np.array([[30.0, 0, (w - 1) / 2], [0, 30.0, (h - 1) / 2], [0, 0, 1]])
    return Sequence(name="c", frame_paths=paths, intrinsics=K, height=h, width=w, mask=np.ones((h, w), bool))


def _res(k, registered, models, points, passed):
    return dict(index=k, name=f"a{k}", registered=registered, frames=4, models=models, model_sizes=[registered],
                points=points, passed=passed, problems=[] if passed else ["too few"], num_features=0.0)


class Chosen(Exception):
    pass


def _solve_with(monkeypatch, tmp_path, results):
    """Run _solve with canned attempt results; returns (attempts run, folder of the model it chose)."""
    calls = []

    def fake_attempt(sfm_seq, names, cfg, k, out_dir):
        calls.append(k)
        return results[k]

    def fake_load(model_dir):
        raise Chosen(Path(model_dir).parent.name)

    monkeypatch.setattr(stage, "_run_attempt", fake_attempt)
    monkeypatch.setattr(colmap, "load_reconstruction", fake_load)
    cfg = stage._cfg({"attempts": [dict(name=f"a{k}") for k in range(len(results))], "max_size": 0})
    with pytest.raises(Chosen) as e:
        stage._solve(cfg, _clip(tmp_path), tmp_path / "out", list(range(len(results))), allow_partial=True)
    return calls, str(e.value)


def test_attempts_stop_at_the_first_pass(tmp_path, monkeypatch):
    calls, chosen = _solve_with(monkeypatch, tmp_path, [_res(0, 2, 1, 50, False), _res(1, 4, 1, 60, True),
                                                        _res(2, 4, 1, 900, True)])
    assert calls == [0, 1] and chosen == "01_a1"


def test_best_failed_attempt_most_registered_then_fewest_models(tmp_path, monkeypatch):
    calls, chosen = _solve_with(monkeypatch, tmp_path, [_res(0, 3, 1, 900, False), _res(1, 4, 2, 500, False),
                                                        _res(2, 4, 1, 100, False)])
    assert calls == [0, 1, 2] and chosen == "02_a2"


def _fake_result(out, seq, cfg=None, settings=None):
    out.mkdir(parents=True, exist_ok=True)
    for f in ("sequence.npz", "attempts.json"):
        (out / f).write_text("earlier")
    settings = settings or stage._settings(stage._cfg(cfg), seq)
    (out / "settings.json").write_text(json.dumps(settings, indent=2, sort_keys=True))


def test_other_intrinsics_or_rewritten_frames_are_not_complete(tmp_path):
    seq = _clip(tmp_path)
    out = tmp_path / "sfm"
    _fake_result(out, seq)
    assert stage.is_complete(None, seq, out)
    K = seq.intrinsics.copy()
    K[0, 0] *= 1.1  # a corrected focal length: COLMAP must run with it
    assert not stage.is_complete(None, seq.replace(intrinsics=K), out)
    # a frame overwritten with other content of the same byte count (a re-export): its time tells
    p = seq.frame_paths[1]
    st = p.stat()
    os.utime(p, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    assert not stage.is_complete(None, seq, out)


class Mapped(Exception):
    pass


def _stored_attempt(tmp_path, params_change=None, frames=100):
    cfg = stage._cfg({"min_points": 10})
    attempt = cfg["attempts"][0]
    adir = stage._attempt_dir(tmp_path, 0, attempt)
    adir.mkdir(parents=True)
    stored = dict(index=0, name=attempt["name"], params={**attempt, **(params_change or {})}, registered=frames,
                  frames=frames, models=1, model_sizes=[frames], points=500, registered_fraction=1.0)
    (adir / "result.json").write_text(json.dumps(stored))
    return cfg


def test_stored_attempt_with_other_hyperparameters_runs_again(tmp_path, monkeypatch):
    def mapping(*a, **k):
        raise Mapped

    monkeypatch.setattr(colmap, "run_mapping", mapping)
    names = [f"{i:06d}.png" for i in range(100)]
    seq = SimpleNamespace(intrinsics=np.eye(3))
    cfg = _stored_attempt(tmp_path / "same")
    assert stage._run_attempt(seq, names, cfg, 0, tmp_path / "same")["passed"]  # reused, COLMAP not run
    cfg = _stored_attempt(tmp_path / "other", {"peak_threshold": 0.01})
    with pytest.raises(Mapped):
        stage._run_attempt(seq, names, cfg, 0, tmp_path / "other")


def test_result_set_aside_by_a_killed_run_is_restored_first(tmp_path, monkeypatch):
    """A run with other settings moved the result into .other_settings and was killed: the next run with the
    earlier settings finds that result back in place and skips."""
    seq = _clip(tmp_path)
    out = tmp_path / "sfm"
    kept = out / ".other_settings"
    _fake_result(kept, seq)  # the earlier result, set aside
    _fake_result(out, seq, cfg={"max_size": 16})  # the killed run's settings (nothing else written yet)
    for f in ("sequence.npz", "attempts.json"):
        (out / f).unlink()

    def no_solve(*a, **k):
        raise AssertionError("SfM made again")

    monkeypatch.setattr(stage, "_solve", no_solve)
    stage.run(None, seq, out)
    assert (out / "sequence.npz").read_text() == "earlier" and not kept.exists()
    assert stage.is_complete(None, seq, out)


def test_mask_erosion_keeps_the_image_border(tmp_path):
    """The image border is not the rim of the field of view: a full mask stays full after erosion."""
    seq = _clip(tmp_path)
    cfg = stage._cfg({"max_size": 0, "mask_erode_px": 4})
    stage._prepare_images(seq, cfg, tmp_path / "out")
    assert (np.asarray(Image.open(tmp_path / "out" / "mask.png")) == 255).all()


# ------------------------------------------------------------------ colmap.py
from test_colmap_io import _random_sequence  # noqa: E402  (tests/sfm/test_colmap_io.py)

from endorecon.sfm.colmap import read_colmap_model, write_colmap_model  # noqa: E402
from endorecon.utils.errors import InputError  # noqa: E402


def test_model_images_named_with_a_folder_match_frames_by_file_name(tmp_path):
    """COLMAP models made from an image tree name images 'images/0001.png': they are matched by file name."""
    seq = _random_sequence()
    out = write_colmap_model(seq, tmp_path / "model", binary=False)
    lines = (out / "images.txt").read_text().splitlines(keepends=True)
    body = [i for i, ln in enumerate(lines) if ln.strip() and not ln.startswith("#")]
    for i in body[0::2]:  # image lines (each followed by its 2D points line)
        parts = lines[i].rstrip("\n").split(" ")
        parts[-1] = "sub/" + parts[-1]
        lines[i] = " ".join(parts) + "\n"
    (out / "images.txt").write_text("".join(lines))
    back = read_colmap_model(out, seq.frame_paths)
    assert back.registered.tolist() == seq.registered.tolist()
    np.testing.assert_allclose(back.cam_from_world[seq.registered], seq.cam_from_world[seq.registered], atol=1e-9)


def test_model_with_two_cameras_is_refused(tmp_path):
    seq = _random_sequence()
    out = write_colmap_model(seq, tmp_path / "model", binary=False)
    with open(out / "cameras.txt", "a") as f:
        f.write("2 PINHOLE 64 48 80 80 32 24\n")
    with pytest.raises(InputError, match="2 cameras"):
        read_colmap_model(out, seq.frame_paths)


def test_mapping_gets_the_intrinsics_in_the_corner_convention(tmp_path, monkeypatch):
    """COLMAP is handed cx + 0.5, cy + 0.5 (its pixel (0, 0) is the top-left corner)."""
    seen = {}

    def extract(db, image_dir, image_names=None, reader_options=None, **k):
        seen["params"] = [float(v) for v in reader_options.camera_params.split(",")]
        raise Mapped

    monkeypatch.setattr(colmap.pycolmap, "extract_features", extract)
    K = np.array([[55.0, 0.0, 31.25], [0.0, 57.0, 23.75], [0.0, 0.0, 1.0]])
    with pytest.raises(Mapped):
        colmap.run_mapping(tmp_path, ["a.png"], None, K, {}, tmp_path / "work")
    assert seen["params"] == [55.0, 57.0, 31.75, 24.25]


def test_simple_pinhole_model_has_fy_equal_to_fx(tmp_path):
    seq = _random_sequence()
    out = write_colmap_model(seq, tmp_path / "model", binary=False)
    (out / "cameras.txt").write_text("1 SIMPLE_PINHOLE 64 48 55 31.75 24.25\n")
    K = read_colmap_model(out, seq.frame_paths).intrinsics
    np.testing.assert_allclose(K, [[55.0, 0, 31.25], [0, 55.0, 23.75], [0, 0, 1]], atol=1e-12)


# ------------------------------------------------------------------ __main__.py (CLI inputs)
from endorecon.data.sequence import write_camera_json  # noqa: E402
from endorecon.sfm.__main__ import build_sequence  # noqa: E402


def _frames_dir(tmp_path, h=24, w=32):
    seq = _clip(tmp_path, h=h, w=w)
    return seq.frame_paths[0].parent, seq


def test_cli_refuses_a_camera_json_for_another_frame_size(tmp_path):
    frames, seq = _frames_dir(tmp_path)
    write_camera_json(tmp_path / "camera.json", seq.intrinsics * [[2], [2], [1]], 48, 64)
    with pytest.raises(InputError, match="camera.json is for 64x48"):
        build_sequence({"input": str(frames), "camera": str(tmp_path / "camera.json")})


def test_cli_mask_overrides_the_sequence_folders_mask(tmp_path):
    frames, seq = _frames_dir(tmp_path)
    folder = frames.parent
    write_camera_json(folder / "camera.json", seq.intrinsics, 24, 32)
    Image.fromarray(np.full((24, 32), 255, np.uint8)).save(folder / "mask.png")
    fixed = np.full((24, 32), 255, np.uint8)
    fixed[:6] = 0  # a text overlay masked out
    Image.fromarray(fixed).save(tmp_path / "fixed.png")
    got = build_sequence({"input": str(folder), "mask": str(tmp_path / "fixed.png")})
    assert got.mask[:6].sum() == 0 and got.mask[6:].all()
