"""Tools around a trained policy (argument parsing in :mod:`zenrl.cli`):

* ``zenrl evaluate`` (:mod:`~zenrl.tools.evaluation`): N episodes per opponent in parallel
  processes, wins / draws / losses with Wilson intervals, mean score difference or return with a
  t interval (:mod:`~zenrl.tools.stats`); ``--round-robin``: every pair of several policies and
  bots, a pairwise table and Elo ratings (:mod:`zenrl.common.ratings`).
* ``zenrl play`` (:mod:`~zenrl.tools.media`): one episode as a GIF (pillow) or MP4 (imageio).
* ``zenrl plot`` (:mod:`~zenrl.tools.plotting`): learning curves from ``metrics.jsonl``.
* ``zenrl export`` (:mod:`~zenrl.tools.torchscript`): the greedy policy as TorchScript.
* ``zenrl average`` (:mod:`~zenrl.tools.averaging`): one checkpoint whose policy weights are the
  mean of several (stochastic weight averaging).

Each takes a checkpoint file (evaluate and play also a ``zenrl export`` file), a run folder or a checkpoints folder (the newest checkpoint:
:func:`~zenrl.tools.loading.resolve_checkpoint`). pillow, matplotlib, imageio and pygame are the
optional extra ``viz``; a command that needs a missing one fails with a
:class:`~zenrl.common.errors.ZenrlError` saying what to install.
"""

from zenrl.tools.evaluation import (EpisodeResult, EpisodeRunner, Job, PairJob, PairResult, RoundRobinRunner,
                                    evaluate, make_jobs, render_round_robin, render_table, round_robin,
                                    round_robin_jobs, summarize, summarize_round_robin)
from zenrl.tools.loading import (MATCH_OPPONENTS, ExportedPlayer, env_config_for, is_exported, is_match_env,
                                 load_player, load_policy_env, print_json_line, quiet_native_imports,
                                 resolve_checkpoint)
from zenrl.tools.media import play, record_episode, write_video
from zenrl.tools.plotting import plot, read_metrics
from zenrl.tools.stats import mean_ci, t975, wilson
from zenrl.tools.torchscript import ExportedPolicy, export, guard_exported

__all__ = ["PairJob", "PairResult", "RoundRobinRunner", "render_round_robin", "round_robin", "round_robin_jobs",
           "summarize_round_robin", "EpisodeResult", "EpisodeRunner", "ExportedPlayer", "ExportedPolicy", "Job", "MATCH_OPPONENTS",
           "env_config_for", "evaluate", "export", "guard_exported", "is_exported", "is_match_env", "load_player", "load_policy_env", "make_jobs", "mean_ci", "play", "plot", "print_json_line",
           "quiet_native_imports", "read_metrics", "record_episode", "render_table", "resolve_checkpoint", "summarize",
           "t975", "wilson", "write_video"]
