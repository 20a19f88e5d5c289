"""EndoDataModule: pairs, folds, batch contract, determinism, augmentation consistency, prediction."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from PIL import Image

from endorecon.data.datamodule import PAIR_KEYS, EndoDataModule, PreparedSequence, make_pairs, split_validation
from endorecon.data.sequence import Sequence
from endorecon.data.sparse import build_sparse_cache
from endorecon.geometry import flow_from_depth
from endorecon.utils.errors import InputError

H, W, N = 48, 64, 10
K = np.array([[50.0, 0.0, 31.1], [0.0, 46.0, 23.4], [0.0, 0.0, 1.0]])
NO_AUG = {"enabled": False}


def make_prepared(root, patient: int, rng, sim: bool = False, unregistered=(), excluded=()) -> PreparedSequence:
    d = root / f"p{patient}"
    d.mkdir()
    paths = []
    for k in range(N):
        p = d / f"{k:03d}.png"
        Image.fromarray((rng.random((H, W, 3)) * 255).astype(np.uint8)).save(p)
        paths.append(p)
    T = np.stack([np.eye(4)] * N)
    for k in range(N):
        a = np.radians(0.5 * k)
        T[k, :3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
        T[k, :3, 3] = [-0.15 * k, 0.05 * k, 0.1 * k]
    for k in unregistered:
        T[k] = np.nan
    P = 300
    X = np.stack([rng.uniform(-5, 5, P), rng.uniform(-4, 4, P), rng.uniform(9, 13, P)], 1)
    vis = [np.arange(N)] * P
    mask = np.ones((H, W), bool)
    mask[:4] = False
    seq = Sequence(name=f"p{patient}", frame_paths=paths, intrinsics=K, height=H, width=W, mask=mask,
                   cam_from_world=T, points_xyz=X, visibility=vis, patient=patient)  # fmt: skip
    sim_depth = (rng.uniform(5, 10, (N, H, W)) * (rng.random((N, H, W)) > 0.2)).astype(np.float32) if sim else None
    ex = np.zeros(N, bool)
    ex[list(excluded)] = True
    return PreparedSequence(seq=seq, cache=build_sparse_cache(seq), sim_depth=sim_depth, excluded=ex)


@pytest.fixture(scope="module")
def prepared(tmp_path_factory):
    root = tmp_path_factory.mktemp("seqs")
    rng = np.random.default_rng(0)
    return [
        make_prepared(root, 0, rng, sim=True, unregistered=(3,), excluded=(5,)),
        make_prepared(root, 1, rng),
        make_prepared(root, 2, rng),
    ]


def dm(prepared, **kw) -> EndoDataModule:
    fold = kw.pop("fold", 1)
    cfg = dict(height=H, width=W, batch_size=4, num_workers=0, min_interval=1, max_interval=3,
               val_fraction=0.3, seed=0, augment=NO_AUG, name="phantom", root="/nowhere")  # fmt: skip
    return EndoDataModule(cfg, prepared, fold=fold, patients_with_ct=[1, 2], **kw)


def first_batches(loader, n=2):
    out = []
    for k, b in enumerate(loader):
        out.append(b)
        if k + 1 == n:
            break
    return out


def test_make_pairs_and_validation_split():
    pairs = make_pairs(np.array([0, 1, 2, 4, 7]), 1, 2)
    assert {tuple(p) for p in pairs} == {(0, 1), (1, 0), (0, 2), (2, 0), (1, 2), (2, 1), (2, 4), (4, 2)}
    usable = np.ones(10, bool)
    usable[[2, 9]] = False
    tr, va = split_validation(usable, 0.25)
    assert list(va) == [7, 8] and list(tr) == [0, 1, 3, 4, 5, 6]
    assert len(split_validation(usable, 0.0)[1]) == 0
    assert list(split_validation(usable, 0.1, min_interval=2)[1]) == [6, 7, 8]  # widened to hold a pair
    assert len(split_validation(usable, 0.1, min_interval=5)[1]) == 0  # would starve training


def test_batch_contract(prepared):
    m = dm(prepared)
    b = next(iter(m.train_dataloader()))
    assert set(b) == set(PAIR_KEYS)
    B = 4
    for k in ("image_i", "image_j"):
        assert b[k].shape == (B, 3, H, W) and b[k].dtype == torch.float32
        assert 0 <= b[k].min() and b[k].max() <= 1
    for k in ("mask_i", "mask_j", "sparse_valid_i", "sparse_valid_j", "sparse_flow_valid_ij",
              "sparse_flow_valid_ji", "sim_valid_i", "sim_valid_j"):  # fmt: skip
        assert b[k].shape == (B, 1, H, W) and b[k].dtype == torch.bool, k
    for k in ("sparse_depth_i", "sparse_depth_j", "sim_depth_i", "sim_depth_j"):
        assert b[k].shape == (B, 1, H, W) and b[k].dtype == torch.float32, k
    for k in ("sparse_flow_ij", "sparse_flow_ji"):
        assert b[k].shape == (B, 2, H, W) and b[k].dtype == torch.float32
    assert b["K"].shape == (B, 3, 3) and b["K"].dtype == torch.float32
    assert b["cam_j_from_cam_i"].shape == (B, 4, 4) and b["cam_j_from_cam_i"].dtype == torch.float32
    for k in ("index_i", "index_j"):
        assert b[k].shape == (B,) and b[k].dtype == torch.long
    assert b["has_sim"].shape == (B,) and b["has_sim"].dtype == torch.bool
    assert (b["sparse_depth_i"][~b["sparse_valid_i"]] == 0).all()


def test_unaugmented_batch_equals_cache_and_poses(prepared):
    m = dm(prepared)
    m.setup()
    ds = m.train_set
    for k in range(0, len(ds), 7):
        s, i, j = ds.pairs[k]
        p = prepared[s]
        item = ds[k]
        d, v = p.cache.depth_map(i)
        assert torch.equal(item["sparse_depth_i"], torch.from_numpy(d)) and torch.equal(item["sparse_valid_i"], torch.from_numpy(v))
        f, fv = p.cache.flow_map(i, j)
        assert torch.equal(item["sparse_flow_valid_ij"], torch.from_numpy(fv)) and fv.sum() > 50
        torch.testing.assert_close(item["sparse_flow_ij"], torch.from_numpy(f))
        f, fv = p.cache.flow_map(j, i)
        torch.testing.assert_close(item["sparse_flow_ji"], torch.from_numpy(f))
        T = p.seq.cam_from_world
        torch.testing.assert_close(item["cam_j_from_cam_i"], torch.from_numpy(T[j] @ np.linalg.inv(T[i])).float())
        img = torch.from_numpy(np.array(Image.open(p.seq.frame_paths[j]))).permute(2, 0, 1).float() / 255
        torch.testing.assert_close(item["image_j"], img)
        assert (int(item["index_i"]), int(item["index_j"])) == (i, j)
        assert bool(item["has_sim"]) == (p.sim_depth is not None)
        if p.sim_depth is not None:
            assert torch.equal(item["sim_depth_i"][0], torch.from_numpy(p.sim_depth[i]))
            assert torch.equal(item["sim_valid_i"][0], torch.from_numpy(p.sim_depth[i] > 0))
        else:
            assert not item["sim_valid_i"].any() and not item["sim_depth_i"].any()


def test_pairs_respect_interval_registration_exclusion_and_fold(prepared):
    m = dm(prepared, min_interval=2, max_interval=3)
    for pairs in (m.train_pairs, m.val_pairs, m.test_pairs):
        d = np.abs(pairs[:, 1] - pairs[:, 2])
        assert ((d >= 2) & (d <= 3)).all()
        assert {(s, j, i) for s, i, j in pairs} == {tuple(p) for p in pairs}  # both orders
    assert set(m.test_pairs[:, 0]) == {1}
    assert set(m.train_pairs[:, 0]) == {0, 2} and set(m.val_pairs[:, 0]) <= {0, 2}
    s0 = m.train_pairs[m.train_pairs[:, 0] == 0][:, 1:]
    assert not np.isin(s0, [3, 5]).any()  # unregistered 3, excluded 5
    for s in (0, 2):  # validation frames are a block at the end, disjoint from training frames
        tr = set(m.train_pairs[m.train_pairs[:, 0] == s][:, 1:].ravel())
        va = set(m.val_pairs[m.val_pairs[:, 0] == s][:, 1:].ravel())
        assert va and not tr & va and min(va) > max(tr)
    assert len(dm(prepared, fold=None).test_pairs) == 0


def test_bad_fold_and_config(prepared):
    with pytest.raises(InputError, match=r"fold=0.*\n.*\[1, 2\]"):
        dm(prepared, fold=0)
    with pytest.raises(InputError, match="fold=7"):
        dm(prepared, fold=7)
    with pytest.raises(InputError, match="max_interval"):
        dm(prepared, min_interval=4, max_interval=2)
    with pytest.raises(InputError, match="resize"):
        dm(prepared, height=32)
    with pytest.raises(InputError, match="no prepared sequence of patient 2"):
        dm(prepared[:2], fold=2)
    with pytest.raises(InputError, match="unknown key"):
        dm(prepared, augment={"p_fip": 1.0})
    p = prepared[0]
    with pytest.raises(InputError, match="sim_depth"):
        PreparedSequence(seq=p.seq, cache=p.cache, sim_depth=np.zeros((N, H, W + 1), np.float32))


def test_config_file_drives_the_module(prepared):
    from pathlib import Path

    from omegaconf import OmegaConf

    cfg = OmegaConf.load(Path(__file__).parents[2] / "conf" / "data" / "default.yaml")
    assert (cfg.height, cfg.width) == (128, 160)
    cfg.height, cfg.width = H, W
    m = EndoDataModule(cfg, prepared, fold=2, patients_with_ct=[1, 2], num_workers=0)
    assert m.batch_size == cfg.batch_size and m.max_interval == cfg.max_interval and m.seed == cfg.seed
    assert m.augment.p_flip == cfg.augment.p_flip and m.augment.blur_sigma == tuple(cfg.augment.blur_sigma)
    assert set(m.test_pairs[:, 0]) == {2}
    with pytest.raises(TypeError, match="batchsize"):
        EndoDataModule(cfg, prepared, fold=2, patients_with_ct=[1, 2], batchsize=3)


def _equal(a, b) -> bool:
    return all(torch.equal(x[k], y[k]) for x, y in zip(a, b) for k in PAIR_KEYS)


def test_deterministic_with_seed_and_workers(prepared):
    aug = {"enabled": True, "p_flip": 0.5, "p_rotate": 0.5, "p_color": 1.0, "p_noise": 1.0}
    a = first_batches(dm(prepared, augment=aug, seed=3).train_dataloader())
    b = first_batches(dm(prepared, augment=aug, seed=3).train_dataloader())
    c = first_batches(dm(prepared, augment=aug, seed=4).train_dataloader())
    assert _equal(a, b) and not _equal(a, c)
    loader = dm(prepared, augment=aug, seed=3, num_workers=2).train_dataloader()
    assert loader.persistent_workers
    w = first_batches(loader)
    assert _equal(a, w)
    # epochs differ, and set_epoch replays an epoch exactly (resume)
    m = dm(prepared, augment=aug, seed=3)
    loader = m.train_dataloader()
    e0 = first_batches(loader)
    e1 = first_batches(loader)
    assert _equal(e0, a) and not _equal(e0, e1)
    loader.sampler.set_epoch(1)
    assert _equal(first_batches(loader), e1)


def test_augmented_batches_stay_geometrically_consistent(prepared):
    """Flow at sparse pixels == flow implied by the sparse depth there with the batch's (augmented) K and pose.

    Points sit within half a pixel of the pixel centre where they are rasterised, so the two differ by at
    most half a pixel times the flow's spatial derivative (small for these small motions)."""
    aug = {"enabled": True, "p_flip": 0.5, "p_rotate": 1.0, "max_rotation_deg": 20, "p_color": 0}
    m = dm(prepared, augment=aug, batch_size=8)
    flipped = 0
    for b in first_batches(m.train_dataloader(), 3):
        ref, z = flow_from_depth(b["sparse_depth_i"], b["K"], b["cam_j_from_cam_i"])
        ok = b["sparse_flow_valid_ij"] & b["sparse_valid_i"]
        assert ok.sum() > 100
        err = (ref - b["sparse_flow_ij"]).norm(dim=1, keepdim=True)[ok]
        assert err.max() < 0.08, float(err.max())  # measured 0.033 px max
        flipped += int((b["K"][:, 0, 2] != float(K[0, 2])).sum())
    assert flipped > 0
    # validation never augments: its items are the plain cache maps and the original K
    vb = next(iter(m.val_dataloader()))
    assert torch.allclose(vb["K"], torch.from_numpy(K).float().expand(len(vb["K"]), 3, 3))
    s, i, j = m.val_pairs[0]
    item = m.val_set[0]
    assert torch.equal(item["sparse_depth_i"], torch.from_numpy(prepared[s].cache.depth_map(i)[0]))
    assert torch.equal(item["sparse_flow_valid_ij"], torch.from_numpy(prepared[s].cache.flow_map(i, j)[1]))


