"""The training data: frame pairs with sparse SfM supervision, per-fold splits.

:class:`EndoDataModule` turns a list of :class:`PreparedSequence` (a sequence at
training resolution with poses, its :class:`~endorecon.data.sparse.SparseCache`,
optional simulated depth from the previous bootstrapping iteration and the
frames flagged by failure detection) into Lightning dataloaders.

Split (leave-one-patient-out, as in the paper): ``fold=k`` holds out patient k
(one of the patients with CT) as the **test** set and trains on every other
sequence.  **Validation** is a deterministic part of the training sequences:
the last ``val_fraction`` of each training sequence's usable frames (a
contiguous block at the end, so that validation frames are not interleaved
with near-identical training frames); training pairs use the other frames,
validation pairs lie inside the block, no pair crosses it.

Pairs: (i, j) of the same sequence, both registered and not excluded, with
``min_interval <= |i − j| <= max_interval`` (frame-index units), both orders.

Determinism: the training sampler draws, per epoch, a permutation and one seed
per sample from ``(seed, epoch)``; the dataset seeds all augmentation of a
sample from that seed.  Batches are therefore identical for the same seed
whatever ``num_workers`` is, and Lightning's ``set_epoch`` makes resumed runs
continue the same stream.

Batch (training/validation/test), all float tensors float32::

    image_i, image_j              (B,3,H,W) in [0,1]
    mask_i, mask_j                (B,1,H,W) bool
    K                             (B,3,3)  pixel-centre (after augmentation)
    cam_j_from_cam_i              (B,4,4)
    sparse_depth_i, sparse_depth_j, sparse_valid_i, sparse_valid_j   (B,1,H,W), 0 = none
    sparse_flow_ij, sparse_flow_ji (B,2,H,W) pixels, at the source frame's pixels
    sparse_flow_valid_ij, sparse_flow_valid_ji (B,1,H,W) bool
    sim_depth_i, sim_depth_j, sim_valid_i, sim_valid_j  (B,1,H,W) (0/False without simulation)
    index_i, index_j              (B,) long frame indices in their sequence
    has_sim                       (B,) bool

Prediction (:meth:`EndoDataModule.predict_dataloader`) yields every frame of a
sequence once: ``image, mask, K, sparse_depth, sparse_valid, cam_from_world``
(NaN when unregistered), ``index``, ``registered``, ``excluded``.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Iterator, Mapping

import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, Sampler

from endorecon.data.augment import AugmentConfig, PairSample, augment_pair
from endorecon.data.sequence import Sequence
from endorecon.data.sparse import SparseCache, inside_image, rasterize_points
from endorecon.utils.errors import InputError

PAIR_KEYS = (
    "image_i", "image_j", "mask_i", "mask_j", "K", "cam_j_from_cam_i",
    "sparse_depth_i", "sparse_depth_j", "sparse_valid_i", "sparse_valid_j",
    "sparse_flow_ij", "sparse_flow_valid_ij", "sparse_flow_ji", "sparse_flow_valid_ji",
    "sim_depth_i", "sim_depth_j", "sim_valid_i", "sim_valid_j",
    "index_i", "index_j", "has_sim",
)  # fmt: skip


@dataclasses.dataclass
class PreparedSequence:
    """A sequence ready for training.

    Attributes:
        seq: the sequence at training resolution, with poses (NaN rows = unregistered).
        cache: its sparse cache built at that resolution.
        sim_depth: (N, H, W) float32 simulated depth of the previous iteration, or None.
        sim_valid: (N, H, W) bool, or None (then ``sim_depth > 0``).
        excluded: (N,) bool frames flagged by failure detection (never sampled), or None.
    """

    seq: Sequence
    cache: SparseCache
    sim_depth: np.ndarray | None = None
    sim_valid: np.ndarray | None = None
    excluded: np.ndarray | None = None

    def __post_init__(self) -> None:
        N, H, W = len(self.seq), self.seq.height, self.seq.width
        if (self.cache.height, self.cache.width, self.cache.num_frames) != (H, W, N):
            raise InputError(
                f"sequence {self.seq.name!r}: sparse cache is for {self.cache.num_frames} frames at "
                f"{self.cache.width}x{self.cache.height}, the sequence has {N} at {W}x{H}",
                fix="rebuild the cache with build_sparse_cache(resized sequence)",
            )
        if not np.allclose(self.cache.intrinsics, self.seq.intrinsics, rtol=0, atol=1e-6):
            raise InputError(f"sequence {self.seq.name!r}: sparse cache intrinsics differ", fix="rebuild the cache")
        if self.sim_depth is not None:
            self.sim_depth = np.asarray(self.sim_depth, dtype=np.float32)
            if self.sim_depth.shape != (N, H, W):
                raise InputError(
                    f"sequence {self.seq.name!r}: sim_depth is {self.sim_depth.shape}, expected {(N, H, W)}",
                    fix="render simulated depth at the training resolution",
                )
            if self.sim_valid is None:
                self.sim_valid = self.sim_depth > 0
        if self.sim_valid is not None:
            if self.sim_depth is None:
                raise InputError(f"sequence {self.seq.name!r}: sim_valid given without sim_depth")
            self.sim_valid = np.asarray(self.sim_valid, dtype=bool)
            if self.sim_valid.shape != (N, H, W):
                raise InputError(f"sequence {self.seq.name!r}: sim_valid is {self.sim_valid.shape}, expected {(N, H, W)}")
        if self.excluded is None:
            self.excluded = np.zeros(N, dtype=bool)
        self.excluded = np.asarray(self.excluded, dtype=bool)
        if self.excluded.shape != (N,):
            raise InputError(f"sequence {self.seq.name!r}: excluded is {self.excluded.shape}, expected ({N},)")

    @property
    def usable(self) -> np.ndarray:
        """(N,) bool: registered and not excluded."""
        return self.seq.registered & ~self.excluded


# -------------------------------------------------------------------- pairs
def make_pairs(frames: np.ndarray, min_interval: int, max_interval: int) -> np.ndarray:
    """All ordered pairs (i, j) of ``frames`` (sorted frame indices) with min <= |i − j| <= max: (P, 2) int64."""
    frames = np.sort(np.asarray(frames, dtype=np.int64))
    if len(frames) < 2:
        return np.zeros((0, 2), dtype=np.int64)
    d = frames[None, :] - frames[:, None]
    a, b = np.nonzero((np.abs(d) >= min_interval) & (np.abs(d) <= max_interval))
    return np.stack([frames[a], frames[b]], axis=1)


def split_validation(usable: np.ndarray, val_fraction: float, min_interval: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Usable frames -> (train frames, validation frames): the last ``val_fraction`` of them go to validation.

    The block is widened to ``min_interval + 1`` frames so that it holds at least one pair; if that
    would leave fewer than ``min_interval + 1`` training frames, there is no validation block.
    """
    frames = np.flatnonzero(usable)
    n_val = int(round(val_fraction * len(frames)))
    if n_val == 0:
        return frames, frames[:0]
    n_val = max(n_val, min_interval + 1)
    if len(frames) - n_val < min_interval + 1:
        return frames, frames[:0]
    return frames[:-n_val], frames[-n_val:]


