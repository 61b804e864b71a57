"""``zenrl`` command line: one subcommand per role plus the launcher and tools.

Every role command takes ``--config FILE`` and ``--set section.field=value`` (repeatable);
its ``--help`` lists the options that role reads (:data:`ROLE_OPTIONS`), ``zenrl run --help``
and ``zenrl config --list`` every option with its default and description.
"""

from __future__ import annotations

import argparse
import errno
import faulthandler
import logging
import os
import re
import signal
import sys
import threading
from typing import Callable

from zenrl import EXIT_CONFIG
from zenrl.common.config import RunConfig, describe_options, load_config
from zenrl.common.errors import CheckpointError, ConfigError, ZenrlError
from zenrl.placement import apply_from_env

log = logging.getLogger("zenrl")

#: Zenoh error texts end with the Rust source line that raised them: noise to a user
_RUST_SOURCE = re.compile(r"\s+at \S+\.rs:\d+\.?")


def _int_at_least(lo: int) -> Callable[[str], int]:
    """An argparse type: an int >= ``lo`` (a careless value gets argparse's one-line error)."""
    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
        if v < lo:
            raise argparse.ArgumentTypeError(f"must be >= {lo}, got {v}")
        return v
    return parse


def _port(text: str) -> int:
    """An argparse type: a TCP port, 1..65535."""
    v = _int_at_least(1)(text)
    if v > 65535:
        raise argparse.ArgumentTypeError(f"a TCP port is 1..65535, got {v}")
    return v


def _float_above(lo: float, at_most: float | None = None, *, or_equal: bool = False) -> Callable[[str], float]:
    """An argparse type: a finite float > ``lo`` (>= with ``or_equal``; and <= ``at_most``)."""
    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
        low_ok = v >= lo if or_equal else v > lo
        if not low_ok or v == float("inf") or (at_most is not None and v > at_most):
            bound = f"{'>=' if or_equal else '>'} {lo:g}" + ("" if at_most is None else f" and <= {at_most:g}")
            raise argparse.ArgumentTypeError(f"must be {bound}, got {text}")
        return v
    return parse


def _output_file(text: str) -> str:
    """An argparse type: a file this command may write, checked before the work that makes it
    (an evaluation or a match is not run to be lost on a mistyped path): not a directory, in an
    existing directory, and opened for appending once (a file that was not there is removed
    again)."""
    path = os.path.abspath(text)
    parent = os.path.dirname(path)
    if os.path.isdir(path):
        raise argparse.ArgumentTypeError(f"{text!r} is a directory, not a file")
    if not os.path.isdir(parent):
        raise argparse.ArgumentTypeError(f"cannot write {text!r}: no directory {parent!r}")
    existed = os.path.exists(path)
    try:  # the one sure test (root passes access checks that the filesystem still refuses)
        with open(path, "ab"):
            pass
    except OSError as e:
        raise argparse.ArgumentTypeError(f"cannot write {text!r}: {e.strerror or e}") from None
    if not existed:
        try:
            os.unlink(path)
        except FileNotFoundError:  # another process's check removed it first
            pass
    return text


def setup_logging(level: str = "INFO", role: str = "") -> None:
    fmt = f"%(asctime)s %(levelname)s {role + ' ' if role else ''}%(name)s: %(message)s"
    logging.basicConfig(level=getattr(logging, level.upper(), logging.INFO), format=fmt, stream=sys.stderr)


def quiet_zenoh(level: str) -> None:
    """Zenoh's own log at ERROR only (a link closed by the BLOCK fuse still shows), unless zenrl
    logs at DEBUG: its WARN lines (a router not reachable yet, a link closing at shutdown) carry
    Rust source paths and nothing a user acts on. ``RUST_LOG`` overrides."""
    from zenrl.common.transport import init_zenoh_logging

    init_zenoh_logging("warn" if level.upper() == "DEBUG" else "error")


#: The configuration each role process reads: whole sections, or single options as
#: ``section.field`` (a role's ``--help`` lists these; ``zenrl run`` passes every option on).
ROLE_OPTIONS: dict[str, tuple[str, ...]] = {
    # the replay checks R2D2's sequences (of r2d2's length and state size) when algo says so
    # a league agent's processes (--agent) take their config from league.agents, and reset on its generations
    "replay": ("algo", "run_id", "runs_dir", "seed", "replay", "transport", "env", "actor.n_step", "r2d2", "league"),
    "learner": ("algo", "run_id", "runs_dir", "seed", "max_updates", "learner", "a3c", "impala", "r2d2", "network",
                "env", "transport", "actor.num_actors", "replay.shards", "league"),
    "actor": ("algo", "run_id", "runs_dir", "seed", "actor", "a3c", "impala", "r2d2", "selfplay", "opponents", "network",
              "env", "transport", "learner.gamma", "league", "replay.shards"),
    "evaluator": ("algo", "run_id", "runs_dir", "seed", "evaluator", "r2d2", "network", "env", "transport", "league"),
    "exporter": ("run_id", "transport", "actor.num_actors", "league"),
    "league": ("run_id", "runs_dir", "seed", "league", "opponents.pool", "transport"),
}


