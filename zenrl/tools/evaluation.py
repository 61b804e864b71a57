"""``zenrl evaluate``: N episodes (matches: per opponent, half as red, half as blue) in ``spawn``
worker processes (no Zenoh), summarised with confidence intervals; and ``zenrl evaluate
--round-robin``: every pair of a set of policies and bots plays N matches, summarised as a
pairwise win / draw / loss table and Elo ratings (:mod:`zenrl.common.ratings`)."""

from __future__ import annotations

import math
import multiprocessing as mp
import os
import signal
import threading
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np
import torch

from zenrl.actor.env_guard import reward_number
from zenrl.common.errors import ZenrlError
from zenrl.common.ratings import PairRecord, fit_ratings
from zenrl.games.burgerwar.judge import match_outcome, robot_marker_points
from zenrl.games.burgerwar.opponents import OPPONENT_NAMES
from zenrl.tools.loading import (MATCH_OPPONENTS, is_match_env, load_player, load_policy_env, quiet_native_imports,
                                 resolve_checkpoint)
from zenrl.tools.stats import mean_ci, wilson

@dataclass(frozen=True)
class Job:
    """One evaluation episode: ``opponent`` None for a non-match env; ``side`` "red"/"blue"."""

    index: int
    seed: int
    opponent: str | None = None
    side: str | None = None


@dataclass
class EpisodeResult:
    index: int
    seed: int
    opponent: str | None
    side: str | None
    ret: float
    length: int
    outcome: str | None = None  # "win" | "draw" | "loss" (match envs)
    my_score: int | None = None
    enemy_score: int | None = None
    robot_points: tuple[int, int] | None = None  # (mine, the enemy's) from robot markers


def split_opponents(opponents: Sequence[str]) -> tuple[list[str], list[str]]:
    """(scripted bot names, policy files) of an ``--opponents`` list: a bot's name, or the path
    of a checkpoint or an exported file (a frozen policy, e.g. an earlier snapshot). Anything
    else is a :class:`ZenrlError` naming it."""
    bots, files = [], []
    for o in opponents:
        if o in OPPONENT_NAMES and o != "policy":
            bots.append(o)
        elif Path(o).is_file():
            files.append(o)
        else:
            raise ZenrlError(f"opponent {o!r} is neither a bot ({', '.join(n for n in OPPONENT_NAMES if n != 'policy')}) "
                             "nor an existing checkpoint or exported policy file")
    return bots, files


class _Switch:
    """The env's ``opponent_policy``: forwards to whichever frozen policy the episode plays."""

    def __init__(self) -> None:
        self.current = None

    def __call__(self, obs: Any) -> int:
        return self.current(obs)


class EpisodeRunner:
    """Loads the checkpoint (or exported file) once and plays :class:`Job` episodes (one per
    call). ``opponents`` may name policy files as well as bots (:func:`split_opponents`)."""

    def __init__(self, checkpoint: str, env_id: str | None, env_kwargs: Mapping[str, Any] | None,
                 opponents: Sequence[str] | None, sample: bool = False, allow_exported: bool = False) -> None:
        torch.set_num_threads(1)
        bots, files = split_opponents(opponents) if opponents else (None, [])
        if files and not bots:
            bots = ["idle"]  # the env needs one scripted bot to start from; every job names its own
        self.policy, self.env, _ = load_policy_env(checkpoint, env_id, env_kwargs, opponents=bots, sample=sample,
                                                   allow_exported=allow_exported)
        self.frozen = {}
        if files:
            self.switch = _Switch()
            self.env.unwrapped.opponent_policy = self.switch  # built on the first episode that names "policy"
            self.frozen = {f: load_player(f, self.env.observation_space, self.env.action_space, allow_exported)
                           for f in files}

    def run(self, job: Job) -> EpisodeResult:
        self.policy.reseed(job.seed)  # a sampled episode depends on its job only, not on the worker
        self.policy.reset()  # a recurrent policy starts the episode from a zero state
        options = {}
        if job.opponent in self.frozen:
            self.switch.current = self.frozen[job.opponent]
            reseed = getattr(self.switch.current, "reseed", None)  # a player is any obs -> action callable
            if reseed is not None:
                reseed(job.seed + 1)  # a mixed policy's member: the job's own draw, whichever worker plays it
            reset = getattr(self.switch.current, "reset", None)
            if reset is not None:
                reset()
            options = {"opponent": "policy", "side": job.side}
        elif job.opponent is not None:
            options = {"opponent": job.opponent, "side": job.side}
        obs, info = self.env.reset(seed=job.seed, options=options or None)
        ret, n, done = 0.0, 0, False
        while not done:
            obs, r, term, trunc, info = self.env.step(self.policy(obs))
            ret += r if type(r) is float else reward_number(r, self.env.spec.id if self.env.spec else "this env")
            n += 1
            done = term or trunc
        res = EpisodeResult(job.index, job.seed, job.opponent, job.side, ret, n)
        if job.opponent is not None:
            # the env's own result (info["outcome"]); a match cut off by an outer TimeLimit has none and is judged here
            res.outcome, res.my_score, res.enemy_score = ((info["outcome"], info["my_score"], info["enemy_score"]) if "outcome" in info
                                                          else match_outcome(info))
            res.robot_points = robot_marker_points(info)
        return res

    def close(self) -> None:
        self.env.close()


