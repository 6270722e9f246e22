"""Output paths of every command (``--out``, ``--record``, ``eval --report``): a file where a folder
is wanted (or a folder where a file is) is refused by name with exit 2 while the arguments are
read, before any work starts, never with a traceback (stack.commands.argtypes.out_folder /
out_file / out_stem)."""

from __future__ import annotations

import argparse

import pytest

from stack.cli import main
from stack.commands import argtypes

OUT_COMMANDS = {   # name: (the command line, its output folder's flag)
    "demo": (["demo", "--quick"], "--out"),
    "demo --resume": (["demo", "--resume"], "--out"),
    "sweep": (["sweep", "--seeds", "0,", "--episodes", "16"], "--out"),
    "train": (["train", "--episodes", "16"], "--out"),
    "plot": (["plot", "some-run"], "--out"),
    "certs": (["certs"], "--out"),
    "eval --record": (["eval", "--policy", "scripted", "--world", "pymunk", "--episodes", "1"], "--record"),
    "eval --trace": (["eval", "--policy", "scripted", "--world", "pymunk", "--episodes", "1"], "--trace"),
    "bridge --record": (["bridge", "--fleet", "f", "--policy", "scripted"], "--record"),
}


def _refused(argv: list[str], capsys) -> str:
    """stderr of ``formation ARGV``, which must stop with exit 2 while parsing."""
    with pytest.raises(SystemExit) as done:
        main(argv)
    assert done.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return err


@pytest.mark.parametrize("command", list(OUT_COMMANDS))
def test_an_out_that_is_a_file_is_refused_by_name_before_any_work(command, tmp_path, capsys):
    afile = tmp_path / "afile"
    afile.write_text("x\n")
    argv, flag = OUT_COMMANDS[command]
    err = _refused([*argv, flag, str(afile)], capsys)
    assert f"{flag}: {afile}: exists and is not a folder" in err
    assert afile.read_text() == "x\n"
    err = _refused([*argv, flag, str(afile / "run")], capsys)
    assert f"{afile} is a file, not a folder" in err


def test_an_export_stem_that_is_a_folder_or_under_a_file_is_refused_before_loading(tmp_path, capsys):
    """Before, export took any --out and failed only when writing, after loading the checkpoint."""
    (tmp_path / "afile").write_text("x\n")
    err = _refused(["export", "ck.pt", "--out", str(tmp_path)], capsys)
    assert f"--out: {tmp_path}: is a folder; give a file stem in it, e.g. {tmp_path / 'policy'}" in err
    err = _refused(["export", "ck.pt", "--out", str(tmp_path / "afile" / "policy")], capsys)
    assert f"--out: {tmp_path / 'afile' / 'policy'}: {tmp_path / 'afile'} is a file, not a folder" in err
    assert argtypes.out_stem(str(tmp_path / "new" / "policy")) == tmp_path / "new" / "policy"


def test_eval_report_that_is_a_folder_is_refused_before_the_episodes(tmp_path, capsys):
    folder = tmp_path / "adir"
    folder.mkdir()
    err = _refused(["eval", "--policy", "scripted", "--world", "pymunk", "--episodes", "1", "--episode-ticks", "3",
                    "--report", str(folder)], capsys)
    assert f"--report: {folder}: is a folder; give a file name, e.g. {folder / 'result.json'}" in err
    assert list(folder.iterdir()) == []      # no temporary file left beside it either
    assert list(tmp_path.iterdir()) == [folder]


def test_out_folder_and_out_file_accept_what_can_be_written(tmp_path):
    (tmp_path / "made").mkdir()
    assert argtypes.out_folder(str(tmp_path / "made")) == tmp_path / "made"
    assert argtypes.out_folder(str(tmp_path / "new" / "deeper")) == tmp_path / "new" / "deeper"
    (tmp_path / "old.json").write_text("{}")
    assert argtypes.out_file(str(tmp_path / "old.json")) == tmp_path / "old.json"
    assert argtypes.out_file(str(tmp_path / "sub" / "r.json")) == tmp_path / "sub" / "r.json"
    with pytest.raises(argparse.ArgumentTypeError, match="is a file, not a folder"):
        argtypes.out_file(str(tmp_path / "old.json" / "r.json"))