def _options_epilog(role: str | None = None) -> str:
    """Every option with its default and description, or only those ``role`` reads."""
    rows = describe_options()
    if role is None:
        lines = ["configuration options (YAML file, ZENRL__SECTION__FIELD env vars, or --set section.field=value):"]
    else:
        wanted = ROLE_OPTIONS[role]
        rows = [r for r in rows if r[0] in wanted or r[0].split(".", 1)[0] in wanted]
        lines = [f"configuration options the {role} reads (YAML file, ZENRL__SECTION__FIELD env vars, or "
                 "--set section.field=value; every option: zenrl config --list):"]
    width = max(len(r[0]) for r in rows)
    for name, default, desc in rows:
        lines.append(f"  {name:<{width}}  {desc} [default: {default}]")
    return "\n".join(lines)


def _add_config_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", "-c", help="YAML config file")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                   help="override one config option (repeatable)")
    p.add_argument("--run-id", help="run id (key prefix zenrl/<run-id>/); also config run_id")
    p.add_argument("--router", help="Zenoh router endpoint (also $ZENRL_ROUTER)")
    p.add_argument("--seed", type=_int_at_least(0), help="base random seed")
    p.add_argument("--log-level", default=os.environ.get("ZENRL_LOG_LEVEL", "INFO"), help="logging level")


def _add_credential_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--allow-dev-credentials", action="store_true",
                   help="start even with the repository's development passwords (secured mode; also "
                        "ZENRL_ALLOW_DEV_CREDENTIALS=1): for trying things out, never on a reachable network")


def resolve(args: argparse.Namespace, extra: list[str] | None = None) -> RunConfig:
    ov = list(args.overrides) + list(extra or [])
    if getattr(args, "run_id", None):
        ov.append(f"run_id={args.run_id}")
    if getattr(args, "router", None):
        ov.append(f"transport.router={args.router}")
    if getattr(args, "seed", None) is not None:
        ov.append(f"seed={args.seed}")
    return load_config(args.config, ov)


def _run_role(args: argparse.Namespace, role: str, fn: Callable[[RunConfig, str, threading.Event], None]) -> int:
    from zenrl.common.league_reset import EXIT_GENERATION, GenerationReset
    from zenrl.common.roles import RoleFailed
    from zenrl.common.signals import install_stop_signals
    from zenrl.identity import check_dev_credentials

    setup_logging(args.log_level, role)
    # SIGUSR1 writes every thread's stack to stderr (the child's log under `zenrl run`): where a
    # stuck process is, before the launcher restarts it
    try:
        faulthandler.register(signal.SIGUSR1, all_threads=True)
    except (AttributeError, ValueError, OSError):  # a stderr without a file descriptor (embedded, tests)
        pass
    placed = apply_from_env()  # before any thread starts, so that every thread inherits it
    if placed is not None:
        log.info("cpu placement: CPUs %s, nice +%d", placed.cpus, placed.nice)
    try:
        cfg = resolve(args)
        if getattr(args, "agent", None):
            from zenrl.launcher.league_run import agent_config

            cfg = agent_config(cfg, args.agent)
        check_dev_credentials(cfg.transport.client_config, args.allow_dev_credentials)
        run_id = cfg.run_id or "default"
        stop = threading.Event()
        install_stop_signals(stop)
        _watch_parent(stop)
        fn(cfg, run_id, stop)
    except (ConfigError, CheckpointError) as e:
        log.error("%s", e)
        sys.stderr.write(f"zenrl: error: {e}\n")
        return EXIT_CONFIG
    except GenerationReset as e:  # league.self_reset: the restart policy starts this process afresh
        log.warning("%s", e)
        return EXIT_GENERATION
    except RoleFailed as e:  # the loop cannot go on: exit non-zero so the launcher or engine restarts it
        log.error("%s", e)
        sys.stderr.write(f"zenrl: error: {role} cannot go on: {e}\n")
        return 1
    return 0


def _watch_parent(stop: threading.Event) -> None:
    """Started by ``zenrl run``: stop when the launcher is gone (no orphaned processes)."""
    parent = os.environ.get("ZENRL_PARENT_PID")
    if not parent:
        return

    def watch() -> None:
        while not stop.wait(1.0):
            if os.getppid() != int(parent):
                log.warning("launcher (pid %s) is gone; stopping", parent)
                stop.set()

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def cmd_replay(args: argparse.Namespace) -> int:
    from zenrl.replay.service import main

    shard = args.shard
    if shard is None and os.environ.get("ZENRL_REPLAY_SHARD", "").strip():
        raw = os.environ["ZENRL_REPLAY_SHARD"].strip()
        if not raw.isdigit():
            sys.stderr.write(f"zenrl: error: ZENRL_REPLAY_SHARD={raw!r} must be a shard number (0, 1, ...)\n")
            return EXIT_CONFIG
        shard = int(raw)
    # a shard's default id names it, so that its alive/stats keys differ from the other shards'
    sid = args.id or ("replay" if shard is None else f"replay-{shard}")
    return _run_role(args, "replay", lambda c, r, s: main(c, r, s, sid, shard))