# ------------------------------------------------------------------ sampler
class EpochSampler(Sampler):
    """Yields ``(index, sample_seed)``; order and seeds are a function of (seed, epoch) only.

    Each ``__iter__`` uses the current epoch and then advances it; Lightning's
    ``set_epoch`` (called before every epoch) overrides it, so a resumed run
    replays the same stream.
    """

    def __init__(self, n: int, seed: int, shuffle: bool = True):
        self.n, self.seed, self.shuffle, self.epoch = int(n), int(seed), bool(shuffle), 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return self.n

    def __iter__(self) -> Iterator[tuple[int, int]]:
        rng = np.random.default_rng([self.seed, self.epoch])
        order = rng.permutation(self.n) if self.shuffle else np.arange(self.n)
        seeds = rng.integers(0, 2**63 - 1, size=self.n, dtype=np.int64)
        self.epoch += 1
        return iter([(int(i), int(s)) for i, s in zip(order, seeds)])


def _worker_init(worker_id: int) -> None:
    # Workers share 2 cores with everything else: one intra-op thread each.
    torch.set_num_threads(1)
    np.random.seed(torch.initial_seed() % 2**32)


# ------------------------------------------------------------------ datasets
class _FrameStore:
    """Decoded frames of the prepared sequences, kept in memory up to ``max_bytes`` (per process)."""

    def __init__(self, prepared: list[PreparedSequence], max_bytes: int):
        self.prepared = prepared
        self.max_bytes = int(max_bytes)
        self.frames: dict[tuple[int, int], np.ndarray] = {}
        self.bytes = 0

    def get(self, s: int, i: int) -> torch.Tensor:
        img = self.frames.get((s, i))
        if img is None:
            img = self.prepared[s].seq.load_frame(i)
            if self.bytes + img.nbytes <= self.max_bytes:
                self.frames[(s, i)] = img
                self.bytes += img.nbytes
        return torch.tensor(img).permute(2, 0, 1).float() / 255.0  # copy: PIL arrays are read-only