_RUNNER: EpisodeRunner | None = None  # one per worker process (set by the pool initializer)


def _init_pool_worker(initializer: Callable[..., None], initargs: tuple[Any, ...]) -> None:
    # Ctrl-C reaches every process of the terminal's group: it is the parent's to act on. A
    # worker interrupted inside the pool's queue leaves its lock held, and the pool's shutdown
    # then waits forever (seen: a KeyboardInterrupt traceback, then a hang).
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    parent = os.getppid()

    def watch() -> None:  # a parent killed outright (SIGKILL) cannot stop the pool: end with it
        while os.getppid() == parent:
            time.sleep(1.0)
        os._exit(1)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()
    initializer(*initargs)


def run_pooled(workers: int, initializer: Callable[..., None], initargs: tuple[Any, ...],
               fn: Callable[[Any], Any], jobs: Sequence[Any], on_result: Callable[[Any], None]) -> None:
    """``on_result(fn(job))`` for every job, as each finishes, in ``workers`` ``spawn``
    processes set up by ``initializer(*initargs)``, with at most two jobs per worker queued at a
    time. Ctrl-C or SIGTERM (noted by a handler that only records it: an exception raised inside
    the pool's own calls, a submit or its wake-up pipe, could leave it unable to shut down, and
    the interpreter's exit waiting for it), or an exception (a job's), stops the pool at once:
    the queued jobs are cancelled and the workers terminated, not waited for; then
    KeyboardInterrupt, or that exception, is raised."""
    noted: list[int] = []
    before: dict[int, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            before[sig] = signal.signal(sig, lambda signum, _frame: noted.append(signum))  # no lock taken
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"),
                               initializer=_init_pool_worker, initargs=(initializer, initargs))
    try:
        todo = iter(jobs)
        queued: set[Any] = set()
        more = True
        while True:
            while more and len(queued) < 2 * workers and not noted:
                job = next(todo, _NO_JOB)
                more = job is not _NO_JOB
                if more:
                    queued.add(pool.submit(fn, job))
            if noted:
                raise KeyboardInterrupt
            if not queued:
                break
            done, queued = wait(queued, timeout=0.2, return_when=FIRST_COMPLETED)
            for fut in done:
                on_result(fut.result())
    except BaseException:
        procs = list((getattr(pool, "_processes", None) or {}).values())
        pool.shutdown(wait=False, cancel_futures=True)
        for p in procs:
            p.terminate()
        for p in procs:
            p.join(5)
        if noted:  # whatever surfaced first (a worker hit by the same Ctrl-C breaks the pool)
            raise KeyboardInterrupt from None
        raise
    finally:
        for sig, handler in before.items():
            signal.signal(sig, handler)
    pool.shutdown()


#: the end of the jobs (a job may be any value, None too)
_NO_JOB = object()


def _init_worker(checkpoint: str, env_id: str | None, env_kwargs: Mapping[str, Any] | None,
                 opponents: Sequence[str] | None, sample: bool = False, allow_exported: bool = False) -> None:
    global _RUNNER
    quiet_native_imports()  # the worker shares the parent's stdout, whose last line is the JSON
    _RUNNER = EpisodeRunner(checkpoint, env_id, env_kwargs, opponents, sample, allow_exported)


