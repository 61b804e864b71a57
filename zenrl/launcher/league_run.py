"""``zenrl run`` of a league config (``league.enabled``): besides the router, the league service
(``zenrl league``, on the launch's run id) and, for each learning agent of ``league.agents``,
its own replay, learner and actors on a run id of its own (``<run>.<agent>``: its keys are
``zenrl/<run>.<agent>/...``, its files ``runs/<run>/agents/<run>.<agent>/``), configured by
:func:`agent_configs`. Only the main agent has an evaluator (against the env's bots).

An exploiter's reset is carried out here: when the league's stats show a higher
``generation/<agent>`` than the one applied, that agent's replay, learner and actors are
stopped, its folder is deleted (checkpoints, weights-version mark, replay log) and they start
afresh; the applied generations are kept in ``runs/<run>/league_applied.json``.
"""

from __future__ import annotations

import json
import logging
import re
from pathlib import Path
from typing import Any

from zenrl.common.config import RunConfig, _set_path
from zenrl.common.errors import ConfigError
from zenrl.league.core import agent_run_id

log = logging.getLogger("zenrl.launcher")

APPLIED_FILE = "league_applied.json"


def agents_dir(cfg: RunConfig, run_id: str) -> Path:
    return Path(cfg.runs_dir) / run_id / "agents"


def agent_configs(cfg: RunConfig, run_id: str) -> dict[str, RunConfig]:
    """The resolved config of each learning agent's processes: the run's, with its own run id
    and runs_dir, ``league.run_id`` / ``league.player`` set, ``actor.num_actors`` /
    ``actor.envs_per_actor`` from its entry, the evaluator only for the main agent, then its
    ``overrides``. A bad override is a :class:`ConfigError` naming the agent."""
    from pydantic import ValidationError

    out = {}
    for aid, agent in cfg.league.agents.items():
        tree: dict[str, Any] = cfg.model_dump(mode="json")
        try:
            tree["run_id"] = agent_run_id(run_id, aid)
        except ValueError as e:
            raise ConfigError(str(e)) from None
        tree["runs_dir"] = str(agents_dir(cfg, run_id))
        tree["league"].update(run_id=run_id, player=aid)
        tree["actor"].update(num_actors=agent.num_actors, envs_per_actor=agent.envs_per_actor)
        if agent.role != "main":
            tree["evaluator"]["enabled"] = False
        for k, v in agent.overrides.items():
            _set_path(tree, k, v)
        try:
            out[aid] = RunConfig.model_validate(tree)
        except ValidationError as e:
            first = e.errors()[0]
            raise ConfigError(f"league.agents.{aid}.overrides: {'.'.join(map(str, first['loc']))}: {first['msg']} "
                              f"(got {first.get('input')!r})") from None
    return out


def check_league(cfg: RunConfig) -> None:
    """What a league run needs, checked before anything starts: a match env whose bots
    include every ``league.bots`` name, ``opponents.pool`` names (frozen players of the league)
    that are valid player ids and clash with no bot or agent, agent configs that validate."""
    if cfg.league.exploiter_init == "main" and cfg.algo not in ("apex", "r2d2"):
        raise ConfigError(f"league.exploiter_init: main starts an exploiter's learner from main's checkpoint "
                          f"(learner.init_from), which algo {cfg.algo} has not; use fresh")
    from zenrl.common.env_factory import make_env

    env = make_env(cfg.env)
    try:
        if not hasattr(env.unwrapped, "opponent_policy"):
            raise ConfigError(f"league.enabled needs a match env (zenrl/BurgerWar*), not env.id={cfg.env.id!r}")
        for b in cfg.league.bots:
            try:
                env.reset(seed=0, options={"opponent": b})
            except ValueError as e:
                raise ConfigError(f"league.bots: {b!r} is no bot of {cfg.env.id}: {e}") from None
    finally:
        env.close()
    taken = set(cfg.league.bots) | set(cfg.league.agents)
    for name in cfg.opponents.pool:
        if name in taken:
            raise ConfigError(f"opponents.pool.{name}: the name is taken by a league bot or agent")
        if not re.fullmatch(r"[A-Za-z][A-Za-z0-9_\-]{0,31}", name) or any(name.startswith(f"{a}-") for a in cfg.league.agents):
            raise ConfigError(f"opponents.pool.{name}: a league player's name is 1-32 letters, digits, '_' or '-', "
                              "starting with a letter and not with an agent's name and '-' (its snapshots' names)")
    agent_configs(cfg, cfg.run_id or "x" * 20)


def agent_config(cfg: RunConfig, agent: str) -> RunConfig:
    """``--agent`` (each role and the health probe): the config of one learning agent's
    processes of the league in ``cfg`` (run id ``<run>.<agent>``, its overrides), as ``zenrl
    run`` resolves it for its own children. A :class:`ConfigError` for a config with no league,
    an unknown agent, or an exploiter that only ``zenrl run`` can reset."""
    if not cfg.league.enabled:
        raise ConfigError(f"--agent {agent}: the config has no league (league.enabled is false)")
    if agent not in cfg.league.agents:
        raise ConfigError(f"--agent {agent!r} is not one of league.agents {sorted(cfg.league.agents)}")
    check_league(cfg)
    lc = cfg.league
    if lc.self_reset and lc.exploiter_init == "main" and lc.agents[agent].role == "exploiter":
        raise ConfigError(f"--agent {agent}: league.exploiter_init main needs zenrl run (it hands the reset exploiter "
                          "main's checkpoint); a cluster's exploiters start fresh: set league.exploiter_init: fresh")
    return agent_configs(cfg, cfg.run_id or "default")[agent]


def read_applied(run_dir: Path) -> dict[str, int]:
    try:
        d = json.loads((run_dir / APPLIED_FILE).read_text())
    except (OSError, ValueError):
        return {}
    return {str(k): int(v) for k, v in d.items()} if isinstance(d, dict) else {}


def write_applied(run_dir: Path, applied: dict[str, int]) -> None:
    from zenrl.launcher.runfolder import write_json_atomic

    write_json_atomic(run_dir / APPLIED_FILE, applied)


def exploiter_init(agents: dict[str, RunConfig], aid: str, run_dir: Path) -> Path | None:
    """Where reset exploiter ``aid`` starts (``league.exploiter_init``): None for fresh weights,
    or a copy of the main agent's newest checkpoint, ``runs/<run>/agents/<aid>.init.pt`` (a copy,
    so that main's learner may prune its own file while the exploiter's learner reads this one).
    None too while main has no checkpoint yet."""
    import os
    import shutil

    from zenrl.common.checkpoints import list_checkpoints

    acfg = agents[aid]
    if acfg.league.exploiter_init != "main" or acfg.league.agents[aid].role != "exploiter":
        return None
    main = next(k for k, a in acfg.league.agents.items() if a.role == "main")
    mcfg = agents[main]
    ckpts = list_checkpoints(Path(mcfg.runs_dir) / (mcfg.run_id or "") / "checkpoints")
    if not ckpts:
        log.info("league: %s starts fresh: %s has no checkpoint yet", aid, main)
        return None
    out = run_dir / "agents" / f"{aid}.init.pt"
    tmp = out.with_suffix(".tmp")
    try:
        shutil.copyfile(ckpts[-1], tmp)
        os.replace(tmp, out)
    except OSError as e:  # pruned between the listing and the copy, or a full disk: start fresh
        log.warning("league: %s starts fresh: cannot copy %s: %s", aid, ckpts[-1], e)
        return None
    log.info("league: %s starts from %s's %s", aid, main, ckpts[-1].name)
    return out
