"""Tools around a trained policy: ``zenrl evaluate``, ``zenrl play``, ``zenrl plot``,
``zenrl export`` (argument parsing in :mod:`zenrl.cli`).

* :func:`evaluate` plays N matches per opponent (half as red, half as blue) in parallel
  processes (``spawn``; no Zenoh) and reports wins / draws / losses with a Wilson 95% interval
  and the mean score difference with a t interval; for other envs the mean return and its
  interval.
* :func:`play` renders one episode to a GIF (pillow) or MP4 (imageio + imageio-ffmpeg).
* :func:`plot` draws learning curves from ``runs/<id>/metrics.jsonl`` (matplotlib, Agg).
* :func:`export` writes the greedy policy as a TorchScript file that loads without zenrl.

pillow, matplotlib, imageio and pygame (Gymnasium's classic-control renderer) are the optional
extra ``viz``; a command that needs a missing one fails with a
:class:`~zenrl.common.errors.ZenrlError` saying what to install.
"""

from __future__ import annotations

import json
import math
import multiprocessing as mp
import os
import sys
import warnings
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import gymnasium as gym
import numpy as np
import torch

from zenrl.common.config import EnvConfig, RunConfig
from zenrl.common.env_factory import make_env
from zenrl.common.envs.bw_judge import match_outcome
from zenrl.common.errors import ZenrlError
from zenrl.common.networks import num_actions
from zenrl.common.policy_io import GreedyPolicy, build_network, checkpoint_config, read_checkpoint

MATCH_OPPONENTS = ("cheese", "teriyaki", "clubhouse", "waypoint")


