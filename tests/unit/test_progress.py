"""The launcher's env-steps/s figure (zenrl/launcher/display.py, Progress.tick_rate): actors report about
once a second, the display ticks twice a second; the rate must be steady, not 0 / double."""

import pytest

from zenrl.launcher import RATE_WINDOW_S, Progress


def test_rate_is_steady_between_reports():
    p = Progress()
    rates = []
    for tick in range(40):  # 20 s of 0.5 s ticks; two actors report 500 steps each, once a second
        t = tick * 0.5
        if tick % 2 == 0:
            p._actor("a", 500 * (tick // 2 + 1))
            p._actor("b", 500 * (tick // 2 + 1))
        p.tick_rate(now=t)
        rates.append(p.env_steps_rate)
    assert all(r == pytest.approx(1000.0) for r in rates[4:]), rates


def test_rate_falls_to_zero_when_actors_stop():
    p = Progress()
    for tick in range(10):
        p._actor("a", 1000 * (tick + 1))
        p.tick_rate(now=float(tick))
    assert p.env_steps_rate == pytest.approx(1000.0)
    p.tick_rate(now=9.0 + RATE_WINDOW_S / 2)
    assert p.env_steps_rate == pytest.approx(1000.0)  # a pause shorter than the window
    p.tick_rate(now=9.0 + RATE_WINDOW_S + 0.5)
    assert p.env_steps_rate == 0.0


def test_resumed_run_continues_its_totals():
    p = Progress(start=100.0, base_env_steps=50_000, base_elapsed_s=30.0)
    p._actor("a", 700)
    p._actor("b", 300)
    assert p.segment_env_steps == 1000 and p.env_steps == 51_000
    assert p.elapsed_s(now=110.0) == pytest.approx(40.0)
    p.tick_rate(now=110.0)
    p._actor("a", 1700)
    p.tick_rate(now=111.0)
    assert p.env_steps_rate == pytest.approx(1000.0)  # the base is no burst of steps


def test_live_table_shows_win_rate_in_percent():
    from rich.console import Console

    from zenrl.launcher.display import render_table

    line = {"env_steps": 10, "eval_return": 1.5, "eval_win_rate": 1 / 3}
    console = Console(width=80, record=True)
    console.print(render_table("r", line, "interrupted by user (Ctrl-C)"))
    text = console.export_text()
    assert "33%" in text and "0.33" not in text and "interrupted by user (Ctrl-C)" in text


def test_last_error_line_of_a_log(tmp_path):
    from zenrl.launcher.runfolder import last_error_line

    log = tmp_path / "learner.log"
    log.write_text("2026-01-01 INFO learner zenrl: starting\nTraceback (most recent call last):\n"
                   '  File "x.py", line 1, in <module>\n    f()\nValueError: zenrl needs a Discrete action space\n\n')
    assert last_error_line(log) == "ValueError: zenrl needs a Discrete action space"
    log.write_text("a INFO x: fine\nb ERROR learner zenrl.learner: checkpoint unreadable\nc INFO x: stopping\n")
    assert last_error_line(log) == "b ERROR learner zenrl.learner: checkpoint unreadable"
    log.write_text("a ERROR learner zenrl: no checkpoint in 'x'\nzenrl: error: no checkpoint in 'x'\n")
    assert last_error_line(log) == "no checkpoint in 'x'"
    log.write_text("only info\n")
    assert last_error_line(log) == "only info"
    assert last_error_line(tmp_path / "missing.log") is None


def test_a_child_that_keeps_failing_stops_the_run_with_its_last_error(tmp_path):
    """A real child process that crashes: the run stops (exit code 1) and the reason carries the
    last error line of the child's log; a child exiting with EXIT_CONFIG is never restarted."""
    import subprocess
    import sys

    from zenrl.common.config import RunConfig
    from zenrl.launcher import EXIT_CONFIG
    from zenrl.launcher.supervisor import Child, Launcher

    cfg = RunConfig.model_validate({"run_id": "t-fail", "runs_dir": str(tmp_path)})
    for code, max_restarts, want_rc, want in ((1, 0, 1, "learner keeps failing (exit code 1): RuntimeError: boom"),
                                              (EXIT_CONFIG, 5, 2, "learner failed on its configuration: RuntimeError: boom")):
        la = Launcher(cfg)
        la.max_restarts = max_restarts
        log = tmp_path / f"learner-{code}.log"
        with open(log, "wb") as f:
            proc = subprocess.Popen([sys.executable, "-c", f"import sys; sys.stderr.write('RuntimeError: boom\\n'); sys.exit({code})"],
                                    stdout=f, stderr=subprocess.STDOUT)
        proc.wait(timeout=30)
        la.children = [Child("learner", "learner", [], proc=proc, log_path=log)]
        la._supervise()
        assert la.stop.is_set() and la.stop_reason == want and la.exit_code == want_rc, la.stop_reason
        assert la.children[0].restarts == 0


def _eval(mean: float, version: int = 1):
    import numpy as np

    from zenrl.common import protocol as P

    return P.EvalResult(version, version * 10, np.full(3, mean, np.float32)).encode()


def test_summary_keeps_the_newest_evaluations_their_count_and_the_first_solved(tmp_path):
    """summary.json is rewritten every 30 s: it keeps the newest MAX_KEPT_EVALS evaluations
    (metrics.jsonl holds every one), how many there were, and the first that reached
    target_return, across a resume, from a summary written before the bound too."""
    import json

    from zenrl.common.config import load_config
    from zenrl.launcher.display import MAX_KEPT_EVALS
    from zenrl.launcher.supervisor import Launcher

    cfg = load_config(None, [f"runs_dir={tmp_path}", "run_id=ev", "target_return=400"], environ={})
    la = Launcher(cfg)
    n = MAX_KEPT_EVALS + 500
    for i in range(n):  # the 11th reaches the target; later ones do not (the run went on)
        la.progress.on_message("k", _eval(450.0 if i == 10 else 100.0 + i % 7, i))
    s = la.summary()
    assert len(s["evals"]) == MAX_KEPT_EVALS and s["evals_total"] == n
    assert [e["version"] for e in s["evals"]] == list(range(500, n))
    assert s["solved"] and s["first_solved"]["version"] == 10 and s["first_solved"]["mean"] == 450.0
    assert s["first_solved"]["segment"] == 0

    # a summary of an earlier version: every evaluation, no count, no first_solved
    old = dict(s, evals=[dict(e, version=v) for v, e in enumerate([s["first_solved"]] * 1 + s["evals"] * 2)])
    del old["evals_total"], old["first_solved"]
    (tmp_path / "ev").mkdir(exist_ok=True)
    (tmp_path / "ev" / "summary.json").write_text(json.dumps(old))
    la = Launcher(cfg, resume=True)
    la.progress.on_message("k", _eval(90.0, 7))
    s2 = la.summary()
    assert s2["evals_total"] == 1 + 2 * MAX_KEPT_EVALS + 1 and len(s2["evals"]) == MAX_KEPT_EVALS
    assert s2["evals"][-1]["version"] == 7 and s2["evals"][-1]["segment"] == 1
    assert s2["solved"] and s2["first_solved"]["version"] == 0 and s2["first_solved"]["mean"] == 450.0

    # and one written with the bound: its count and first_solved carry on
    (tmp_path / "ev" / "summary.json").write_text(json.dumps(s2))
    la = Launcher(cfg, resume=True)
    s3 = la.summary()
    assert s3["evals_total"] == s2["evals_total"] and s3["first_solved"] == s2["first_solved"]
    assert s3["evals"] == s2["evals"]

    # no target: nothing is solved, and nothing kept for it
    la = Launcher(load_config(None, [f"runs_dir={tmp_path}", "run_id=ev2"], environ={}))
    la.progress.on_message("k", _eval(1e9))
    assert la.summary()["solved"] is False and la.summary()["first_solved"] is None


def test_a_run_with_more_actors_than_the_machine_holds_is_told():
    from zenrl.launcher.display import ACTOR_PRIVATE_BYTES, crowding_warnings

    gib = 1 << 30
    mem = (24 * gib, "the machine's memory")
    assert crowding_warnings(8, 2, mem) == []  # 4 per CPU, 1.25 GiB: fine
    cpu = crowding_warnings(9, 2, mem)
    assert len(cpu) == 1 and cpu[0].startswith("9 actor processes on 2 CPUs: each takes ~2 s of CPU to start")
    assert "actor.envs_per_actor" in cpu[0]
    many = crowding_warnings(500, 2, mem)  # ~78 GiB of actors on 24
    assert len(many) == 2 and many[1].startswith("500 actor processes take 78.1 GiB or more of their own")
    assert "the machine's memory is 24.0 GiB: the kernel will kill processes for memory" in many[1]
    half = crowding_warnings(100, 64, mem)  # 15.6 GiB: more than half, less than all
    assert len(half) == 1 and "15.6 GiB" in half[0] and "kill" not in half[0]
    assert crowding_warnings(int(12 * gib // ACTOR_PRIVATE_BYTES), 64, mem) == []  # exactly half
    assert crowding_warnings(500, 0, None) == []  # nothing known: nothing said
