"""A league agent run as a cluster runs it (`--agent`, no `zenrl run` to restart anything), real
OS processes on a real router: `zenrl league`, and the exploiter's `zenrl replay`, `zenrl
learner --auto-resume` and `zenrl actor`, each started with `--agent exploiter`. When the league
starts the exploiter's next generation, each of the three deletes its old generation's files (the
learner's checkpoints, the replay's durable log) and exits with status 75; started again, as a
restart policy would, the learner starts fresh instead of resuming the old generation. The
agent's `zenrl exporter --agent exploiter` watches its run id with its own actor count."""

import urllib.request

import pytest
import yaml

from tests.conftest import free_port, wait_until

pytestmark = pytest.mark.integration

MATCH = {"opponents": {"cheese": 1}, "side": "random", "reward": "zero_sum", "control_hz": 5, "action_set": "rich",
         "match_time": 6.0, "sudden_death_time": 2.0}


def config(tmp_path):
    doc = {"algo": "apex", "seed": 3, "runs_dir": str(tmp_path / "runs"),
           "env": {"id": "zenrl/BurgerWar-v0", "kwargs": MATCH},
           "network": {"hidden": [32]},
           "actor": {"num_actors": 1, "envs_per_actor": 4, "chunk_size": 32},
           "replay": {"min_size": 64, "durable": True, "flush_interval_s": 0.2},
           "learner": {"batch_size": 32, "checkpoint_interval_s": 1.0, "publish_every_updates": 5},
           "league": {"enabled": True, "bots": ["cheese"], "exploiter_reset_s": 30, "stats_interval_s": 0.5,
                      "save_interval_s": 1.0, "min_games": 100000, "snapshot_interval_s": 100000,
                      "agents": {"main": {"role": "main"}, "exploiter": {"role": "exploiter", "num_actors": 3}}}}
    path = tmp_path / "league.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def test_an_exploiters_processes_reset_themselves_on_a_new_generation(tmp_path, router, run_id, procs):
    common = ["--config", str(config(tmp_path)), "--router", router, "--run-id", run_id]
    agent = tmp_path / "runs" / run_id / "agents" / f"{run_id}.exploiter"
    ckpts, replay_log = agent / "checkpoints", agent / "replay"
    procs.zenrl("league", ["league", *common])
    roles = {"replay": ["replay", *common, "--agent", "exploiter"],
             "learner": ["learner", *common, "--agent", "exploiter", "--auto-resume"],
             "actor": ["actor", *common, "--agent", "exploiter", "--id", "ex-a0", "--slot", "0"]}
    ps = {name: procs.zenrl(f"exploiter-{name}", argv) for name, argv in roles.items()}

    # the agent's exporter (--agent): its run id, and its own actor count as the expected one
    port = free_port()
    procs.zenrl("exploiter-exporter", ["exporter", *common, "--agent", "exploiter", "--port", str(port),
                                       "--host", "127.0.0.1"])

    def scrape() -> str:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as r:
                return r.read().decode()
        except OSError:
            return ""

    wait_until(lambda: f'zenrl_actors_expected{{run="{run_id}.exploiter"}} 3.0' in scrape(), 60,
               "the exporter's expected actors of the exploiter (3, its league.agents entry)", interval_s=0.5)

    # generation 0 trains: checkpoints and a durable log appear, the markers say 0
    wait_until(lambda: ckpts.is_dir() and any(ckpts.glob("ckpt-*.pt")), 120, "the exploiter's first checkpoint",
               interval_s=0.5)
    assert replay_log.is_dir()
    for role in ("learner", "replay"):
        assert (agent / f"league_generation.{role}").read_text() == "0\n"
    assert all(p.poll() is None for p in ps.values())

    # the league's timer starts generation 1: all three stop by themselves, status 75
    for name, p in ps.items():
        code = wait_until(lambda p=p: p.poll(), 90, f"the exploiter's {name} to exit on the new generation")
        assert code == 75, procs.log(f"exploiter-{name}")[-3000:]
        assert "generation 1" in procs.log(f"exploiter-{name}")
    assert "reset" in procs.log("league")
    assert not ckpts.exists() and not replay_log.exists()
    for role in ("learner", "replay"):
        assert (agent / f"league_generation.{role}").read_text() == "1\n"

    # started again (the restart policy): the learner finds nothing to resume and starts fresh
    # (within the 30 s of generation 1: the league's timer would end it too)
    again = procs.zenrl("exploiter-learner-2", roles["learner"])
    wait_until(lambda: ckpts.is_dir() and any(ckpts.glob("ckpt-*.pt")), 60, "the restarted learner's checkpoint",
               interval_s=0.5)
    assert again.poll() is None, procs.log("exploiter-learner-2")[-2000:]
    again.terminate()
    assert again.wait(60) == 0, procs.log("exploiter-learner-2")[-2000:]
    text = procs.log("exploiter-learner-2")
    assert "resum" not in text.lower() and "generation" not in text, text[-2000:]
