"""The launcher's env-steps/s figure (zenrl/launcher.py, Progress.tick_rate): actors report about
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
