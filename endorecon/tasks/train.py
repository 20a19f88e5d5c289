"""The train task: bootstrapped self-supervised training for one leave-one-out fold.

``python train.py fold=k iteration=i`` makes ``outputs/train/fold=k/iteration=0..i``.
Each iteration dir is complete when its ``metrics.json`` exists; complete
iterations are skipped, missing earlier ones are run first (or, with
``bootstrap.run_missing=false``, the task stops and prints the command).

One iteration: train the DepthModule on all training patients' sequences
(with the Dense Simulation Loss on the previous iteration's simulated depth,
poses refined by the previous PGO, flagged frames excluded), then the
:class:`endorecon.callbacks.BootstrapCallback` fuses, renders, detects
failures and refines poses for every sequence, the held-out patient's
included, and evaluates the held-out patient's mesh against its CT.
"""

from __future__ import annotations

import logging
from pathlib import Path

import lightning as L
import numpy as np
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from endorecon.data.sequence import Sequence, read_poses_txt
from endorecon.data.transforms import resize_sequence
from endorecon.tasks import pipeline
from endorecon.utils.errors import InputError
from endorecon.utils.io import atomic_write_text, read_json

log = logging.getLogger(__name__)


def iteration_dir(cfg: DictConfig, it: int) -> Path:
    return Path(cfg.paths.run_dir) / f"iteration={it}"


def is_complete(it_dir: Path) -> bool:
    return (it_dir / "metrics.json").is_file()


# The settings that make an iteration's results.  Left out: where things go, how they are shown or logged, how
# fast they run (workers, caches, chunks, compile, devices), and what is only checked against the results
# (bootstrap.targets) or run around them (adapt, evaluation caps).
_RESULT_GROUPS = ("data", "model", "loss", "fusion", "failure", "pgo", "sfm", "bootstrap", "trainer", "seed")
_NO_EFFECT = {
    "data": {"num_workers", "cache_frames_mb"},
    "model": {"log_images_every_n_steps"},
    "fusion": {"compile", "device", "block_count"},
    "failure": {"batch_size"},
    "pgo": {"progress", "edge_chunk", "std_cache_mb"},
    "sfm": set(pipeline.SFM_NO_EFFECT),
    "bootstrap": {"targets", "run_missing", "evaluate", "depth_cap_mm"},
    "trainer": {"_target_", "accelerator", "devices", "log_every_n_steps", "num_sanity_val_steps",
                "enable_model_summary", "limit_val_batches", "deterministic"},
}


def _leaves(node, prefix: str = "") -> dict:
    if isinstance(node, dict):
        out = {}
        for k, v in node.items():
            out.update(_leaves(v, f"{prefix}.{k}" if prefix else str(k)))
        return out
    return {prefix: node}


def config_differences(recorded: DictConfig, current: DictConfig) -> list[str]:
    """``group.key: recorded -> current`` for every result-making setting that differs between an iteration's
    recorded ``.hydra/config.yaml`` and ``current`` (unresolved: interpolations compare as written).  A key that
    only one of them has (added or removed since) is not compared."""
    out = []
    rec, cur = (OmegaConf.to_container(c, resolve=False) for c in (recorded, current))
    for group in _RESULT_GROUPS:
        if group not in rec or group not in cur:
            continue
        a, b = _leaves(rec[group], group), _leaves(cur[group], group)
        skip = _NO_EFFECT.get(group, set())
        for key in sorted(set(a) & set(b)):
            if key.split(".")[1:2] and key.split(".")[1] in skip:
                continue
            if a[key] != b[key]:
                out.append(f"{key}: {a[key]!r} -> {b[key]!r}")
    return out


def recorded_differences(cfg: DictConfig):
    """Yields ``(iteration, path, differences)`` for each iteration of this fold up to ``cfg.iteration`` that has a
    recorded ``.hydra/config.yaml``: :func:`config_differences` between it and ``cfg``, one iteration at a time."""
    for it in range(int(cfg.iteration) + 1):
        path = iteration_dir(cfg, it) / ".hydra" / "config.yaml"
        if not path.is_file():
            continue
        try:
            recorded = OmegaConf.load(path)
        except Exception as e:  # noqa: BLE001 - any parse error: the file cannot vouch for the iteration
            raise InputError(f"unreadable config of a previous run ({type(e).__name__})", path,
                             f"delete {path.parents[1]} so that the iteration is made again") from e
        yield it, path, config_differences(recorded, cfg)