def _sim(p: PreparedSequence, i: int) -> tuple[torch.Tensor | None, torch.Tensor | None]:
    if p.sim_depth is None:
        return None, None
    return torch.from_numpy(p.sim_depth[i][None].copy()), torch.from_numpy(p.sim_valid[i][None].copy())


def load_pair(store: _FrameStore, s: int, i: int, j: int) -> PairSample:
    """The un-augmented pair (i, j) of prepared sequence ``s``."""
    p = store.prepared[s]
    T = p.seq.cam_from_world
    mask = torch.from_numpy(p.seq.mask[None].copy())
    ids_i, uv_i, z_i = p.cache.frame_points(i)
    ids_j, uv_j, z_j = p.cache.frame_points(j)
    sdi, svi = _sim(p, i)
    sdj, svj = _sim(p, j)
    return PairSample(
        image_i=store.get(s, i),
        image_j=store.get(s, j),
        mask_i=mask,
        mask_j=mask.clone(),
        K=p.seq.intrinsics.copy(),
        cam_j_from_cam_i=T[j] @ np.linalg.inv(T[i]),
        ids_i=ids_i, uv_i=uv_i, z_i=z_i,
        ids_j=ids_j, uv_j=uv_j, z_j=z_j,
        sim_depth_i=sdi, sim_depth_j=sdj, sim_valid_i=svi, sim_valid_j=svj,
    )  # fmt: skip