def cmd_learner(args: argparse.Namespace) -> int:
    from zenrl.processes import learner_main

    return _run_role(args, "learner", lambda c, r, s: learner_main(c, r, s, resume=args.resume))


def cmd_actor(args: argparse.Namespace) -> int:
    from zenrl.identity import ACTOR_LOGINS_ENV, bind_actor, take_actor_login
    from zenrl.processes import actor_main

    pool = args.logins or os.environ.get(ACTOR_LOGINS_ENV)
    if pool:  # one login of the pool, held while this process lives: transport.client_config
        try:
            args.overrides.append(f"transport.client_config={take_actor_login(pool)}")
        except ConfigError as e:
            sys.stderr.write(f"zenrl: error: {e}\n")
            return EXIT_CONFIG

    def run(c: RunConfig, r: str, s: threading.Event) -> None:
        # a login actor-<i> is actor actor-<i> on slot <i> (the router drops anything else it sends)
        bound = bind_actor(c.transport.client_config, args.id, args.slot if args.slot is not None else c.actor.slot)
        if bound is not None:
            actor_main(c, r, s, actor_id=bound[0], bound_slot=bound[1])  # claims exactly its own slot
        else:
            actor_main(c, r, s, actor_id=args.id, slot=args.slot)

    return _run_role(args, "actor", run)


def cmd_evaluator(args: argparse.Namespace) -> int:
    from zenrl.actor.evaluator import main

    return _run_role(args, "evaluator", lambda c, r, s: main(c, r, s))


def cmd_exporter(args: argparse.Namespace) -> int:
    from zenrl.exporter import serve

    return _run_role(args, "exporter", lambda c, r, s: serve(c, r, s, args.port, args.host, args.expected_actors,
                                                             args.poll_s))


def cmd_league(args: argparse.Namespace) -> int:
    """``zenrl league`` (the league service) or ``zenrl league status``."""
    if args.action == "status":
        return _league_status(args)
    if args.run_dir:
        raise ConfigError(f"zenrl league: unexpected argument {args.run_dir!r} (did you mean zenrl league status?)")
    from zenrl.league.service import main

    return _run_role(args, "league", lambda c, r, s: main(c, r, s, args.id))


def _league_status(args: argparse.Namespace) -> int:
    from zenrl.launcher.league_status import league_status

    setup_logging(args.log_level, "status")
    quiet_zenoh(args.log_level)
    run_dir = None
    if args.run_dir:
        run_dir, running = _running_run_dir(args)
        if not running:  # a run that stopped: the state its league saved
            return league_status("", args.run_id or run_dir.name, as_json=args.json, run_dir=run_dir)
    cfg = resolve(args)
    if not cfg.run_id:
        raise ConfigError("which league? zenrl league status runs/<run-id>, or --run-id ID --router EP")
    return league_status(cfg.transport.router or "", cfg.run_id, min(cfg.transport.connect_timeout_s, 5.0),
                         cfg.transport.client_config, as_json=args.json, timeout_s=cfg.transport.query_timeout_s)


def _running_run_dir(args: argparse.Namespace):
    """(the run folder ``args.run_dir`` names (a run id typed instead works too), whether its
    league can be asked): ``args.run_id`` / ``args.router`` filled from its ``launcher.json``;
    not asked when its launcher is gone and no ``--router`` was given."""
    from pathlib import Path

    from zenrl.launcher.runfolder import read_launcher_info

    run_dir = Path(args.run_dir)
    if not run_dir.is_dir() and (Path("runs") / args.run_dir).is_dir():
        run_dir = Path("runs") / args.run_dir
    if not run_dir.is_dir():
        raise ConfigError(f"no run folder {args.run_dir!r} (give runs/<run-id>)")
    info = read_launcher_info(run_dir)
    if not args.run_id:
        args.run_id = info["run_id"] if info and info.get("run_id") else run_dir.name
    if not args.router and (info is None or not _alive(info.get("pid"))):
        return run_dir, False
    if not args.router and info is not None:
        args.router = info["router"]
    return run_dir, True


def cmd_router(args: argparse.Namespace) -> int:
    from zenrl.common.signals import install_stop_signals
    from zenrl.common.transport import open_router
    from zenrl.identity import check_router_dev_credentials

    setup_logging(args.log_level, "router")
    try:
        check_router_dev_credentials(args.router_config, args.allow_dev_credentials)
    except ConfigError as e:
        sys.stderr.write(f"zenrl: error: {e}\n")
        return EXIT_CONFIG
    stop = threading.Event()
    install_stop_signals(stop)
    listen = args.listen or ["tcp/0.0.0.0:7447"]
    session = open_router(listen, args.router_config, args.connect or (), replace_listen=bool(args.listen))
    log.info("router up, listening on %s, linking to %s", args.listen or args.router_config or listen,
             args.connect or "no other router")
    try:
        stop.wait()
    finally:
        session.close()
    return 0


