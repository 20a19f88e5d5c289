"""Mutation guards for ensure_dataset's settings comparison (endorecon/phantom/generate.py)."""

import json

import pytest

import importlib

gen = importlib.import_module("endorecon.phantom.generate")
from endorecon.phantom import ensure_dataset

H, W = 48, 64


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    cfg = dict(root=str(tmp_path_factory.mktemp("ens") / "c"), patients=1, frames=2, height=H, width=W, seed=0)
    root = ensure_dataset(cfg)
    return cfg, root, json.loads((root / "dataset.json").read_text())


def _other_seqs(meta):
    meta["patients"][0]["sequences"] = meta["patients"][0]["sequences"] * 2


@pytest.mark.parametrize("change", [
    lambda m: m.update(seed=m["seed"] + 1), lambda m: m.update(fov_deg=m["fov_deg"] + 5.0),
    lambda m: m.update(motion_blur=3), lambda m: m.update(frames=m["frames"] + 1),
    lambda m: m.update(height=m["height"] * 2), lambda m: m.update(width=m["width"] * 2),
    lambda m: m.update(mesh="/elsewhere/cavity.ply"), lambda m: m.update(waypoints=[[0, 0, 0], [0, 0, 5.0]]),
    _other_seqs, lambda m: m.update(patients=m["patients"] * 2),
], ids=["seed", "fov_deg", "motion_blur", "frames", "height", "width", "mesh", "waypoints", "sequences", "patients"])
def test_a_phantom_made_with_another_setting_is_made_again(made, monkeypatch, change):
    """Each generator setting recorded in dataset.json is compared: a phantom that differs in any one of them
    is regenerated, not reused as this configuration's data."""
    cfg, root, meta = made
    other = json.loads(json.dumps(meta))
    change(other)
    calls = []
    defaults = gen.generator_defaults()
    monkeypatch.setattr(gen, "generator_defaults", lambda: defaults)
    monkeypatch.setattr(gen, "generate", lambda out, **kw: calls.append(kw) or out)
    (root / "dataset.json").write_text(json.dumps(other))
    try:
        ensure_dataset(cfg)
    finally:
        (root / "dataset.json").write_text(json.dumps(meta))
    assert len(calls) == 1
    ensure_dataset(cfg)  # the recorded settings again: reused
    assert len(calls) == 1