def pair_to_batch(sample: PairSample, index_i: int, index_j: int) -> dict[str, torch.Tensor]:
    """Rasterise a pair's point sets into the batch dict (one element, no batch dimension)."""
    H, W = sample.image_i.shape[-2:]
    mi, mj = sample.mask_i[0].numpy(), sample.mask_j[0].numpy()
    di, vi = rasterize_points(sample.uv_i, sample.z_i[:, None], sample.z_i, H, W, mi)
    dj, vj = rasterize_points(sample.uv_j, sample.z_j[:, None], sample.z_j, H, W, mj)
    _, a, b = np.intersect1d(sample.ids_i, sample.ids_j, assume_unique=True, return_indices=True)
    uvi, uvj, zi, zj = sample.uv_i[a], sample.uv_j[b], sample.z_i[a], sample.z_j[b]
    both = inside_image(uvi, H, W, mi) & inside_image(uvj, H, W, mj)
    uvi, uvj, zi, zj = uvi[both], uvj[both], zi[both], zj[both]
    fij, fvij = rasterize_points(uvi, uvj - uvi, zi, H, W)
    fji, fvji = rasterize_points(uvj, uvi - uvj, zj, H, W)
    has_sim = sample.sim_depth_i is not None
    zeros = torch.zeros(1, H, W)
    no = torch.zeros(1, H, W, dtype=torch.bool)
    t = torch.from_numpy
    return {
        "image_i": sample.image_i.float(),
        "image_j": sample.image_j.float(),
        "mask_i": sample.mask_i.bool(),
        "mask_j": sample.mask_j.bool(),
        "K": torch.as_tensor(sample.K, dtype=torch.float32),
        "cam_j_from_cam_i": torch.as_tensor(sample.cam_j_from_cam_i, dtype=torch.float32),
        "sparse_depth_i": t(di),
        "sparse_depth_j": t(dj),
        "sparse_valid_i": t(vi),
        "sparse_valid_j": t(vj),
        "sparse_flow_ij": t(fij),
        "sparse_flow_valid_ij": t(fvij),
        "sparse_flow_ji": t(fji),
        "sparse_flow_valid_ji": t(fvji),
        "sim_depth_i": sample.sim_depth_i.float() if has_sim else zeros,
        "sim_depth_j": sample.sim_depth_j.float() if has_sim else zeros.clone(),
        "sim_valid_i": sample.sim_valid_i.bool() if has_sim else no,
        "sim_valid_j": sample.sim_valid_j.bool() if has_sim else no.clone(),
        "index_i": torch.tensor(index_i, dtype=torch.long),
        "index_j": torch.tensor(index_j, dtype=torch.long),
        "has_sim": torch.tensor(has_sim),
    }


class PairDataset(Dataset):
    """Frame pairs ``(sequence, i, j)``; items are keyed by ``(index, sample_seed)`` (see :class:`EpochSampler`)
    or by a plain index (then seed 0)."""

    def __init__(
        self,
        prepared: list[PreparedSequence],
        pairs: np.ndarray,
        augment: AugmentConfig | None = None,
        cache_bytes: int = 512 * 2**20,
    ):
        self.pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 3)  # (seq, i, j)
        self.augment = augment if augment is not None and augment.enabled else None
        self.store = _FrameStore(prepared, cache_bytes)

    def __len__(self) -> int:
        return len(self.pairs)

    def __getitem__(self, key: int | tuple[int, int]) -> dict[str, torch.Tensor]:
        idx, seed = key if isinstance(key, tuple) else (int(key), 0)
        s, i, j = (int(v) for v in self.pairs[idx])
        sample = load_pair(self.store, s, i, j)
        if self.augment is not None:
            sample = augment_pair(sample, np.random.default_rng([seed, idx]), self.augment)
        return pair_to_batch(sample, i, j)


class FrameDataset(Dataset):
    """Every frame of one prepared sequence once, for inference."""

    def __init__(self, prepared: PreparedSequence, cache_bytes: int = 0):
        self.p = prepared
        self.store = _FrameStore([prepared], cache_bytes)

    def __len__(self) -> int:
        return len(self.p.seq)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        p = self.p
        depth, valid = p.cache.depth_map(i)
        return {
            "image": self.store.get(0, i),
            "mask": torch.from_numpy(p.seq.mask[None].copy()),
            "K": torch.as_tensor(p.seq.intrinsics, dtype=torch.float32),
            "sparse_depth": torch.from_numpy(depth),
            "sparse_valid": torch.from_numpy(valid),
            "cam_from_world": torch.as_tensor(p.seq.cam_from_world[i], dtype=torch.float32),
            "index": torch.tensor(i, dtype=torch.long),
            "registered": torch.tensor(bool(p.seq.registered[i])),
            "excluded": torch.tensor(bool(p.excluded[i])),
        }


def frame_dataloader(prepared: PreparedSequence, batch_size: int = 8, num_workers: int = 0) -> DataLoader:
    """Every frame of ``prepared`` once, in order (inference after training)."""
    return DataLoader(
        FrameDataset(prepared),
        batch_size=batch_size,
        shuffle=False,
        num_workers=num_workers,
        worker_init_fn=_worker_init if num_workers > 0 else None,
    )