def cmd_credentials(args: argparse.Namespace) -> int:
    import json

    from zenrl.identity import make_credentials

    setup_logging(args.log_level, "credentials")
    owner = tuple(int(x) for x in args.owner.split(":")) if args.owner else None
    out = make_credentials(args.templates, args.out, args.actors, ca=args.ca, dev=args.dev, force=args.force,
                           owner=owner, users_file=args.users_file)  # type: ignore[arg-type]
    sys.stdout.write(json.dumps(out) + "\n")
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    from zenrl.launcher import launch

    setup_logging(args.log_level, "run")
    quiet_zenoh(args.log_level)
    extra = []
    if args.actors is not None:
        extra.append(f"actor.num_actors={args.actors}")
    if args.no_progress:
        extra.append("progress=false")
    if args.resume:
        if not os.path.isdir(args.resume):
            raise ConfigError(f"--resume {args.resume!r}: no such run folder")
        if not os.path.isfile(os.path.join(args.resume, "config.yaml")):
            raise ConfigError(f"--resume {args.resume!r} is not a run folder (it has no config.yaml)")
        if not args.config:
            args.config = os.path.join(args.resume, "config.yaml")
    cfg = resolve(args, extra)
    return launch(cfg, resume_dir=args.resume, exporter_port=args.exporter_port)


def cmd_status(args: argparse.Namespace) -> int:
    from pathlib import Path

    from zenrl.launcher.runfolder import read_launcher_info, read_summary
    from zenrl.launcher.status_client import status

    setup_logging(args.log_level, "status")
    quiet_zenoh(args.log_level)
    run_dir = None
    if args.run_dir:
        run_dir = Path(args.run_dir)
        if not run_dir.is_dir() and (Path("runs") / args.run_dir).is_dir():
            run_dir = Path("runs") / args.run_dir  # a run id typed instead of its folder
        if not run_dir.is_dir():
            raise ConfigError(f"no run folder {args.run_dir!r} (give runs/<run-id>)")
        info = read_launcher_info(run_dir)
        if info is not None and not _alive(info.get("pid")) and not args.router:
            # a launcher that was killed leaves its launcher.json behind
            sys.stderr.write(f"zenrl status: run {run_dir.name} is not running: its launcher (pid {info.get('pid')}) "
                             f"is gone; zenrl run --resume {run_dir} continues it\n")
            return 1
        if info is None and not args.router:
            ended = read_summary(run_dir)
            if ended is not None:
                sys.stderr.write(f"zenrl status: run {run_dir.name} is not running; it stopped: "
                                 f"{ended.get('stop_reason') or 'reason unknown'} (see {run_dir / 'summary.json'})\n")
                return 1
            raise ConfigError(f"{str(run_dir)!r} has no launcher.json (not started by zenrl run, or its launcher "
                              "was killed): give --router EP")
        if not args.run_id:
            args.run_id = info["run_id"] if info and info.get("run_id") else run_dir.name
        if info is not None and not args.router:
            args.router = info["router"]
    cfg = resolve(args)
    if not cfg.run_id:
        raise ConfigError("which run? zenrl status runs/<run-id> (a run of zenrl run), or --run-id ID --router EP")
    # a league run: its agents' processes run under <run>.<agent> (their configs are in agents/)
    agents = sorted(p.stem for p in (run_dir / "agents").glob("*.yaml")) if run_dir is not None else []
    return status(cfg.transport.router or "", cfg.run_id, min(cfg.transport.connect_timeout_s, 5.0),
                  cfg.transport.client_config, run_dir, as_json=args.json, wait_s=args.wait,
                  sub_runs=[f"{cfg.run_id}.{a}" for a in agents])


def _alive(pid: object) -> bool:
    """Whether process ``pid`` exists on this machine (a run folder's launcher)."""
    if not isinstance(pid, int) or pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


def cmd_config(args: argparse.Namespace) -> int:
    if args.list:
        sys.stdout.write(_options_epilog() + "\n")
        return 0
    import yaml

    cfg = resolve(args)
    sys.stdout.write(yaml.safe_dump(cfg.model_dump(), sort_keys=False))
    return 0


def _json_arg(text: str | None) -> dict:
    import json

    if not text:
        return {}
    try:
        v = json.loads(text)
    except json.JSONDecodeError as e:
        raise ZenrlError(f"--env-kwargs is not valid JSON: {e}") from None
    if not isinstance(v, dict):
        raise ZenrlError(f"--env-kwargs must be a JSON object, got {text!r}")
    return v


def cmd_evaluate(args: argparse.Namespace) -> int:
    from rich.console import Console

    from zenrl import strict_json, tools

    setup_logging(args.log_level, "evaluate")
    tools.quiet_native_imports()
    if args.round_robin:
        return _round_robin(args)
    if not args.checkpoint:
        raise ZenrlError("evaluate needs --checkpoint (or --round-robin PLAYERS)")
    opponents = [o.strip() for o in args.opponents.split(",") if o.strip()]
    summary = tools.evaluate(args.checkpoint, args.env, _json_arg(args.env_kwargs), opponents, args.episodes,
                             args.workers, args.seed, progress=not args.no_progress, policy=args.policy,
                             allow_exported=args.exported)
    Console(width=None if sys.stdout.isatty() else 120).print(tools.render_table(summary))
    if args.json:
        with open(args.json, "w") as f:
            f.write(strict_json.dumps(summary, indent=1, default=float))
    brief = {k: v for k, v in summary.items() if k != "results"}
    tools.print_json_line(brief)
    return 0


