"""More mutation guards for endorecon.utils: atomic writes, quoting of path overrides, error messages."""

from __future__ import annotations

import pytest

from endorecon.utils.errors import InputError


def test_atomic_path_failure_leaves_neither_output_nor_temp_file(tmp_path):
    from endorecon.utils.io import atomic_path, atomic_write_text

    atomic_write_text(tmp_path / "a.txt", "old")
    with pytest.raises(RuntimeError):
        with atomic_path(tmp_path / "a.txt") as tmp:
            tmp.write_text("half")
            raise RuntimeError("crash")
    with pytest.raises(RuntimeError):
        with atomic_path(tmp_path / "b.txt") as tmp:
            tmp.write_text("half")
            raise RuntimeError("crash")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]  # no temp file, no b.txt
    assert (tmp_path / "a.txt").read_text() == "old"


def test_atomic_dir_replaces_an_existing_dir_and_leaves_nothing_beside_it(tmp_path):
    from endorecon.utils.io import atomic_dir

    for text in ("one", "two"):
        with atomic_dir(tmp_path / "d") as tmp:
            (tmp / "x.txt").write_text(text)
    assert (tmp_path / "d" / "x.txt").read_text() == "two"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d"]  # neither .d.old nor a temp dir


def test_report_errors_prints_one_message_and_exits_2(capsys):
    from endorecon.utils.cli import report_errors

    def bad():
        raise InputError("mask has size 1x1", "/data/m.png", fix="give the right mask")

    with pytest.raises(SystemExit) as e:
        report_errors(bad)
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "error:" in err and "/data/m.png: mask has size 1x1" in err and "fix: give the right mask" in err
    assert report_errors(lambda x: x + 1, 1) == 2


def test_input_error_message_names_path_and_fix():
    e = InputError("bad", "/a/b.ply", fix="redo it")
    assert str(e) == "/a/b.ply: bad\n  fix: redo it" and e.path.name == "b.ply" and e.fix == "redo it"
    assert str(InputError("bad")) == "bad"