def _run_job(job: Job) -> EpisodeResult:
    if _RUNNER is None:
        raise RuntimeError("worker not initialised")
    return _RUNNER.run(job)


def make_jobs(episodes: int, opponents: Sequence[str] | None, seed: int) -> list[Job]:
    """``episodes`` per opponent, alternating red/blue (same seeds for every opponent); one
    list of plain episodes when ``opponents`` is None."""
    if not opponents:
        return [Job(i, seed + i) for i in range(episodes)]
    jobs = []
    for opp in opponents:
        for j in range(episodes):
            jobs.append(Job(len(jobs), seed + j, opp, "red" if j % 2 == 0 else "blue"))
    return jobs


def summarize(results: Iterable[EpisodeResult], match: bool) -> dict[str, Any]:
    """Per-opponent (match) or overall (other envs) statistics, JSON-ready."""
    results = sorted(results, key=lambda r: r.index)
    if not match:
        m, lo, hi = mean_ci([r.ret for r in results])
        return {"kind": "return", "episodes": len(results),
                "rows": [{"opponent": None, "episodes": len(results), "return_mean": m, "return_ci95": [lo, hi],
                          "return_std": float(np.std([r.ret for r in results])) if results else float("nan"),
                          "length_mean": float(np.mean([r.length for r in results])) if results else float("nan")}]}
    rows = []
    for opp in dict.fromkeys(r.opponent for r in results):
        rs = [r for r in results if r.opponent == opp]
        n = len(rs)
        w = sum(r.outcome == "win" for r in rs)
        d = sum(r.outcome == "draw" for r in rs)
        l_ = sum(r.outcome == "loss" for r in rs)
        diff = [r.my_score - r.enemy_score for r in rs]
        m, lo, hi = mean_ci(diff)
        by_side = {side: {"episodes": sum(r.side == side for r in rs),
                          "wins": sum(r.side == side and r.outcome == "win" for r in rs)} for side in ("red", "blue")}
        row = {"opponent": opp, "episodes": n, "wins": w, "draws": d, "losses": l_,
               "win_rate": w / n if n else float("nan"), "win_rate_ci95": list(wilson(w, n)),
               "score_diff_mean": m, "score_diff_ci95": [lo, hi],
               "return_mean": float(np.mean([r.ret for r in rs])), "by_side": by_side}
        if n and all(r.robot_points is not None for r in rs):
            # how the matches were won: points read from the other robot's markers, each side
            row["robot_points_mean"] = float(np.mean([r.robot_points[0] for r in rs]))
            row["enemy_robot_points_mean"] = float(np.mean([r.robot_points[1] for r in rs]))
        rows.append(row)
    n_all = len(results)
    w_all = sum(r.outcome == "win" for r in results)
    return {"kind": "match", "episodes": n_all, "rows": rows,
            "total": {"episodes": n_all, "wins": w_all, "draws": sum(r.outcome == "draw" for r in results),
                      "losses": sum(r.outcome == "loss" for r in results),
                      "win_rate": w_all / n_all if n_all else float("nan"), "win_rate_ci95": list(wilson(w_all, n_all))}}