def check_same_settings(cfg: DictConfig) -> None:
    """Refuse to skip or resume iterations of this fold that were made with other settings: the run dir
    (``outputs/train/fold=<k>``) does not encode the overrides, and their results would be returned as this
    configuration's."""
    for it, path, diffs in recorded_differences(cfg):
        if diffs:
            shown = "; ".join(diffs[:6]) + (f"; and {len(diffs) - 6} more" if len(diffs) > 6 else "")
            raise InputError(
                f"iteration {it} of fold {cfg.fold} was made with other settings ({shown})", path,
                f"pass the settings it was made with, train elsewhere (paths.output_root=<dir>), or delete "
                f"{Path(cfg.paths.run_dir)} to train again with these")


def check_same_sfm(seq: Sequence, summary: dict, refined_cam_from_world: np.ndarray, sdir: Path,
                   sfm_cache: Path) -> None:
    """Refuse poses that an earlier iteration refined from another SfM model of ``seq``.

    The next iteration projects *this* SfM's points with those poses (sparse depth and flow) and fuses with
    them; poses of another model (SfM made again after its settings, the data path or the cache changed)
    sit in another world frame and scale, and everything trained or fused from them would be silently
    wrong.  Checked by the points' digest each summary records; summaries from before it was recorded are
    checked by the frame dense PGO holds fixed (unless an SfM rerun replaced that frame)."""
    from endorecon.data.sequence import same_fixed_frame, sfm_fingerprint

    recorded, now = summary.get("sfm_fingerprint"), sfm_fingerprint(seq)
    if recorded is not None and now is not None:
        same = recorded == now
    else:
        reg = np.flatnonzero(seq.registered)
        replaced = set((summary.get("resfm") or {}).get("replaced_frames") or [])
        same = None if (len(reg) and int(reg[0]) in replaced) else same_fixed_frame(seq.cam_from_world,
                                                                                     refined_cam_from_world)
    if same is False:
        raise InputError(
            f"these poses of {seq.name} were refined from another SfM model than the one in the SfM cache now "
            f"({sfm_cache}; sparse points digest {now}, recorded {recorded or 'not recorded, fixed frame moved'}): "
            "SfM ran again because its settings, the data path or the cache changed since that iteration",
            sdir / "poses.txt",
            f"rerun with the sfm.* settings and paths the fold was trained with, or delete {sdir.parents[1]} and "
            "the iterations after it so that they are made again from this SfM")


def prepare_sequences(cfg: DictConfig, sfm_seqs: list[Sequence], prev_dir: Path | None):
    """Sequences at training resolution with poses, sparse caches, simulated depth and exclusions of ``prev_dir``."""
    from endorecon.data.datamodule import PreparedSequence
    from endorecon.data.sparse import build_sparse_cache

    out = []
    for seq in sfm_seqs:
        small = resize_sequence(seq, int(cfg.data.height), int(cfg.data.width))
        sim = sim_valid = excluded = None
        if prev_dir is not None:
            sdir = prev_dir / "sequences" / pipeline._slug(seq.name)
            names, poses = read_poses_txt(sdir / "poses.txt")
            if names != [p.name for p in small.frame_paths]:
                raise InputError("refined poses list other frames than the sequence", sdir / "poses.txt",
                                 "delete the iteration dirs of this fold and rerun")
            summary = read_json(sdir / "summary.json",
                                f"delete {prev_dir} and the iterations after it so that they are made again")
            check_same_sfm(seq, summary, poses, sdir, Path(cfg.paths.cache_dir) / "sfm")
            small = small.replace(cam_from_world=poses)
            sim, sim_valid = pipeline.load_simulated(sdir / "simulated_depth.npz")
            excluded = np.zeros(len(small), bool)
            # "excluded": the flagged frames and their neighbours (summaries before it held "flagged" alone)
            excluded[summary.get("excluded", summary["flagged"])] = True
        cache = build_sparse_cache(small)
        out.append(PreparedSequence(seq=small, cache=cache, sim_depth=sim, sim_valid=sim_valid, excluded=excluded))
    return out