# --------------------------------------------------------------- datamodule
DEFAULTS: dict[str, Any] = dict(
    height=128,
    width=160,
    batch_size=8,
    num_workers=0,
    min_interval=1,
    max_interval=5,
    val_fraction=0.1,
    seed=0,
    augment=None,
    cache_frames_mb=512,
    drop_last=False,
)


class EndoDataModule(L.LightningDataModule):
    """Pairs for training/validation/test of one fold, frames for prediction.

    Args:
        cfg: the ``data`` config (``conf/data/default.yaml``) or None; keys it does not
            know (e.g. the phantom generator's) are ignored.
        prepared: the prepared sequences of all patients (``seq.patient`` set).
        fold: patient held out for test, one of ``patients_with_ct``; None = no test split.
        patients_with_ct: patients that have a CT (the allowed folds).
        **overrides: any of the config keys, taking precedence over ``cfg``.

    Config keys (defaults in :data:`DEFAULTS`):
        height, width: training resolution (every prepared sequence must be at it).
        batch_size, num_workers: DataLoader settings (workers are persistent).
        min_interval, max_interval: allowed |i − j| of a pair.
        val_fraction: fraction of each training sequence's usable frames (at its end) used for validation.
        seed: seed of pair order and augmentation.
        augment: :class:`AugmentConfig` or mapping (training only).
        cache_frames_mb: decoded frames kept in memory per dataset and worker.
        drop_last: drop the last incomplete training batch.
    """

    def __init__(
        self,
        cfg: Mapping[str, Any] | None,
        prepared: list[PreparedSequence],
        fold: int | None,
        patients_with_ct: list[int],
        **overrides: Any,
    ):
        super().__init__()
        unknown = sorted(set(overrides) - set(DEFAULTS))
        if unknown:
            raise TypeError(f"unknown data module option(s) {unknown}; known: {sorted(DEFAULTS)}")
        c = dict(DEFAULTS)
        c.update({k: cfg[k] for k in DEFAULTS if cfg is not None and k in cfg})
        c.update(overrides)
        self.prepared = list(prepared)
        self.patients_with_ct = [int(p) for p in patients_with_ct]
        self.fold = None if fold is None else int(fold)
        self.height, self.width = int(c["height"]), int(c["width"])
        self.batch_size, self.num_workers = int(c["batch_size"]), int(c["num_workers"])
        self.min_interval, self.max_interval = int(c["min_interval"]), int(c["max_interval"])
        self.val_fraction = float(c["val_fraction"])
        self.seed = int(c["seed"])
        aug = c["augment"]
        self.augment = AugmentConfig.from_dict(dict(aug) if isinstance(aug, Mapping) else aug)
        self.cache_bytes = int(float(c["cache_frames_mb"]) * 2**20)
        self.drop_last = bool(c["drop_last"])
        self._check()
        self._split()
        self.train_set = self.val_set = self.test_set = None

    # ------------------------------------------------------------ checks
    def _check(self) -> None:
        if self.fold is not None and self.fold not in self.patients_with_ct:
            raise InputError(
                f"fold={self.fold} is not a patient with CT",
                fix=f"set fold to one of {sorted(self.patients_with_ct)} (the held-out test patient)",
            )
        if not 1 <= self.min_interval <= self.max_interval:
            raise InputError(
                f"min_interval={self.min_interval}, max_interval={self.max_interval}",
                fix="use 1 <= data.min_interval <= data.max_interval",
            )
        if not 0.0 <= self.val_fraction < 1.0:
            raise InputError(f"val_fraction={self.val_fraction}", fix="use 0 <= data.val_fraction < 1")
        if self.batch_size < 1 or self.num_workers < 0:
            raise InputError(f"batch_size={self.batch_size}, num_workers={self.num_workers}",
                             fix="batch_size >= 1, num_workers >= 0")  # fmt: skip
        if not self.prepared:
            raise InputError("no prepared sequence", fix="prepare at least one sequence (SfM + sparse cache)")
        for p in self.prepared:
            if (p.seq.height, p.seq.width) != (self.height, self.width):
                raise InputError(
                    f"sequence {p.seq.name!r} is {p.seq.width}x{p.seq.height}, training resolution is "
                    f"{self.width}x{self.height}",
                    fix="resize it with endorecon.data.transforms.resize_sequence before preparing it",
                )

    def _split(self) -> None:
        train, val, test = [], [], []
        for s, p in enumerate(self.prepared):
            usable = p.usable

            def add(out, frames):
                pr = make_pairs(frames, self.min_interval, self.max_interval)
                out.append(np.concatenate([np.full((len(pr), 1), s, np.int64), pr], axis=1))

            if self.fold is not None and p.seq.patient == self.fold:
                add(test, np.flatnonzero(usable))
            else:
                tr, va = split_validation(usable, self.val_fraction, self.min_interval)
                add(train, tr)
                add(val, va)
        empty = np.zeros((0, 3), np.int64)
        self.train_pairs = np.concatenate(train) if train else empty
        self.val_pairs = np.concatenate(val) if val else empty
        self.test_pairs = np.concatenate(test) if test else empty
        if self.fold is not None and not test:
            raise InputError(
                f"fold={self.fold}: no prepared sequence of patient {self.fold}",
                fix=f"prepare that patient's sequences or choose another fold from {sorted(self.patients_with_ct)}",
            )
        if len(self.train_pairs) == 0:
            raise InputError(
                f"fold={self.fold}: no training pair (min_interval={self.min_interval}, "
                f"max_interval={self.max_interval})",
                fix="add sequences of other patients, or widen data.max_interval",
            )

    # ------------------------------------------------------------ Lightning
    def setup(self, stage: str | None = None) -> None:
        if self.train_set is None:
            self.train_set = PairDataset(self.prepared, self.train_pairs, self.augment, self.cache_bytes)
            self.val_set = PairDataset(self.prepared, self.val_pairs, None, self.cache_bytes)
            self.test_set = PairDataset(self.prepared, self.test_pairs, None, self.cache_bytes)

    def _loader(self, ds: PairDataset, shuffle: bool, drop_last: bool) -> DataLoader:
        w = self.num_workers
        return DataLoader(
            ds,
            batch_size=self.batch_size,
            sampler=EpochSampler(len(ds), self.seed, shuffle=shuffle),
            num_workers=w,
            persistent_workers=w > 0,
            worker_init_fn=_worker_init if w > 0 else None,
            drop_last=drop_last,
        )

    def train_dataloader(self) -> DataLoader:
        self.setup("fit")
        return self._loader(self.train_set, shuffle=True, drop_last=self.drop_last)

    def val_dataloader(self) -> DataLoader | list:
        self.setup("fit")
        if len(self.val_set) == 0:
            return []
        return self._loader(self.val_set, shuffle=False, drop_last=False)

    def test_dataloader(self) -> DataLoader | list:
        self.setup("test")
        if len(self.test_set) == 0:
            return []
        return self._loader(self.test_set, shuffle=False, drop_last=False)

    def predict_dataloader(self) -> list[DataLoader]:
        """One loader per prepared sequence (in ``self.prepared`` order), every frame once."""
        return [frame_dataloader(p, self.batch_size, 0) for p in self.prepared]

    def sequences(self, split: str) -> list[int]:
        """Indices into ``prepared`` of the sequences in ``split`` ("train" also covers validation, "test")."""
        if split not in ("train", "test"):
            raise ValueError(f"split must be 'train' or 'test', got {split!r}")
        test = [s for s, p in enumerate(self.prepared) if self.fold is not None and p.seq.patient == self.fold]
        return test if split == "test" else [s for s in range(len(self.prepared)) if s not in test]