def _round_robin(args: argparse.Namespace) -> int:
    """``zenrl evaluate --round-robin A,B,...``: every pair plays --episodes matches."""
    from rich.console import Console

    from zenrl import strict_json, tools

    if args.policy != "greedy":
        raise ZenrlError("--round-robin plays greedy policies only (no --policy sample)")
    players = [o.strip() for o in args.round_robin.split(",") if o.strip()]
    if args.checkpoint:
        players.insert(0, args.checkpoint)
    summary = tools.round_robin(players, args.episodes, args.env, _json_arg(args.env_kwargs), args.workers, args.seed,
                                progress=not args.no_progress, allow_exported=args.exported, anchor=args.anchor)
    console = Console(width=None if sys.stdout.isatty() else 160)
    for table in tools.render_round_robin(summary):
        console.print(table)
    if args.json:
        with open(args.json, "w") as f:
            f.write(strict_json.dumps(summary, indent=1, default=float))
    tools.print_json_line({k: v for k, v in summary.items() if k != "results"})
    return 0


def cmd_play(args: argparse.Namespace) -> int:
    from zenrl import tools

    setup_logging(args.log_level, "play")
    tools.quiet_native_imports()
    out = tools.play(args.checkpoint, args.out, args.env, _json_arg(args.env_kwargs), args.opponent, args.side,
                     args.seed, args.fps, args.max_steps, args.speedup, allow_exported=args.exported)
    tools.print_json_line(out)
    return 0


def cmd_plot(args: argparse.Namespace) -> int:
    from zenrl import tools

    setup_logging(args.log_level, "plot")
    w, h = (int(x) for x in args.size.lower().split("x"))
    tools.print_json_line(tools.plot(args.run_dir, args.out, w, h))
    return 0


def cmd_export(args: argparse.Namespace) -> int:
    from zenrl import tools

    setup_logging(args.log_level, "export")
    tools.quiet_native_imports()
    from zenrl.tools.torchscript import GUARD_ANGLE_DEG, GUARD_RADIUS_M

    guard = None
    if args.guard:
        guard = (GUARD_RADIUS_M if args.guard_radius is None else args.guard_radius,
                 GUARD_ANGLE_DEG if args.guard_angle is None else args.guard_angle)
    if tools.is_exported(args.checkpoint):
        # an exported file can only be wrapped (its weights are a program's now)
        if not args.exported:
            raise ZenrlError(f"{args.checkpoint} is an exported policy (a TorchScript program, which runs code when "
                             "loaded): pass --exported to wrap it with --guard, for a file you trust")
        if guard is None or args.member or args.env or args.env_kwargs:
            raise ZenrlError(f"{args.checkpoint} is already an exported policy: export takes checkpoints; of an "
                             "exported file it only writes a guarded copy (--guard, without --member, --env, --env-kwargs)")
        tools.print_json_line(tools.guard_exported(args.checkpoint, args.out, *guard))
        return 0
    tools.print_json_line(tools.export(args.checkpoint, args.out, args.env, _json_arg(args.env_kwargs), args.member, guard))
    return 0


