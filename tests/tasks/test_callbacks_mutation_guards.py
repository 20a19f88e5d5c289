"""Mutation guards for the bootstrap end stage and LastCheckpoint (endorecon/callbacks/)."""

import types


def test_last_checkpoint_defaults_to_the_trainers_checkpoints_folder(tmp_path):
    from endorecon.callbacks import LastCheckpoint

    trainer = types.SimpleNamespace(default_root_dir=str(tmp_path))
    assert LastCheckpoint().path(trainer) == tmp_path / "checkpoints" / "last.ckpt"
    assert LastCheckpoint(dirpath=str(tmp_path / "d"), filename="x.ckpt").path(trainer) == tmp_path / "d" / "x.ckpt"
