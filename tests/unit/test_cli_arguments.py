"""Careless command-line values get argparse's one-line error naming the option, not a traceback
from deep inside (a port past 65535, zero episodes, a negative frame rate or seed)."""

from __future__ import annotations

import pytest

from zenrl.cli import build_parser


@pytest.mark.parametrize("argv, option, why", [
    (["exporter", "--run-id", "r", "--port", "99999"], "--port", "1..65535"),
    (["exporter", "--run-id", "r", "--port", "0"], "--port", ">= 1"),
    (["exporter", "--run-id", "r", "--poll-s", "0"], "--poll-s", "> 0"),
    (["run", "--actors", "0"], "--actors", ">= 1"),
    (["run", "--exporter-port", "70000"], "--exporter-port", "1..65535"),
    (["run", "--seed", "-1"], "--seed", ">= 0"),
    (["evaluate", "--checkpoint", "x", "--episodes", "0"], "--episodes", ">= 1"),
    (["evaluate", "--checkpoint", "x", "--workers", "0"], "--workers", ">= 1"),
    (["evaluate", "--checkpoint", "x", "--seed", "-5"], "--seed", ">= 0"),
    (["evaluate", "--checkpoint", "x", "--episodes", "ten"], "--episodes", "not an integer"),
    (["play", "--checkpoint", "x", "--fps", "-1"], "--fps", "> 0"),
    (["play", "--checkpoint", "x", "--fps", "nan"], "--fps", "> 0"),
    (["play", "--checkpoint", "x", "--speedup", "inf"], "--speedup", "> 0"),
    (["play", "--checkpoint", "x", "--max-steps", "0"], "--max-steps", ">= 1"),
    (["export", "--checkpoint", "x", "--out", "y", "--guard-angle", "200"], "--guard-angle", "<= 180"),
    (["average", "x", "--out", "y", "--last", "0"], "--last", ">= 1"),
    (["credentials", "--out", "d", "--actors", "-3"], "--actors", ">= 1"),
    (["status", "--wait", "-1"], "--wait", ">= 0"),
    # output files are checked before the work that makes them (an evaluation is not run to be lost)
    (["evaluate", "--checkpoint", "x", "--json", "/nonexistent-dir/x.json"], "--json", "no directory '/nonexistent-dir'"),
    (["evaluate", "--checkpoint", "x", "--json", "/proc/x.json"], "--json", "cannot write '/proc/x.json'"),
    (["play", "--checkpoint", "x", "--out", "/"], "--out", "is a directory"),
    (["export", "--checkpoint", "x", "--out", "/nonexistent-dir/p.pt"], "--out", "no directory"),
    (["average", "x", "--out", "/proc/a.pt"], "--out", "cannot write"),
    (["plot", "x", "--out", "/proc/c.png"], "--out", "cannot write"),
])
def test_out_of_range_values_are_one_line_errors(capsys, argv, option, why):
    with pytest.raises(SystemExit) as e:
        build_parser().parse_args(argv)
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert f"argument {option}" in err and why in err, err


def test_in_range_values_parse():
    a = build_parser().parse_args(["play", "--checkpoint", "x", "--out", "a.gif", "--fps", "12.5", "--seed", "0",
                                   "--max-steps", "1"])
    assert (a.fps, a.seed, a.max_steps) == (12.5, 0, 1)
    a = build_parser().parse_args(["exporter", "--run-id", "r", "--port", "65535"])
    assert a.port == 65535


def test_an_output_file_checked_up_front_is_left_as_it_was(tmp_path):
    new = tmp_path / "new.gif"
    a = build_parser().parse_args(["play", "--checkpoint", "x", "--out", str(new)])
    assert a.out == str(new) and not new.exists()  # opened to test it, removed again
    old = tmp_path / "old.json"
    old.write_text('{"kept": true}')
    build_parser().parse_args(["evaluate", "--checkpoint", "x", "--json", str(old)])
    assert old.read_text() == '{"kept": true}'  # not truncated by the check


@pytest.mark.parametrize("cmd", [["evaluate"], ["play", "--out", "a.gif"], ["export", "--out", "a.pt"]])
def test_the_run_folder_as_the_first_argument_is_the_checkpoint(tmp_path, cmd):
    """`zenrl evaluate runs/<id>`, as `zenrl status runs/<id>` takes it: the same as --checkpoint."""
    from zenrl.cli import _policy_checkpoint

    out = [str(tmp_path / x) if x.startswith("a.") else x for x in cmd]
    a = build_parser().parse_args([out[0], "runs/r1", *out[1:]])
    _policy_checkpoint(a)
    assert a.checkpoint == "runs/r1"
    a = build_parser().parse_args([*out, "--checkpoint", "runs/r1", "runs/r1"])
    _policy_checkpoint(a)  # the same one twice: taken
    assert a.checkpoint == "runs/r1"


@pytest.mark.parametrize("argv, why", [
    (["export", "--out", "a.pt"], "required: --checkpoint (or the run folder or checkpoint as the first argument"),
    (["play", "--out", "a.gif"], "required: --checkpoint (or the run folder"),
    (["evaluate", "runs/a", "--checkpoint", "runs/b"], "two checkpoints: --checkpoint runs/b and runs/a; give one"),
])
def test_a_missing_or_doubled_checkpoint_is_a_usage_error(tmp_path, capsys, argv, why):
    from zenrl.cli import main

    argv = [str(tmp_path / x) if x.startswith("a.") else x for x in argv]
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    assert why in capsys.readouterr().err.strip().splitlines()[-1]