def _need(module: str, what: str):
    """Import an optional dependency or fail with the install hint."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError:
        raise ZenrlError(f"{what} needs the '{module.split('.')[0]}' package: pip install 'zenrl[viz]' "
                         f"(or pip install {module.split('.')[0]})") from None


# --------------------------------------------------------------------------------------------
# Loading
# --------------------------------------------------------------------------------------------
def env_config_for(cfg: RunConfig, env_id: str | None = None, env_kwargs: Mapping[str, Any] | None = None) -> EnvConfig:
    """The env a checkpoint was trained on, with ``env_id`` / ``env_kwargs`` overriding it
    (kwargs are merged key by key; a different id starts from the given kwargs only)."""
    if env_id is None or env_id == cfg.env.id:
        kw = dict(cfg.env.kwargs)
        kw.update(env_kwargs or {})
        return EnvConfig(id=cfg.env.id, kwargs=kw, max_episode_steps=cfg.env.max_episode_steps)
    return EnvConfig(id=env_id, kwargs=dict(env_kwargs or {}))


def is_match_env(env: gym.Env) -> bool:
    from zenrl.common.envs.burgerwar import BurgerWarEnv

    return isinstance(env.unwrapped, BurgerWarEnv)


def _match_kwargs(kwargs: Mapping[str, Any], opponents: Sequence[str]) -> dict[str, Any]:
    """Env kwargs for evaluating against scripted ``opponents`` (self-play's "policy" entry and
    callables are dropped: the opponent is chosen per episode)."""
    kw = {k: v for k, v in kwargs.items() if k not in ("opponent_policy",)}
    kw["opponents"] = list(opponents)
    return kw


def load_policy_env(checkpoint: str | os.PathLike[str], env_id: str | None = None,
                    env_kwargs: Mapping[str, Any] | None = None, render_mode: str | None = None,
                    opponents: Sequence[str] | None = None, sample: bool = False) -> tuple[GreedyPolicy, gym.Env, RunConfig]:
    """Checkpoint -> (greedy policy, a fresh env it plays in, the checkpoint's config).
    ``sample``: the policy draws from an actor-critic's action distribution instead."""
    state = read_checkpoint(checkpoint)
    cfg = checkpoint_config(state)
    ecfg = env_config_for(cfg, env_id, env_kwargs)
    if opponents is not None:
        ecfg = EnvConfig(id=ecfg.id, kwargs=_match_kwargs(ecfg.kwargs, opponents), max_episode_steps=ecfg.max_episode_steps)
    env = make_env(ecfg, render_mode=render_mode)
    net = build_network(state, env.observation_space, env.action_space)
    try:
        policy = GreedyPolicy(net, num_actions(env.action_space), name=Path(checkpoint).name, sample=sample)
    except ValueError as e:
        env.close()
        raise ZenrlError(f"{checkpoint}: {e}") from None
    return policy, env, cfg


# --------------------------------------------------------------------------------------------
# Statistics
# --------------------------------------------------------------------------------------------
_T975 = [12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179, 2.160,
         2.145, 2.131, 2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064, 2.060, 2.056,
         2.052, 2.048, 2.045, 2.042]


def t975(df: int) -> float:
    """Two-sided 95% critical value of Student's t with ``df`` degrees of freedom (table up to
    30, then a 1/df correction of 1.96 that is within 0.002 of the exact value)."""
    if df < 1:
        return float("nan")
    if df <= 30:
        return _T975[df - 1]
    return 1.959964 + 2.4 / df


def wilson(k: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    """Wilson score 95% interval of a proportion k/n (``(0, 1)`` for n = 0)."""
    if n == 0:
        return 0.0, 1.0
    p = k / n
    den = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return max(0.0, centre - half), min(1.0, centre + half)


def mean_ci(x: Sequence[float]) -> tuple[float, float, float]:
    """(mean, low, high): t 95% interval of the mean (NaN bounds for fewer than 2 values)."""
    a = np.asarray(x, np.float64)
    if a.size == 0:
        return float("nan"), float("nan"), float("nan")
    m = float(a.mean())
    if a.size < 2:
        return m, float("nan"), float("nan")
    h = t975(a.size - 1) * float(a.std(ddof=1)) / math.sqrt(a.size)
    return m, m - h, m + h


# --------------------------------------------------------------------------------------------
# evaluate
# --------------------------------------------------------------------------------------------
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


class EpisodeRunner:
    """Loads the checkpoint once and plays :class:`Job` episodes (one per call)."""

    def __init__(self, checkpoint: str, env_id: str | None, env_kwargs: Mapping[str, Any] | None,
                 opponents: Sequence[str] | None, sample: bool = False) -> None:
        torch.set_num_threads(1)
        self.policy, self.env, _ = load_policy_env(checkpoint, env_id, env_kwargs, opponents=opponents, sample=sample)

    def run(self, job: Job) -> EpisodeResult:
        self.policy.reseed(job.seed)  # a sampled episode depends on its job only, not on the worker
        options = {}
        if job.opponent is not None:
            options = {"opponent": job.opponent, "side": job.side}
        obs, info = self.env.reset(seed=job.seed, options=options or None)
        ret, n, done = 0.0, 0, False
        while not done:
            obs, r, term, trunc, info = self.env.step(self.policy(obs))
            ret += float(r)
            n += 1
            done = term or trunc
        res = EpisodeResult(job.index, job.seed, job.opponent, job.side, ret, n)
        if job.opponent is not None:
            res.outcome, res.my_score, res.enemy_score = match_outcome(info)
        return res

    def close(self) -> None:
        self.env.close()


_RUNNER: EpisodeRunner | None = None  # one per worker process (set by the pool initializer)


def _init_worker(checkpoint: str, env_id: str | None, env_kwargs: Mapping[str, Any] | None,
                 opponents: Sequence[str] | None, sample: bool = False) -> None:
    global _RUNNER
    _RUNNER = EpisodeRunner(checkpoint, env_id, env_kwargs, opponents, sample)


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
        rows.append({"opponent": opp, "episodes": n, "wins": w, "draws": d, "losses": l_,
                     "win_rate": w / n if n else float("nan"), "win_rate_ci95": list(wilson(w, n)),
                     "score_diff_mean": m, "score_diff_ci95": [lo, hi],
                     "return_mean": float(np.mean([r.ret for r in rs])), "by_side": by_side})
    n_all = len(results)
    w_all = sum(r.outcome == "win" for r in results)
    return {"kind": "match", "episodes": n_all, "rows": rows,
            "total": {"episodes": n_all, "wins": w_all, "draws": sum(r.outcome == "draw" for r in results),
                      "losses": sum(r.outcome == "loss" for r in results),
                      "win_rate": w_all / n_all if n_all else float("nan"), "win_rate_ci95": list(wilson(w_all, n_all))}}


def evaluate(checkpoint: str, env_id: str | None = None, env_kwargs: Mapping[str, Any] | None = None,
             opponents: Sequence[str] | None = MATCH_OPPONENTS, episodes: int = 20, workers: int = 1,
             seed: int = 2_000_000, progress: bool = True, policy: str = "greedy") -> dict[str, Any]:
    """Play ``episodes`` per opponent (match envs; ``opponents`` ignored otherwise) with the
    policy of ``checkpoint``: ``"greedy"`` (argmax) or ``"sample"`` (draw from an actor-critic's
    action distribution, seeded per episode); ``workers`` > 1 uses that many ``spawn`` processes.
    Returns :func:`summarize`'s dict plus ``checkpoint``, ``env``, ``policy`` and per-episode
    ``results``."""
    if policy not in ("greedy", "sample"):
        raise ZenrlError(f"policy must be 'greedy' or 'sample', got {policy!r}")
    sample = policy == "sample"
    probe_policy, probe_env, cfg = load_policy_env(checkpoint, env_id, env_kwargs, sample=sample)
    match = is_match_env(probe_env)
    env_name = probe_env.spec.id if probe_env.spec else (env_id or cfg.env.id)
    probe_env.close()
    del probe_policy
    opps = list(opponents) if match and opponents else None
    if match and not opps:
        raise ZenrlError("a match env needs at least one opponent (--opponents)")
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
            runner = EpisodeRunner(checkpoint, env_id, env_kwargs, opps, sample)
            try:
                for j in jobs:
                    done(runner.run(j))
            finally:
                runner.close()
        else:
            ctx = mp.get_context("spawn")
            with ProcessPoolExecutor(max_workers=min(workers, len(jobs)), mp_context=ctx, initializer=_init_worker,
                                     initargs=(str(checkpoint), env_id, dict(env_kwargs or {}), opps, sample)) as pool:
                for fut in as_completed([pool.submit(_run_job, j) for j in jobs]):
                    done(fut.result())
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
        return "-"
    return f"[{lo:.0%}, {hi:.0%}]" if pct else f"[{lo:+.2f}, {hi:+.2f}]"


def render_table(summary: Mapping[str, Any]):
    """A rich Table of :func:`evaluate`'s summary."""
    from rich.table import Table

    t = Table(title=f"{summary.get('env', '')}  {Path(str(summary.get('checkpoint', ''))).name}")
    if summary["kind"] == "return":
        for c in ("episodes", "mean return", "95% CI", "std", "mean length"):
            t.add_column(c, justify="right")
        r = summary["rows"][0]
        t.add_row(str(r["episodes"]), f"{r['return_mean']:.2f}", _fmt_ci(r["return_ci95"]), f"{r['return_std']:.2f}",
                  f"{r['length_mean']:.1f}")
        return t
    for c in ("opponent", "n", "wins", "draws", "losses", "win rate", "95% CI (Wilson)", "score diff", "95% CI (t)"):
        t.add_column(c, justify="left" if c == "opponent" else "right")
    for r in summary["rows"]:
        t.add_row(r["opponent"], str(r["episodes"]), str(r["wins"]), str(r["draws"]), str(r["losses"]),
                  f"{r['win_rate']:.0%}", _fmt_ci(r["win_rate_ci95"], True), f"{r['score_diff_mean']:+.2f}",
                  _fmt_ci(r["score_diff_ci95"]))
    tot = summary["total"]
    t.add_row("all", str(tot["episodes"]), str(tot["wins"]), str(tot["draws"]), str(tot["losses"]),
              f"{tot['win_rate']:.0%}", _fmt_ci(tot["win_rate_ci95"], True), "", "", style="bold")
    return t


# --------------------------------------------------------------------------------------------
# play
# --------------------------------------------------------------------------------------------
def _overlay(frame: np.ndarray, lines: Sequence[str]) -> np.ndarray:
    """Draw text lines in the top-left corner of an RGB uint8[H, W, 3] frame (pillow)."""
    Image = _need("PIL.Image", "drawing text on frames")
    ImageDraw = _need("PIL.ImageDraw", "drawing text on frames")
    img = Image.fromarray(frame)
    d = ImageDraw.Draw(img)
    y = 4
    for line in lines:
        d.text((6, y), line, fill=(0, 0, 0))
        y += 12
    return np.asarray(img)


def record_episode(policy: GreedyPolicy, env: gym.Env, seed: int, options: Mapping[str, Any] | None = None,
                   max_steps: int | None = None) -> tuple[list[np.ndarray], dict[str, Any]]:
    """Play one greedy episode, rendering after reset and every step: (frames uint8[H, W, 3],
    summary {return, steps, winner, scores, side, opponent})."""
    match = is_match_env(env)
    obs, info = env.reset(seed=seed, options=dict(options) if options else None)
    ret, n, done = 0.0, 0, False

    def frame() -> np.ndarray:
        try:
            f = np.asarray(env.render(), dtype=np.uint8)
        except gym.error.DependencyNotInstalled as e:  # classic-control envs draw with pygame
            raise ZenrlError(f"rendering {env.spec.id if env.spec else 'this env'} needs an extra package: {e}") from None
        return f if match else _overlay(f, [f"step {n}", f"return {ret:.1f}"])

    frames = [frame()]
    while not done and (max_steps is None or n < max_steps):
        obs, r, term, trunc, info = env.step(policy(obs))
        ret += float(r)
        n += 1
        done = term or trunc
        frames.append(frame())
    out: dict[str, Any] = {"return": ret, "steps": n}
    if match:
        out.update({"winner": info.get("winner"), "scores": info["war_state"]["scores"], "side": info["side"],
                    "opponent": info["opponent"]})
    return frames, out


def write_video(frames: Sequence[np.ndarray], out: str | os.PathLike[str], fps: float) -> None:
    """``.gif`` via pillow, ``.mp4`` via imageio with imageio-ffmpeg (a clear error if absent)."""
    path = Path(out)
    if path.suffix.lower() == ".gif":
        Image = _need("PIL.Image", "writing a GIF")
        imgs = [Image.fromarray(f) for f in frames]
        imgs[0].save(path, save_all=True, append_images=imgs[1:], duration=max(20, int(round(1000 / fps))), loop=0)
    elif path.suffix.lower() == ".mp4":
        iio = _need("imageio.v3", "writing an MP4")
        try:
            import imageio_ffmpeg  # noqa: F401
        except ImportError:
            raise ZenrlError("writing an MP4 needs imageio-ffmpeg: pip install imageio-ffmpeg (or write a .gif)") from None
        iio.imwrite(path, np.stack(frames), fps=fps, codec="libx264", macro_block_size=1)
    else:
        raise ZenrlError(f"--out must end in .gif or .mp4, got {str(path)!r}")


def play(checkpoint: str, out: str, env_id: str | None = None, env_kwargs: Mapping[str, Any] | None = None,
         opponent: str | None = None, side: str | None = None, seed: int = 0, fps: float | None = None,
         max_steps: int | None = None) -> dict[str, Any]:
    """Render one greedy episode of ``checkpoint`` to ``out`` (.gif / .mp4). For the match,
    ``opponent`` (default: the env's draw) and ``side`` pick the game; ``fps`` defaults to real
    time (the match's control_hz; the env's render_fps otherwise)."""
    if Path(out).suffix.lower() not in (".gif", ".mp4"):
        raise ZenrlError(f"--out must end in .gif or .mp4, got {out!r}")
    opps = [opponent] if opponent else None
    policy, env, _ = load_policy_env(checkpoint, env_id, env_kwargs, render_mode="rgb_array", opponents=opps)
    try:
        options = {}
        if is_match_env(env):
            if side:
                options["side"] = side
            rate = float(env.unwrapped.control_hz)
        else:
            rate = float(env.metadata.get("render_fps") or 30)
        frames, summary = record_episode(policy, env, seed, options, max_steps)
    finally:
        env.close()
    write_video(frames, out, fps or rate)
    summary.update({"out": str(out), "frames": len(frames), "size": list(frames[0].shape[:2])})
    return summary


# --------------------------------------------------------------------------------------------
# plot
# --------------------------------------------------------------------------------------------
def read_metrics(path: str | os.PathLike[str]) -> list[dict[str, Any]]:
    """``metrics.jsonl`` records (a torn last line, from a run still writing, is skipped)."""
    recs = []
    with open(path) as f:
        for line in f:
            line = line.strip()
            if not line:
                continue
            try:
                recs.append(json.loads(line))
            except json.JSONDecodeError:
                continue
    return recs


def plot(run_dir: str | os.PathLike[str], out: str | os.PathLike[str], width: int = 1200, height: int = 800) -> dict[str, Any]:
    """Learning curves of a run as a ``width`` x ``height`` PNG: eval return mean +- std (and win
    rate if logged), learner loss, Q mean, updates/s, samples/s and env steps/s if present,
    against wall-clock minutes since the run's first record. Returns which panels were drawn."""
    matplotlib = _need("matplotlib", "zenrl plot")
    matplotlib.use("Agg")
    plt = _need("matplotlib.pyplot", "zenrl plot")
    run = Path(run_dir)
    mpath = run / "metrics.jsonl" if run.is_dir() else run
    if not mpath.is_file():
        raise ZenrlError(f"no metrics file at {str(mpath)!r}")
    recs = read_metrics(mpath)
    if not recs:
        raise ZenrlError(f"{str(mpath)!r} holds no metrics yet")
    t0 = min(r.get("time", 0.0) for r in recs)

    def series(source: str | None, key: str) -> tuple[np.ndarray, np.ndarray]:
        pts = [((r["time"] - t0) / 60.0, r[key]) for r in recs
               if (source is None or r.get("source") == source) and isinstance(r.get(key), (int, float))]
        if not pts:
            return np.zeros(0), np.zeros(0)
        a = np.asarray(pts, np.float64)
        return a[:, 0], a[:, 1]

    panels: list[tuple[str, list[tuple[str, str | None, str]]]] = [
        ("eval return", [("return_mean", "eval", "mean")]),
        ("win rate", [("win_rate", None, "win rate")]),
        ("learner loss", [("loss", "learner", "loss")]),
        ("Q mean", [("q_mean", "learner", "q")]),
        ("updates/s", [("updates_per_s", None, "updates/s")]),
        ("throughput (/s)", [("samples_per_s", None, "samples/s"), ("env_steps_per_s", None, "env steps/s")]),
    ]
    drawn = [(title, curves) for title, curves in panels if any(series(s, k)[0].size for k, s, _ in curves)]
    if not drawn:
        raise ZenrlError(f"{str(mpath)!r} has none of the plotted metrics")
    dpi = 100
    ncol = 2 if len(drawn) > 1 else 1
    nrow = math.ceil(len(drawn) / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(width / dpi, height / dpi), dpi=dpi, squeeze=False)
    for ax, (title, curves) in zip(axes.flat, drawn):
        for key, source, label in curves:
            x, y = series(source, key)
            if not x.size:
                continue
            ax.plot(x, y, label=label, lw=1.2)
            if key == "return_mean":
                _, sd = series(source, "return_std")
                if sd.size == y.size:
                    ax.fill_between(x, y - sd, y + sd, alpha=0.25, label="+- std")
        ax.set_title(title)
        ax.set_xlabel("minutes")
        ax.grid(alpha=0.3)
        if title == "learner loss":
            ax.set_yscale("log")
        ax.legend(loc="best", fontsize=8)
    for ax in list(axes.flat)[len(drawn):]:
        ax.axis("off")
    fig.suptitle(run.name if run.is_dir() else run.parent.name)
    fig.tight_layout()
    fig.savefig(out, dpi=dpi)  # no bbox_inches: the PNG is exactly width x height
    plt.close(fig)
    return {"out": str(out), "panels": [t for t, _ in drawn], "records": len(recs)}


# --------------------------------------------------------------------------------------------
# export
# --------------------------------------------------------------------------------------------
class ExportedPolicy(torch.nn.Module):
    """Greedy policy for TorchScript: one observation (no batch dim) -> int64 scalar action.

    Dict observation space: ``forward({"lidar": float[360], "pose": float[4], ...})`` keyed like
    the env's observation space; plain Box space: ``forward(tensor)``. Preprocessing is inside
    (uint8 camera images are scaled by 1/255, other inputs cast to float32).
    """

    def __init__(self, net: torch.nn.Module, keys: Sequence[str], dict_obs: bool) -> None:
        super().__init__()
        self.net = net
        self.keys = list(keys)
        self.dict_obs = dict_obs

    def forward(self, obs: Any) -> torch.Tensor:
        if self.dict_obs:
            flat = {f"obs/{k}": obs[k].unsqueeze(0) for k in self.keys}
        else:
            flat = {"obs": obs.unsqueeze(0)}
        out = self.net(flat)
        if isinstance(out, tuple):
            out = out[0]
        return out.argmax(1)[0]


def _example_obs(space: gym.Space, seed: int = 0) -> Any:
    space.seed(seed)
    return space.sample()


def export(checkpoint: str, out: str | os.PathLike[str], env_id: str | None = None,
           env_kwargs: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Write the greedy policy of ``checkpoint`` as TorchScript (``torch.jit.trace``) to ``out``,
    with a ``zenrl.json`` extra file describing the inputs and the action set. Load it with
    ``torch.jit.load(out)`` (no zenrl needed)."""
    policy, env, cfg = load_policy_env(checkpoint, env_id, env_kwargs)
    try:
        space = env.observation_space
        dict_obs = isinstance(space, gym.spaces.Dict)
        keys = list(space.spaces) if dict_obs else ["obs"]
        module = ExportedPolicy(policy.net, keys, dict_obs).eval()
        ex = _example_obs(space)
        example = {k: torch.as_tensor(np.asarray(ex[k])) for k in keys} if dict_obs else torch.as_tensor(np.asarray(ex))
        with torch.no_grad(), warnings.catch_warnings():
            # torch 2.13 deprecates TorchScript in favour of torch.export, but a TorchScript file
            # is what loads with a bare `torch.jit.load` (and from C++ libtorch) on a robot
            warnings.simplefilter("ignore", DeprecationWarning)
            traced = torch.jit.trace(module, (example,), strict=False, check_trace=False)
        inputs = {}
        for k in keys:
            sub = space.spaces[k] if dict_obs else space
            inputs[k] = {"shape": list(sub.shape), "dtype": str(sub.dtype)}
        meta = {"format": 1, "env": env.spec.id if env.spec else cfg.env.id, "env_kwargs": _jsonable(env_config_for(cfg, env_id, env_kwargs).kwargs),
                "algo": cfg.algo, "inputs": inputs, "n_actions": int(env.action_space.n),
                "call": ("policy({key: tensor}) " if dict_obs else "policy(tensor) ") +
                        "-> int64 scalar tensor (one observation, no batch dim)"}
        if is_match_env(env):
            from zenrl.common.envs.burgerwar import RICH_ACTIONS, USERS_ACTIONS

            table = {"users": USERS_ACTIONS, "rich": RICH_ACTIONS}.get(env.unwrapped.action_set)
            meta["actions_v_w"] = np.asarray(table).tolist() if table is not None else None
    finally:
        env.close()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.jit.save(traced, str(out), _extra_files={"zenrl.json": json.dumps(meta)})
    return {"out": str(out), **meta}


def _jsonable(x: Any) -> Any:
    try:
        json.dumps(x)
        return x
    except TypeError:
        return {k: v for k, v in x.items() if _is_json(v)} if isinstance(x, dict) else str(x)


def _is_json(v: Any) -> bool:
    try:
        json.dumps(v)
        return True
    except TypeError:
        return False


def print_json_line(obj: Any, stream=None) -> None:
    """One compact JSON line (the last stdout line of the tools is machine-readable)."""
    (stream or sys.stdout).write(json.dumps(obj, default=float) + "\n")