def run(cfg: DictConfig) -> float | None:
    """Run (or resume) bootstrapping iterations 0..cfg.iteration of fold cfg.fold; returns the held-out
    patient's mean residual in mm (for sweeps), when evaluated."""
    for key in ("fold", "iteration"):
        if not isinstance(cfg[key], int) or cfg[key] < 0:
            raise InputError(f"{key} must be an integer >= 0, got {cfg[key]!r}", fix=f"pass {key}=0, 1, 2 ...")
    # checked before any work: a bad cap would otherwise fail only in the evaluation after an iteration's training
    cap = cfg.bootstrap.get("depth_cap_mm")
    if cap is not None and not (isinstance(cap, (int, float)) and not isinstance(cap, bool) and cap > 0):
        raise InputError(f"bootstrap.depth_cap_mm must be a positive depth in mm or null, got {cap!r}",
                         fix="pass bootstrap.depth_cap_mm=30 (or null for uncapped metrics only)")
    from endorecon.callbacks.bootstrap import TARGETS, log_held_out_report

    targets = cfg.bootstrap.get("targets") or {}
    known = tuple(TARGETS)
    for k, v in dict(targets).items():
        if k not in known or not (v is None or (isinstance(v, (int, float)) and not isinstance(v, bool))):
            raise InputError(f"bootstrap.targets.{k}={v!r}: the targets are {', '.join(known)}, each a number or null",
                             fix="pass e.g. bootstrap.targets.max_mm=1.5 (or bootstrap.targets.max_mm=null to leave it unchecked)")
    from endorecon.failure import check_low_thresholds

    check_low_thresholds(cfg.failure.get("low_thresholds"), cfg.failure.get("thresholds"))  # not after an epoch
    L.seed_everything(int(cfg.seed), workers=True)
    check_same_settings(cfg)  # before the data: a refusal should not wait for the phantom and SfM
    info = pipeline.load_sequences(cfg)
    pipeline.check_fold(int(cfg.fold), info.patients_with_ct)
    todo = [it for it in range(int(cfg.iteration) + 1) if not is_complete(iteration_dir(cfg, it))]
    if not todo:
        log.info("all iterations up to %d of fold %d are complete", cfg.iteration, cfg.fold)
    if todo and todo[0] < int(cfg.iteration) and not cfg.bootstrap.run_missing:
        raise InputError(
            f"iteration {cfg.iteration} needs iteration {todo[0]}, which is missing",
            iteration_dir(cfg, todo[0]),
            f"run: {_command_for_iteration(cfg, todo[0])}  (or bootstrap.run_missing=true)",
        )
    sfm_seqs = pipeline.run_sfm(cfg, info.sequences, info.root) if todo else []
    metrics = None
    for it in todo:
        # a checkpoint path resumes the first missing iteration only: the later ones train from their start
        metrics = run_iteration(cfg, it, sfm_seqs, info, resume=it == todo[0])
    if metrics is None:
        it_dir = iteration_dir(cfg, int(cfg.iteration))
        metrics = read_json(it_dir / "metrics.json", f"delete {it_dir} so that the iteration is made again")
        log_held_out_report(metrics, cfg.bootstrap.get("targets"), it_dir)
    ev = metrics.get("evaluation") or {}
    return ev.get("mean_mm")


def _command_for_iteration(cfg: DictConfig, it: int) -> str:
    """This command line with ``iteration=<it>`` (and without ``bootstrap.run_missing``): the user's other
    overrides kept, so that it trains the same configuration in the same place."""
    try:
        from hydra.core.hydra_config import HydraConfig

        given = list(HydraConfig.get().overrides.task)
    except Exception:  # noqa: BLE001 - not under Hydra's main (tests, the API): the fold at least
        given = [f"fold={cfg.fold}"]
    keep = [o for o in given if not o.lstrip("+~").startswith(("iteration=", "bootstrap.run_missing="))]
    return " ".join(["python train.py", *keep, f"iteration={it}"])