def cmd_average(args: argparse.Namespace) -> int:
    from zenrl import tools
    from zenrl.tools.averaging import average

    setup_logging(args.log_level, "average")
    tools.print_json_line(average(args.sources, args.out, args.last))
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="zenrl", description="Distributed actor-learner RL over Eclipse Zenoh.",
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--version", action="version", version=f"zenrl {_version()}")
    sub = p.add_subparsers(dest="command", required=True)
    fmt = argparse.RawDescriptionHelpFormatter

    s = sub.add_parser("run", help="run everything on this machine (embedded router)", epilog=_options_epilog(),
                       formatter_class=fmt)
    _add_config_args(s)
    s.add_argument("--actors", type=_int_at_least(1), help="number of actor processes (actor.num_actors)")
    s.add_argument("--resume", metavar="RUN_DIR", help="resume the run in RUN_DIR (runs/<id>) from its newest checkpoint")
    s.add_argument("--no-progress", action="store_true", help="no live progress display")
    s.add_argument("--exporter-port", type=_port, metavar="PORT",
                   help="also start `zenrl exporter` on this port: Prometheus metrics of the run (docs/monitoring.md)")
    s.set_defaults(func=cmd_run)

    s = sub.add_parser("replay", help="the prioritized replay service", epilog=_options_epilog("replay"), formatter_class=fmt)
    _add_config_args(s)
    s.add_argument("--id", default=None, help="service id (default: replay, or replay-<k> for shard k)")
    s.add_argument("--agent", metavar="ID", help="a league agent's process (a key of league.agents): its run id "
                   "<run>.<ID> and overrides, as zenrl run gives them (a cluster's league; docs/cluster.md)")
    s.add_argument("--shard", type=_int_at_least(0), default=None, metavar="K",
                   help="this service's shard when replay.shards > 1 (0..shards-1; also $ZENRL_REPLAY_SHARD)")
    _add_credential_args(s)
    s.set_defaults(func=cmd_replay)

    s = sub.add_parser("learner", help="the learner", epilog=_options_epilog("learner"), formatter_class=fmt)
    _add_config_args(s)
    s.add_argument("--agent", metavar="ID", help="a league agent's process (a key of league.agents): its run id "
                   "<run>.<ID> and overrides, as zenrl run gives them (a cluster's league; docs/cluster.md)")
    g = s.add_mutually_exclusive_group()
    g.add_argument("--resume", action="store_const", const="require", dest="resume", default="never",
                   help="continue from the newest valid checkpoint of the run (an error if there is none)")
    g.add_argument("--auto-resume", action="store_const", const="auto", dest="resume",
                   help="continue from the newest valid checkpoint if there is one, else start fresh (for restart policies)")
    _add_credential_args(s)
    s.set_defaults(func=cmd_learner)

    s = sub.add_parser("actor", help="an actor process (many envs)", epilog=_options_epilog("actor"), formatter_class=fmt)
    _add_config_args(s)
    s.add_argument("--id", default=None,
                   help="actor id (default: actor-<host>-<pid>; in secured mode the login's, actor-<i>)")
    s.add_argument("--slot", type=_int_at_least(0), default=None,
                   help="exploration slot (default: from config or the running system; in secured mode the login's, <i>)")
    s.add_argument("--agent", metavar="ID", help="a league agent's process (a key of league.agents): its run id "
                   "<run>.<ID> and overrides, as zenrl run gives them (a cluster's league; docs/cluster.md)")
    s.add_argument("--logins", metavar="DIR",
                   help="secured mode: take the first free actor login (client-actor-<i>.json5) of DIR as "
                        "transport.client_config (also $ZENRL_ACTOR_LOGINS; replicas of one template)")
    _add_credential_args(s)
    s.set_defaults(func=cmd_actor)

    s = sub.add_parser("evaluator", help="greedy evaluation of the latest weights", epilog=_options_epilog("evaluator"),
                       formatter_class=fmt)
    _add_config_args(s)
    s.add_argument("--agent", metavar="ID", help="the league's main agent (a key of league.agents): its run id "
                   "<run>.<ID>, as zenrl run gives it (a cluster's league; docs/cluster.md)")
    _add_credential_args(s)
    s.set_defaults(func=cmd_evaluator)

    s = sub.add_parser("exporter", help="Prometheus metrics of a run's stats and health on an HTTP port",
                       epilog=_options_epilog("exporter"), formatter_class=fmt)
    _add_config_args(s)
    s.add_argument("--port", type=_port, default=9464, help="HTTP port of /metrics")
    s.add_argument("--host", default="0.0.0.0", help="address to listen on (default every interface)")
    s.add_argument("--expected-actors", type=_int_at_least(0), default=None,
                   help="actor processes the run should have (default actor.num_actors, or the agent's "
                        "league.agents.<ID>.num_actors with --agent): zenrl_actors_expected")
    s.add_argument("--agent", metavar="ID", help="watch a league agent's processes (a key of league.agents): its "
                   "run id <run>.<ID> and actor count, as zenrl run gives them (a cluster's league)")
    s.add_argument("--poll-s", type=_float_above(0), default=1.0, help="how often the liveliness tokens are polled (seconds)")
    _add_credential_args(s)
    s.set_defaults(func=cmd_exporter)

    s = sub.add_parser("league", help="the league service (players, payoff table, PFSP), or `zenrl league status`",
                       epilog=_options_epilog("league"), formatter_class=fmt)
    s.add_argument("action", nargs="?", choices=("serve", "status"), default="serve",
                   help="serve (default): run the league service; status: show a running league's players, "
                        "ratings and the main agent's opponent distribution")
    s.add_argument("run_dir", nargs="?", metavar="RUN_DIR",
                   help="status: runs/<run-id> of a running zenrl run (else give --run-id and --router)")
    _add_config_args(s)
    s.add_argument("--id", default="league", help="service id")
    s.add_argument("--json", action="store_true", help="status: print JSON")
    _add_credential_args(s)
    s.set_defaults(func=cmd_league)

    s = sub.add_parser("router", help="a standalone Zenoh router (Python)")
    s.add_argument("--listen", action="append", help="endpoint to listen on (repeatable)")
    s.add_argument("--connect", action="append",
                   help="another router to link to (repeatable): a host router names the central one, e.g. tcp/central:7447")
    s.add_argument("--router-config", help="JSON5 router config file (--listen / --connect replace its endpoints)")
    s.add_argument("--log-level", default="INFO")
    _add_credential_args(s)
    s.set_defaults(func=cmd_router)

    s = sub.add_parser("credentials", help="fresh credentials of a secured cluster: passwords, users file, "
                                           "client configs, router configs with per-actor access control")
    s.add_argument("--out", required=True, help="directory to write (kept as it is if it already holds users.txt)")
    s.add_argument("--actors", type=_int_at_least(1), default=16, help="actor logins actor-0 .. actor-<N-1> (default 16)")
    s.add_argument("--templates", default="deploy/zenoh",
                   help="directory with router-secure.json5 and host-router-secure.json5 (default deploy/zenoh)")
    s.add_argument("--ca", default="/certs/ca.pem", help="CA certificate path written into the client configs")
    s.add_argument("--dev", action="store_true", help="the repository's development passwords instead of random ones")
    s.add_argument("--force", action="store_true", help="overwrite an existing set")
    s.add_argument("--owner", metavar="UID:GID", help="owner of the files written (a root setup container)")
    s.add_argument("--users-file", metavar="PATH",
                   help="where the routers read users.txt (default the templates' /zenoh/users.txt)")
    s.add_argument("--log-level", default="WARNING")
    s.set_defaults(func=cmd_credentials)

    s = sub.add_parser("status", help="show the live processes of a run: zenrl status runs/<run-id>")
    s.add_argument("run_dir", nargs="?", metavar="RUN_DIR",
                   help="runs/<run-id> of a running zenrl run (its router is recorded there); "
                        "otherwise give --run-id and --router")
    _add_config_args(s)
    s.add_argument("--json", action="store_true", help="print JSON")
    s.add_argument("--wait", type=_float_above(0, or_equal=True), default=3.0,
                   help="listen at most this many seconds (rates need two reports of each process)")
    s.set_defaults(func=cmd_status)

    s = sub.add_parser("config", help="print the resolved config (or --list every option)")
    _add_config_args(s)
    s.add_argument("--list", action="store_true", help="list every option with its description")
    s.set_defaults(func=cmd_config)

    def policy_args(s: argparse.ArgumentParser, required: bool = True) -> None:
        s.add_argument("--checkpoint",
                       help="a checkpoint file, or a run folder (runs/<id>) or checkpoints folder: its newest "
                            "checkpoint; with --exported (evaluate and play) also a `zenrl export` file, e.g. models/*.pt")
        # `zenrl evaluate runs/<id>`, as `zenrl status runs/<id>` and `zenrl plot runs/<id>` take it
        s.add_argument("checkpoint_pos", nargs="?", metavar="RUN", help="the same as --checkpoint")
        s.set_defaults(_policy_parser=s, _checkpoint_required=required)
        s.add_argument("--env", help="env id (default: the one the checkpoint was trained on)")
        s.add_argument("--env-kwargs", help="JSON object merged over the checkpoint's env.kwargs, e.g. '{\"match_time\": 60}'")
        s.add_argument("--log-level", default=os.environ.get("ZENRL_LOG_LEVEL", "WARNING"), help="logging level")

    exported_help = ("allow `zenrl export` files as --checkpoint or opponents: they are TorchScript programs, "
                     "which run code when loaded (only for files you trust; checkpoints load without running code)")
    s = sub.add_parser("evaluate", help="play N greedy matches per opponent (both sides) and report win rates; "
                                        "or a round robin of several policies and bots with Elo ratings")
    policy_args(s, required=False)
    s.add_argument("--exported", action="store_true", help=exported_help)
    s.add_argument("--opponents", default="cheese,teriyaki,clubhouse,waypoint",
                   help="comma-separated match opponents: bot names, or checkpoint / exported policy files "
                        "(e.g. an earlier snapshot); ignored for non-match envs")
    s.add_argument("--round-robin", metavar="PLAYERS",
                   help="comma-separated bots and checkpoint / exported policy files (plus --checkpoint if given): "
                        "every pair plays --episodes matches (half on each side, each on a fresh seed from --seed; two "
                        "bots do not meet), reported as a win/draw/loss table and Elo ratings with 95%% intervals")
    s.add_argument("--anchor", metavar="PLAYER", help="round robin: the player rated 0 (default: the mean rating is 0)")
    s.add_argument("--episodes", type=_int_at_least(1), default=20,
                   help="episodes per opponent (half red, half blue); with --round-robin, matches per pair")
    s.add_argument("--workers", type=_int_at_least(1), default=max(1, (os.cpu_count() or 2) - 1), help="parallel processes")
    s.add_argument("--seed", type=_int_at_least(0), default=2_000_000, help="first episode seed")
    s.add_argument("--policy", choices=("greedy", "sample"), default="greedy",
                   help="greedy: argmax; sample: draw from an a3c checkpoint's action distribution (seeded per episode)")
    s.add_argument("--json", metavar="OUT", type=_output_file, help="also write the full results (every episode) as JSON here")
    s.add_argument("--no-progress", action="store_true", help="no progress bar")
    s.set_defaults(func=cmd_evaluate)

    s = sub.add_parser("play", help="render one greedy episode to a GIF or MP4")
    policy_args(s)
    s.add_argument("--exported", action="store_true", help=exported_help)
    s.add_argument("--out", required=True, type=_output_file, help="output file, .gif (pillow) or .mp4 (imageio-ffmpeg)")
    s.add_argument("--opponent", help="match opponent (default: drawn from the env's opponents)")
    s.add_argument("--side", choices=["red", "blue"], help="match side (default: the env's)")
    s.add_argument("--seed", type=_int_at_least(0), default=0, help="episode seed")
    s.add_argument("--fps", type=_float_above(0), help="frames per second of the episode (default: real time)")
    s.add_argument("--speedup", type=_float_above(0), default=1.0,
                   help="play this many times faster, e.g. 4 for a 3-minute match in 45 s (a GIF keeps every "
                        "k-th frame above 25 fps)")
    s.add_argument("--max-steps", type=_int_at_least(1), help="stop after this many steps")
    s.set_defaults(func=cmd_play)

    s = sub.add_parser("plot", help="learning curves of a run (metrics.jsonl) as a PNG")
    s.add_argument("run_dir", help="runs/<id> (or a metrics.jsonl file)")
    s.add_argument("--out", default="curves.png", type=_output_file, help="output PNG")
    s.add_argument("--size", default="1200x800", help="WIDTHxHEIGHT in pixels")
    s.add_argument("--log-level", default="WARNING")
    s.set_defaults(func=cmd_plot)

    s = sub.add_parser("export", help="the greedy policy as a TorchScript file (torch.jit.load, no zenrl needed)")
    policy_args(s)
    s.add_argument("--out", required=True, type=_output_file, help="output .pt file")
    s.add_argument("--member", action="append", default=[], metavar="CHECKPOINT",
                   help="another checkpoint of the same env (repeatable): the file is a mixed policy, one member "
                        "(drawn uniformly) playing each match")
    s.add_argument("--guard", action="store_true",
                   help="a match policy with the enemy detector: turn to face the other robot, on the spot, whenever "
                        "it is seen nearer than --guard-radius and more than --guard-angle off the heading (the "
                        "robot's markers are on its sides and back); with --exported, --checkpoint may be an "
                        "exported file to wrap")
    # defaults: zenrl.tools.torchscript.GUARD_RADIUS_M, GUARD_ANGLE_DEG (not imported here: torch)
    s.add_argument("--guard-radius", type=_float_above(0), metavar="M", help="the guard's reach in metres (1.2)")
    s.add_argument("--guard-angle", type=_float_above(0, 180), metavar="DEG",
                   help="the guard turns when the other robot is more than this many degrees off the heading (15)")
    s.add_argument("--exported", action="store_true", help="with --guard: --checkpoint may be a `zenrl export` file "
                                                           "(a program, which runs code when loaded: only one you trust)")
    s.set_defaults(func=cmd_export)

    s = sub.add_parser("average", help="one checkpoint whose policy weights are the mean of several checkpoints' "
                                       "(stochastic weight averaging): steadier than any one of them")
    s.add_argument("sources", nargs="+", metavar="CHECKPOINT",
                   help="ckpt-*.pt files of one run, or a run folder (runs/<id>) or checkpoints folder")
    s.add_argument("--last", type=_int_at_least(1), default=None, metavar="K",
                   help="for a folder: its newest K checkpoints (default: all)")
    s.add_argument("--out", required=True, type=_output_file, help="output checkpoint file (not in a checkpoints folder you resume from)")
    s.add_argument("--log-level", default=os.environ.get("ZENRL_LOG_LEVEL", "WARNING"), help="logging level")
    s.set_defaults(func=cmd_average)
    return p


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("zenrl")
    except PackageNotFoundError:
        from zenrl import __version__

        return __version__