def test_predict_yields_every_frame_once(prepared):
    m = dm(prepared, batch_size=4)
    loaders = m.predict_dataloader()
    assert len(loaders) == 3
    seen = []
    for b in loaders[0]:
        seen += b["index"].tolist()
        for k, i in enumerate(b["index"].tolist()):
            d, v = prepared[0].cache.depth_map(i)
            assert torch.equal(b["sparse_depth"][k], torch.from_numpy(d))
            assert bool(b["registered"][k]) == (i != 3) and bool(b["excluded"][k]) == (i == 5)
        assert b["image"].shape[1:] == (3, H, W) and b["K"].shape[1:] == (3, 3)
    assert seen == list(range(N))
    assert m.sequences("test") == [1] and m.sequences("train") == [0, 2]


def test_lightning_fit_consumes_the_module(prepared):
    import lightning as L

    class Tiny(L.LightningModule):
        def __init__(self):
            super().__init__()
            self.w = torch.nn.Parameter(torch.zeros(1))
            self.seen = []

        def training_step(self, batch, _):
            self.seen.append(batch["index_i"].clone())
            return ((batch["image_i"].mean() - self.w) ** 2).sum()

        def validation_step(self, batch, _):
            self.log("val", batch["sparse_depth_i"].sum())

        def configure_optimizers(self):
            return torch.optim.SGD(self.parameters(), lr=0.1)

    model = Tiny()
    trainer = L.Trainer(max_epochs=2, limit_train_batches=2, limit_val_batches=1, logger=False,
                        enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False)  # fmt: skip
    trainer.fit(model, datamodule=dm(prepared, augment={"enabled": True}))
    assert len(model.seen) == 4
    assert not torch.equal(model.seen[0], model.seen[2])  # epoch 1 reshuffled
