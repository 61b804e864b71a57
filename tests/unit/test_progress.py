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
