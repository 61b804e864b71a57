"""CPU placement of `zenrl run`'s processes (zenrl/placement.py): the plan per machine size, and
a real child process applying what the launcher passes in its environment."""

import json
import os
import subprocess
import sys

import pytest

from zenrl.algorithms import algorithm
from zenrl.placement import ACTOR_NICE, CPUS_ENV, NICE_ENV, Placement, apply_from_env, plan

linux_only = pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="CPU affinity is Linux-only")


@linux_only
def test_two_cpus_reserve_the_last_for_the_learner():
    p = plan("auto", True, 1, [0, 1])
    assert p["learner"] == Placement((1,), 0)
    assert p["actor"] == Placement((0,), ACTOR_NICE)
    assert p["replay"] == p["evaluator"] == p["router"] == Placement((0,), 0)


@linux_only
def test_four_cpus_and_two_learner_threads():
    p = plan("auto", True, 2, [0, 2, 5, 7])  # the ids this process may use, not 0..n-1
    assert p["learner"].cpus == (5, 7)
    assert p["actor"].cpus == (0, 2) == p["replay"].cpus


@pytest.mark.parametrize("mode,algo,threads,cpus", [
    ("off", "apex", 1, [0, 1]),              # the user turned it off
    ("auto", "a3c", 1, [0, 1]),              # A3C workers are the learner's producers and consumers
    ("auto", "apex", 1, list(range(8))),     # big enough for the OS scheduler
    ("auto", "apex", 1, [0]),                # nothing left for the others
    ("auto", "apex", 2, [0, 1]),             # the learner would take every CPU
])
def test_no_placement(mode, algo, threads, cpus):
    assert plan(mode, algorithm(algo).places_learner, threads, cpus) is None


def test_env_round_trip():
    assert Placement((1, 3), 5).env() == {CPUS_ENV: "1,3", NICE_ENV: "5"}
    assert Placement().env() == {}
    assert apply_from_env({}) is None


PROBE = ("import json, os; from zenrl.placement import apply_from_env; p = apply_from_env(); "
         "print(json.dumps({'applied': p is not None, 'cpus': sorted(os.sched_getaffinity(0)), 'nice': os.nice(0)}))")


def _probe(env_extra: dict[str, str]) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in (CPUS_ENV, NICE_ENV)}
    env.update(env_extra)
    out = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    return {**json.loads(out.stdout.strip().splitlines()[-1]), "stderr": out.stderr}


@linux_only
def test_child_applies_its_placement():
    cpu = sorted(os.sched_getaffinity(0))[-1]
    base_nice = os.nice(0)
    got = _probe({CPUS_ENV: str(cpu), NICE_ENV: "3"})
    assert got["applied"] and got["cpus"] == [cpu]
    assert got["nice"] == min(base_nice + 3, 19)


@linux_only
@pytest.mark.parametrize("cpus", ["x", "0,,1", str(10 ** 6)])
def test_bad_placement_is_logged_and_skipped(cpus):
    every = sorted(os.sched_getaffinity(0))
    got = _probe({CPUS_ENV: cpus})
    assert not got["applied"] and got["cpus"] == every
    assert "not applied" in got["stderr"] and CPUS_ENV in got["stderr"]


@linux_only
def test_cpus_apply_when_the_niceness_is_malformed():
    cpu = sorted(os.sched_getaffinity(0))[-1]
    got = _probe({CPUS_ENV: str(cpu), NICE_ENV: "high"})
    assert got["applied"] and got["cpus"] == [cpu]
    assert "not applied" in got["stderr"] and NICE_ENV in got["stderr"] and CPUS_ENV not in got["stderr"]
