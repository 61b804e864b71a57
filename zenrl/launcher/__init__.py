"""``zenrl run``: one machine, one command. Checks the env, opens an in-process Zenoh router,
starts the replay service (Ape-X), the learner, N actors and the evaluator as separate OS
processes, shows live progress, and stops everything on Ctrl-C, a step/update/time budget, or
when the eval return reaches the target. A child that dies is restarted (the learner with
``--auto-resume``) unless it stopped on its configuration. Children also stop by themselves if
the launcher disappears (they watch their parent pid), so nothing is orphaned.

* :mod:`~zenrl.launcher.supervisor`: the env check, the router, starting and restarting children,
  stop conditions, ``summary.json``.
* :mod:`~zenrl.launcher.display`: what the run shows while it runs.
* :mod:`~zenrl.launcher.status_client`: ``zenrl status``.
* :mod:`~zenrl.launcher.runfolder`: ``launcher.json`` (the router of a running launcher) and
  ``summary.json`` (every segment of a resumed run).

``runs/<run-id>/`` holds ``config.yaml`` (resolved), ``metrics.jsonl`` and ``tb/`` (metrics),
``checkpoints/``, ``logs/<process>.log``, ``summary.json`` and, while it runs, ``launcher.json``.
"""

from zenrl.launcher.display import RATE_WINDOW_S, Progress
from zenrl.launcher.supervisor import EXIT_CONFIG, Launcher, check_env, free_port, launch, new_run_id
from zenrl.launcher.status_client import status

__all__ = ["EXIT_CONFIG", "Launcher", "Progress", "RATE_WINDOW_S", "check_env", "free_port", "launch",
           "new_run_id", "status"]