def evaluate(checkpoint: str, env_id: str | None = None, env_kwargs: Mapping[str, Any] | None = None,
             opponents: Sequence[str] | None = MATCH_OPPONENTS, episodes: int = 20, workers: int = 1,
             seed: int = 2_000_000, progress: bool = True, policy: str = "greedy",
             allow_exported: bool = False) -> dict[str, Any]:
    """Play ``episodes`` per opponent (match envs; ``opponents`` ignored otherwise: bot names or
    policy files, see :func:`split_opponents`) with the policy of ``checkpoint`` (a checkpoint or
    ``zenrl export`` file, or a folder's newest checkpoint): ``"greedy"`` (argmax) or ``"sample"`` (draw from an actor-critic's
    action distribution, seeded per episode); ``workers`` > 1 uses that many ``spawn`` processes.
    Returns :func:`summarize`'s dict plus ``checkpoint``, ``env``, ``policy`` and per-episode
    ``results``. Exported files (as the policy or an opponent) load only with ``allow_exported``:
    they are TorchScript programs, which run code when loaded."""
    if policy not in ("greedy", "sample"):
        raise ZenrlError(f"policy must be 'greedy' or 'sample', got {policy!r}")
    sample = policy == "sample"
    checkpoint = str(resolve_checkpoint(checkpoint))  # once: a live run may write a newer one meanwhile
    probe_policy, probe_env, cfg = load_policy_env(checkpoint, env_id, env_kwargs, sample=sample,
                                                     allow_exported=allow_exported)
    match = is_match_env(probe_env)
    env_name = probe_env.spec.id if probe_env.spec else (env_id or cfg.env.id)
    probe_env.close()
    del probe_policy
    opps = list(opponents) if match and opponents else None
    if match and not opps:
        raise ZenrlError("a match env needs at least one opponent (--opponents)")
    if opps:
        split_opponents(opps)  # a mistake is one error here, not one per worker
    jobs = make_jobs(episodes, opps, seed)
    results: list[EpisodeResult] = []
    bar = None
    if progress:
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        bar = Progress(TextColumn("[bold]evaluate"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                       TextColumn("{task.description}"), transient=False)
    task = bar.add_task("", total=len(jobs)) if bar else None

    def done(r: EpisodeResult) -> None:
        results.append(r)
        if bar is not None:
            wins = sum(x.outcome == "win" for x in results)
            bar.update(task, advance=1, description=f"wins {wins}/{len(results)}" if match else f"last return {r.ret:.1f}")

    if bar is not None:
        bar.start()
    try:
        if workers <= 1:
            runner = EpisodeRunner(checkpoint, env_id, env_kwargs, opps, sample, allow_exported)
            try:
                for j in jobs:
                    done(runner.run(j))
            finally:
                runner.close()
        else:
            run_pooled(min(workers, len(jobs)), _init_worker,
                       (str(checkpoint), env_id, dict(env_kwargs or {}), opps, sample, allow_exported), _run_job, jobs,
                       done)
    finally:
        if bar is not None:
            bar.stop()
    out = summarize(results, match)
    out.update({"checkpoint": str(checkpoint), "env": env_name, "seed": seed, "policy": policy,
                "results": [asdict(r) for r in sorted(results, key=lambda r: r.index)]})
    return out


def _fmt_ci(ci: Sequence[float], pct: bool = False) -> str:
    lo, hi = ci
    if any(math.isnan(v) for v in (lo, hi)):
        return ""
    return f"[{lo:.0%}, {hi:.0%}]" if pct else f"[{lo:+.2f}, {hi:+.2f}]"


def render_table(summary: Mapping[str, Any]):
    """A rich Table of :func:`evaluate`'s summary, narrow enough for an 80-column terminal
    (each estimate shares its column with its 95% interval)."""
    from rich import box
    from rich.table import Table

    t = Table(title=f"{summary.get('env', '')}  {Path(str(summary.get('checkpoint', ''))).name}", box=box.SIMPLE_HEAD)
    if summary["kind"] == "return":
        for c in ("episodes", "mean return [95% CI]", "std", "mean length"):
            t.add_column(c, justify="right")
        r = summary["rows"][0]
        t.add_row(str(r["episodes"]), f"{r['return_mean']:.2f} {_fmt_ci(r['return_ci95'])}".strip(),
                  f"{r['return_std']:.2f}", f"{r['length_mean']:.1f}")
        return t
    for c in ("opponent", "n", "W/D/L", "win rate [95% CI]", "score diff [95% CI]"):
        t.add_column(c, justify="left" if c == "opponent" else "right", no_wrap=True)
    for r in summary["rows"]:
        t.add_row(Path(r["opponent"]).name, str(r["episodes"]), f"{r['wins']}/{r['draws']}/{r['losses']}",
                  f"{r['win_rate']:.0%} {_fmt_ci(r['win_rate_ci95'], True)}",
                  f"{r['score_diff_mean']:+.2f} {_fmt_ci(r['score_diff_ci95'])}".strip())
    tot = summary["total"]
    t.add_row("all", str(tot["episodes"]), f"{tot['wins']}/{tot['draws']}/{tot['losses']}",
              f"{tot['win_rate']:.0%} {_fmt_ci(tot['win_rate_ci95'], True)}", "", style="bold")
    if all("robot_points_mean" in r for r in summary["rows"]):
        t.caption = "points a match from the other robot's markers, mine/its: " + ", ".join(
            f"{Path(r['opponent']).name} {r['robot_points_mean']:.1f}/{r['enemy_robot_points_mean']:.1f}"
            for r in summary["rows"])
    return t


# --------------------------------------------------------------------------------------------
# Round robin
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PairJob:
    """One round-robin match: players (bot names or policy files) ``red`` and ``blue``."""

    index: int
    seed: int
    red: str
    blue: str


@dataclass
class PairResult:
    index: int
    seed: int
    red: str
    blue: str
    winner: str  # "red" | "blue" | "draw"
    red_score: int
    blue_score: int
    length: int


class RoundRobinRunner:
    """Loads every policy of ``players`` once into one match env and plays :class:`PairJob`
    matches. The env is the first policy's (with ``env_id`` / ``env_kwargs`` over it) if every
    policy can play in it, else the first policy env, in the players' order, that every policy
    can play in (a policy reads its own observation keys, so an env that gives more serves it:
    ``env_from`` names the file whose env it is). A policy takes the env's agent seat and its
    opponent (a bot, or another policy through the env's ``"policy"`` opponent) the other; each
    sees the match from its own side."""

    def __init__(self, players: Sequence[str], env_id: str | None, env_kwargs: Mapping[str, Any] | None,
                 allow_exported: bool = False) -> None:
        torch.set_num_threads(1)
        bots, files = split_opponents(players)
        if not files:
            raise ZenrlError("a round robin needs at least one policy file: scripted bots only play the opponent's seat")
        first_error: ZenrlError | None = None
        for source in files:
            try:
                self.env, self.policies = self._load(files, source, bots, env_id, env_kwargs, allow_exported)
            except ZenrlError as e:
                first_error = first_error or e
                continue
            self.env_from = source
            break
        else:
            assert first_error is not None
            raise first_error
        self.switch = _Switch()
        self.env.unwrapped.opponent_policy = self.switch

    @staticmethod
    def _load(files: Sequence[str], source: str, bots: Sequence[str], env_id: str | None,
              env_kwargs: Mapping[str, Any] | None, allow_exported: bool) -> tuple[Any, dict[str, Any]]:
        """The env of policy file ``source`` and every policy loaded for it (ZenrlError naming the
        first that cannot play in it)."""
        own, env, _ = load_policy_env(source, env_id, env_kwargs, opponents=bots or ["idle"], allow_exported=allow_exported)
        try:
            if not is_match_env(env):
                raise ZenrlError(f"{source}: a round robin needs a match env, not {env.spec.id if env.spec else env}")
            policies = {f: own if f == source else load_player(f, env.observation_space, env.action_space, allow_exported)
                        for f in files}
        except ZenrlError:
            env.close()
            raise
        return env, policies

    def run(self, job: PairJob) -> PairResult:
        agent_side = "red" if job.red in self.policies else "blue"
        agent, other = (job.red, job.blue) if agent_side == "red" else (job.blue, job.red)
        player = self.policies[agent]
        player.reseed(job.seed)  # a mixed policy's member (and any sampling): the job's own draw
        player.reset()
        if other in self.policies:
            self.switch.current = self.policies[other]
            self.switch.current.reseed(job.seed + 1)
            self.switch.current.reset()
            options = {"opponent": "policy", "side": agent_side}
        else:
            options = {"opponent": other, "side": agent_side}
        obs, info = self.env.reset(seed=job.seed, options=options)
        n, done = 0, False
        while not done:
            obs, _, term, trunc, info = self.env.step(player(obs))
            n += 1
            done = term or trunc
        outcome, mine, theirs = ((info["outcome"], info["my_score"], info["enemy_score"]) if "outcome" in info
                                 else match_outcome(info))
        other_side = "blue" if agent_side == "red" else "red"
        winner = {"win": agent_side, "loss": other_side}.get(outcome, "draw")
        red_score, blue_score = (mine, theirs) if agent_side == "red" else (theirs, mine)
        return PairResult(job.index, job.seed, job.red, job.blue, winner, int(red_score), int(blue_score), n)

    def close(self) -> None:
        self.env.close()


_RR: RoundRobinRunner | None = None


def _init_rr_worker(players: Sequence[str], env_id: str | None, env_kwargs: Mapping[str, Any] | None,
                    allow_exported: bool) -> None:
    global _RR
    quiet_native_imports()
    _RR = RoundRobinRunner(players, env_id, env_kwargs, allow_exported)


def _run_pair(job: PairJob) -> PairResult:
    if _RR is None:
        raise RuntimeError("worker not initialised")
    return _RR.run(job)


def player_names(players: Sequence[str]) -> dict[str, str]:
    """Display names: a file's base name (its path where two base names collide), a bot's name."""
    base = {p: Path(p).name for p in players}
    counts: dict[str, int] = {}
    for b in base.values():
        counts[b] = counts.get(b, 0) + 1
    return {p: (b if counts[b] == 1 else p) for p, b in base.items()}


def round_robin_jobs(players: Sequence[str], matches: int, seed: int) -> tuple[list[PairJob], list[tuple[str, str]]]:
    """``matches`` per pair of players, alternating which of the two plays red, every match on a
    seed of its own (``seed``, ``seed + 1``, ...); pairs of two bots are skipped (a bot only
    plays the env's opponent seat). Returns (jobs, skipped pairs)."""
    bots, _ = split_opponents(players)
    jobs, skipped = [], []
    for i, a in enumerate(players):
        for b in players[i + 1:]:
            if a in bots and b in bots:
                skipped.append((a, b))
                continue
            for k in range(matches):
                red, blue = (a, b) if k % 2 == 0 else (b, a)
                jobs.append(PairJob(len(jobs), seed + len(jobs), red, blue))
    return jobs, skipped


def summarize_round_robin(players: Sequence[str], results: Iterable[PairResult], anchor: str | None = None,
                          virtual_draws: float = 1.0) -> dict[str, Any]:
    """Pairwise table (for each pair a < b in ``players`` order: a's wins, draws, b's wins, a's
    win rate and score with Wilson 95% intervals, a's wins by side) and Elo ratings with 95%
    intervals (:func:`~zenrl.common.ratings.fit_ratings`), JSON-ready."""
    results = sorted(results, key=lambda r: r.index)
    names = player_names(players)
    pairs, records = [], []
    for i, a in enumerate(players):
        for b in players[i + 1:]:
            rs = [r for r in results if {r.red, r.blue} == {a, b}]
            if not rs:
                continue
            aw = sum((r.winner == "red") == (r.red == a) and r.winner != "draw" for r in rs)
            d = sum(r.winner == "draw" for r in rs)
            n = len(rs)
            bw = n - aw - d
            score2 = 2 * aw + d  # the score in half points: Wilson on 2n half-point trials
            pairs.append({"a": names[a], "b": names[b], "matches": n, "a_wins": aw, "draws": d, "b_wins": bw,
                          "a_win_rate": aw / n, "a_win_rate_ci95": list(wilson(aw, n)),
                          "a_score": score2 / (2 * n), "a_score_ci95": list(wilson(score2, 2 * n)),
                          "a_wins_as": {"red": sum(r.red == a and r.winner == "red" for r in rs),
                                        "blue": sum(r.blue == a and r.winner == "blue" for r in rs)}})
            records.append(PairRecord(names[a], names[b], aw, d, bw))
    ratings = fit_ratings([names[p] for p in players], records,
                          anchor=names.get(anchor, anchor) if anchor else None, virtual_draws=virtual_draws)
    return {"kind": "round_robin", "players": [names[p] for p in players], "files": {names[p]: p for p in players},
            "matches": len(results), "pairs": pairs, "anchor": names.get(anchor, anchor) if anchor else None,
            "virtual_draws": virtual_draws,
            "ratings": [{"player": r.player, "elo": r.elo, "elo_ci95": list(r.ci95), "elo_se": r.se,
                         "matches": r.games, "score": r.score}
                        for r in sorted(ratings.values(), key=lambda r: -r.elo if not math.isnan(r.elo) else math.inf)]}


def round_robin(players: Sequence[str], matches: int = 20, env_id: str | None = None,
                env_kwargs: Mapping[str, Any] | None = None, workers: int = 1, seed: int = 4_000_000,
                progress: bool = True, allow_exported: bool = False, anchor: str | None = None) -> dict[str, Any]:
    """Every pair of ``players`` (bot names and checkpoint / exported files, at least one file;
    exported files only with ``allow_exported``) plays ``matches`` greedy matches, half with each
    on red, each on a fresh seed from ``seed``; two bots do not meet. Returns
    :func:`summarize_round_robin`'s dict plus ``env``, ``seed``, ``skipped`` pairs and the
    per-match ``results``. ``anchor``: the player rated 0 (default: the mean rating is 0)."""
    players = list(dict.fromkeys(players))
    if len(players) < 2:
        raise ZenrlError("a round robin needs at least two players")
    if matches < 1:
        raise ZenrlError(f"matches per pair must be at least 1, got {matches}")
    if anchor is not None and anchor not in players and anchor not in player_names(players).values():
        raise ZenrlError(f"--anchor {anchor!r} is not one of the players")
    if anchor is not None and anchor not in players:
        anchor = next(p for p, n in player_names(players).items() if n == anchor)
    probe = RoundRobinRunner(players, env_id, env_kwargs, allow_exported)  # a mistake is one error here
    env_name = probe.env.spec.id if probe.env.spec else str(env_id)
    env_from = probe.env_from
    jobs, skipped = round_robin_jobs(players, matches, seed)
    results: list[PairResult] = []
    bar = task = None
    if progress:
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        bar = Progress(TextColumn("[bold]round robin"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                       transient=False)
        task = bar.add_task("", total=len(jobs))
        bar.start()

    def taken(r: PairResult) -> None:
        results.append(r)
        if bar is not None:
            bar.update(task, advance=1)

    try:
        if workers <= 1:
            try:
                for j in jobs:
                    taken(probe.run(j))
            finally:
                probe.close()
        else:
            probe.close()
            run_pooled(min(workers, len(jobs)), _init_rr_worker, (players, env_id, dict(env_kwargs or {}), allow_exported),
                       _run_pair, jobs, taken)
    finally:
        if bar is not None:
            bar.stop()
    out = summarize_round_robin(players, results, anchor)
    names = player_names(players)
    out.update({"env": env_name, "env_from": names[env_from], "seed": seed, "matches_per_pair": matches,
                "skipped": [[names[a], names[b]] for a, b in skipped],
                "results": [asdict(r) for r in sorted(results, key=lambda r: r.index)]})
    return out


def render_round_robin(summary: Mapping[str, Any]):
    """Two rich Tables of :func:`round_robin`'s summary: the pairwise results (each row player's
    W-D-L and win rate against each column player) and the ratings."""
    from rich import box
    from rich.table import Table

    players = summary["players"]
    cell: dict[tuple[str, str], str] = {}
    for p in summary["pairs"]:
        w, d, l_, n = p["a_wins"], p["draws"], p["b_wins"], p["matches"]
        cell[(p["a"], p["b"])] = f"{w}-{d}-{l_} {w / n:.0%}"
        cell[(p["b"], p["a"])] = f"{l_}-{d}-{w} {l_ / n:.0%}"
    t = Table(title=f"{summary.get('env', '')} round robin: row's wins-draws-losses and win rate vs column "
                    f"({summary.get('matches_per_pair')} matches per pair)", box=box.SIMPLE_HEAD)
    t.add_column("player", no_wrap=True)
    for c in players:
        t.add_column(c, justify="right", no_wrap=True)
    for r in players:
        t.add_row(r, *[("" if r == c else cell.get((r, c), "-")) for c in players])
    rt = Table(title="Elo (Bradley-Terry, " + (f"{summary['anchor']} = 0" if summary.get("anchor") else "mean 0")
               + ")", box=box.SIMPLE_HEAD)
    for c in ("player", "Elo [95% CI]", "matches", "score"):
        rt.add_column(c, justify="left" if c == "player" else "right", no_wrap=True)
    for r in summary["ratings"]:
        if math.isnan(r["elo"]):
            rt.add_row(r["player"], "-", "0", "-")
            continue
        lo, hi = r["elo_ci95"]
        rt.add_row(r["player"], f"{r['elo']:+.0f} [{lo:+.0f}, {hi:+.0f}]", str(r["matches"]), f"{r['score']:.0%}")
    return t, rt
