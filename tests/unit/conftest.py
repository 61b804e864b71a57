"""Fixtures shared by the unit tests."""

import pytest


@pytest.fixture
def make_bw():
    """``make_bw(**kwargs)`` -> a BurgerWarEnv, closed when the test ends."""
    from zenrl.games.burgerwar.env import BurgerWarEnv

    envs = []

    def _make(**kw):
        env = BurgerWarEnv(**kw)
        envs.append(env)
        return env

    yield _make
    for e in envs:
        e.close()
