"""The verdict of ``python -m zenrl.health`` from what it saw (zenrl/health.judge): a token, the
newest stats, and the threads those stats call stalled. The probe itself against real processes
is tests/integration/test_health.py. ``--agent`` against a fake router: the probe looks under the
league agent's run id, as the role with the same ``--agent`` runs."""

import json

import pytest

from tests.conftest import ROOT
from zenrl.health import judge

TOKEN = "zenrl/r/alive/replay/replay"


def test_no_token_is_unhealthy_whatever_the_stats():
    ok, why = judge("replay", TOKEN, "replay", [], {"replay": {"stalled": ""}}, 5.0)
    assert not ok and why == f"no liveliness token {TOKEN} at the router"


def test_token_alone_when_stats_are_not_asked_for():
    assert judge("replay", TOKEN, "replay", ["replay"], {}, None) == (True, "alive")


def test_stats_must_come_from_the_process_itself():
    ok, why = judge("replay", TOKEN, "replay", ["replay"], {"replay-2": {"stalled": ""}}, 5.0)
    assert not ok and "published no stats within 5.0 s" in why


def test_stalled_thread_fails_with_its_name():
    ok, why = judge("replay", TOKEN, "replay", ["replay"], {"replay": {"stalled": "replay-ingest", "size": 10}}, 5.0)
    assert not ok and "replay-ingest" in why and "stalled" in why and "\n" not in why


def test_fresh_stats_without_a_stall_are_healthy():
    # roles outside the role loop publish no ``stalled`` at all; an empty one means none stalled
    for values in ({"stalled": ""}, {"size": 3}):
        assert judge("replay", TOKEN, "replay", ["replay"], {"replay": values}, 5.0) == (True, "alive and publishing stats")


def test_any_matching_process_that_stalls_fails_the_probe():
    stats = {"actor-h-1": {"stalled": ""}, "actor-h-2": {"stalled": "sender,prefetch"}}
    ok, why = judge("actor", "zenrl/r/alive/actor/actor-h-*", "actor-h-*", ["actor-h-1", "actor-h-2"], stats, 5.0)
    assert not ok and "actor-h-2" in why and "sender,prefetch" in why


class _Router:
    """Stands in for the router: the liveliness tokens it holds (no stats are asked for)."""

    tokens: list[str] = []

    def __init__(self, *_args, **_kwargs) -> None:
        pass

    def __enter__(self) -> "_Router":
        return self

    def __exit__(self, *exc) -> None:
        pass

    def alive_now(self, key: str, timeout_s: float = 2.0) -> list[str]:
        prefix = key.rstrip("*")
        return [t for t in self.tokens if t.startswith(prefix)]


def _probe(monkeypatch, capsys, tmp_path, tokens: list[str], *args: str) -> tuple[int, dict]:
    from zenrl import health

    for name in ("ZENRL__RUN_ID", "ZENRL_ROUTER", "ZENRL__RUNS_DIR", "ZENRL__TRANSPORT__CLIENT_CONFIG"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("ZENRL__RUN_ID", "lg")
    monkeypatch.setenv("ZENRL__RUNS_DIR", str(tmp_path))
    monkeypatch.setattr(_Router, "tokens", tokens)
    monkeypatch.setattr(health, "Node", _Router)
    rc = health.main(["--config", str(ROOT / "configs/cluster_league.yaml"), *args])
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 1, lines
    return rc, json.loads(lines[0])


@pytest.mark.parametrize("agent", ["main", "exploiter"])
def test_agent_looks_under_the_agents_run_id(monkeypatch, capsys, tmp_path, agent):
    other = "exploiter" if agent == "main" else "main"
    mine = [f"zenrl/lg.{agent}/alive/replay/replay"]
    rc, out = _probe(monkeypatch, capsys, tmp_path, mine, "--role", "replay", "--id", "replay", "--agent", agent)
    assert (rc, out["ok"], out["run_id"], out["ids"]) == (0, True, f"lg.{agent}", ["replay"]), out
    # the other agent's replay, or a replay of the league's own run id, is not this process
    for tokens in ([f"zenrl/lg.{other}/alive/replay/replay"], ["zenrl/lg/alive/replay/replay"]):
        rc, out = _probe(monkeypatch, capsys, tmp_path, tokens, "--role", "replay", "--id", "replay", "--agent", agent)
        assert rc == 1 and f"zenrl/lg.{agent}/alive/replay/replay" in out["reason"], out


def test_without_agent_the_probe_keeps_the_configs_run_id(monkeypatch, capsys, tmp_path):
    rc, out = _probe(monkeypatch, capsys, tmp_path, ["zenrl/lg.main/alive/replay/replay"], "--role", "replay")
    assert rc == 1 and out["run_id"] == "lg", out


def test_unknown_agent_is_a_one_line_error(monkeypatch, capsys, tmp_path):
    rc, out = _probe(monkeypatch, capsys, tmp_path, ["zenrl/lg.nobody/alive/replay/replay"],
                     "--role", "replay", "--agent", "nobody", "--unreachable-ok")
    assert rc == 1 and not out["ok"] and "not one of league.agents" in out["reason"] and "\n" not in out["reason"], out


def test_the_league_service_is_probed_on_the_leagues_own_run_id(monkeypatch, capsys, tmp_path):
    rc, out = _probe(monkeypatch, capsys, tmp_path, ["zenrl/lg/alive/league/league"],
                     "--role", "league", "--id", "league")
    assert (rc, out["run_id"], out["ids"]) == (0, "lg", ["league"]), out


def test_id_placeholders(tmp_path):
    """--id placeholders: {hostname}, {ordinal} (a StatefulSet pod's index) and {login} (the
    user name of the client config: a secured actor's id, which need not be its pod's ordinal)."""
    import json

    from zenrl.common.errors import ConfigError
    from zenrl.health import resolve_id

    login = tmp_path / "client.json5"
    login.write_text(json.dumps({"mode": "client", "transport": {"auth": {"usrpwd": {"user": "actor-14",
                                                                                  "password": "x"}}}}))
    assert resolve_id("actor-{hostname}-7", "zenrl-actor-3", None) == "actor-zenrl-actor-3-7"
    assert resolve_id("actor-{ordinal}", "zenrl-actor-exploiter-1", None) == "actor-1"
    assert resolve_id("{login}", "zenrl-actor-exploiter-1", str(login)) == "actor-14"
    bare = tmp_path / "bare.json5"
    bare.write_text(json.dumps({"mode": "client"}))
    for cfg in (None, str(bare)):
        with pytest.raises(ConfigError, match="holds no login"):
            resolve_id("{login}", "h", cfg)