def run_iteration(cfg: DictConfig, it: int, sfm_seqs: list[Sequence], info: pipeline.DatasetInfo,
                  resume: bool = True) -> dict:
    from endorecon.callbacks import BootstrapCallback, LastCheckpoint
    from endorecon.data.datamodule import EndoDataModule
    from endorecon.module import DepthModule

    it_dir = iteration_dir(cfg, it)
    it_dir.mkdir(parents=True, exist_ok=True)
    (it_dir / ".hydra").mkdir(exist_ok=True)
    atomic_write_text(it_dir / ".hydra" / "config.yaml", OmegaConf.to_yaml(cfg, resolve=False))
    log.info("bootstrapping iteration %d of fold %d -> %s", it, cfg.fold, it_dir)
    prev_dir = iteration_dir(cfg, it - 1) if it > 0 else None
    prepared = prepare_sequences(cfg, sfm_seqs, prev_dir)
    datamodule = EndoDataModule(cfg.data, prepared, fold=int(cfg.fold), patients_with_ct=info.patients_with_ct)
    module = DepthModule(cfg.model, cfg.loss)
    # Saved with the checkpoint so that reconstruct.py knows the resolution the network learnt at.
    module.hparams["input_hw"] = [int(cfg.data.height), int(cfg.data.width)]
    if prev_dir is not None and cfg.bootstrap.warm_start:
        load_weights(module, prev_dir / "checkpoints" / "last.ckpt")
        # The warm-up protects a random init from the dense NLLs; a warm-started network needs none.
        module.warmup_epochs = 0

    callbacks = [instantiate(c) for c in (cfg.get("callbacks") or {}).values() if c and "_target_" in c]
    for c in callbacks:
        if isinstance(c, (L.pytorch.callbacks.ModelCheckpoint, LastCheckpoint)):
            c.dirpath = str(it_dir / "checkpoints")
    boot = BootstrapCallback(cfg, prepared, it_dir, info)
    callbacks.append(boot)
    logger = False
    if cfg.get("logger") and "_target_" in cfg.logger:
        logger = instantiate(cfg.logger, save_dir=str(it_dir))
    else:  # Lightning refuses a learning-rate monitor without a logger (logger=none crashed after SfM)
        callbacks = [c for c in callbacks if not isinstance(c, L.pytorch.callbacks.LearningRateMonitor)]
    trainer: L.Trainer = instantiate(cfg.trainer, callbacks=callbacks, logger=logger, default_root_dir=str(it_dir))
    ckpt = resume_checkpoint(cfg, it_dir, resume)
    trainer.fit(module, datamodule=datamodule, ckpt_path=ckpt)
    if boot.metrics is None and ckpt is not None and trainer.fit_loop.done and not trainer.interrupted:
        # last.ckpt was saved after the final epoch and the end-of-iteration stage (fusion, failure detection,
        # PGO) then stopped: Lightning restores it, finds max_epochs reached and ends without on_train_end.
        # Make that stage now, with the restored weights (sequences it finished are skipped by their summaries).
        log.info("iteration %d: training had finished in %s; making its fusion, failure detection and PGO", it, ckpt)
        boot.on_train_end(trainer, module)
    if boot.metrics is None and not trainer.is_global_zero and trainer.fit_loop.done and not trainer.interrupted:
        # distributed training: the end-of-iteration stage runs on rank 0 alone; the other ranks take its
        # metrics.json (a barrier could time out: the stage takes minutes per sequence)
        return wait_for_metrics(it_dir)
    if boot.metrics is None:  # training was interrupted before on_train_end
        raise InputError(f"iteration {it} did not finish", it_dir, "resume with ckpt_path=last")
    return boot.metrics


def resume_checkpoint(cfg: DictConfig, it_dir: Path, resume: bool) -> str | None:
    """The checkpoint an iteration's training resumes from: ``ckpt_path=last`` -> its own ``last.ckpt`` when
    there is one; an explicit path -> only for the first missing iteration (``resume``; every later iteration
    given it too was marked complete with the earlier weights, untrained)."""
    last = it_dir / "checkpoints" / "last.ckpt"
    if cfg.ckpt_path == "last":
        return str(last) if last.is_file() else None
    if cfg.ckpt_path is not None and resume:
        return str(cfg.ckpt_path)
    return None


def wait_for_metrics(it_dir: Path, timeout_s: float = 24 * 3600.0, poll_s: float = 5.0) -> dict:
    """The iteration's ``metrics.json``, once rank 0's end-of-iteration stage has written it (another rank)."""
    import time

    path = it_dir / "metrics.json"
    t0 = last_log = time.monotonic()
    while not path.is_file():
        if time.monotonic() - t0 > timeout_s:
            raise InputError(f"rank 0 wrote no metrics.json in {timeout_s:.0f} s", it_dir,
                             "see rank 0's log; resume with ckpt_path=last")
        if time.monotonic() - last_log > 300:
            log.info("waiting for rank 0's end-of-iteration stage (%s)", path)
            last_log = time.monotonic()
        time.sleep(poll_s)
    return read_json(path, f"delete {it_dir} so that the iteration is made again")


def load_weights(module, ckpt: Path) -> None:
    """Network weights of a previous iteration (optimiser and schedule start afresh)."""
    import torch

    if not ckpt.is_file():
        raise InputError("previous iteration's checkpoint is missing", ckpt,
                         "delete that iteration dir so that it is run again")
    state = torch.load(ckpt, map_location="cpu", weights_only=False)["state_dict"]
    module.load_state_dict(state)