def _policy_checkpoint(args: argparse.Namespace) -> None:
    """``--checkpoint`` or the positional ``RUN`` of evaluate, play and export (one of them; the
    parser's usage error when both differ, or when a command that needs one has neither)."""
    parser = getattr(args, "_policy_parser", None)
    if parser is None:
        return
    if args.checkpoint_pos is not None:
        if args.checkpoint is not None and args.checkpoint != args.checkpoint_pos:
            parser.error(f"two checkpoints: --checkpoint {args.checkpoint} and {args.checkpoint_pos}; give one")
        args.checkpoint = args.checkpoint_pos
    if args._checkpoint_required and not args.checkpoint:
        parser.error("the following arguments are required: --checkpoint (or the run folder or checkpoint as the "
                     "first argument: runs/<id>)")


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    _policy_checkpoint(args)
    # A one-shot command (evaluate, export, status, ...) stops on SIGTERM as on Ctrl-C: its
    # finally blocks run (an evaluation's worker pool is terminated, not orphaned). The roles
    # and `zenrl run` replace this with their own orderly stop (zenrl.common.signals).
    main_thread = threading.current_thread() is threading.main_thread()
    before = signal.signal(signal.SIGTERM, signal.default_int_handler) if main_thread else None
    try:
        return int(args.func(args) or 0)
    except ZenrlError as e:
        sys.stderr.write(f"zenrl: error: {_RUST_SOURCE.sub('', str(e))}\n")
        return 2
    except KeyboardInterrupt:
        sys.stderr.write("zenrl: interrupted\n")
        return 130
    except OSError as e:
        if e.errno not in (errno.ENOSPC, errno.EDQUOT, errno.EROFS):
            raise
        # a full or read-only disk: in one line, naming the file where the error does
        where = "" if e.filename else " (writing the run folder, its logs or checkpoints: see runs_dir)"
        sys.stderr.write(f"zenrl: error: {e}{where}\n")
        return 1
    finally:
        if main_thread and before is not None and signal.getsignal(signal.SIGTERM) is signal.default_int_handler:
            signal.signal(signal.SIGTERM, before)


if __name__ == "__main__":
    sys.exit(main())
