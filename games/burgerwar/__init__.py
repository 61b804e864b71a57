"""The Burger War match game: two TurtleBot3 burgers reading AR markers (docs/burgerwar.md).

Modules:

* :mod:`~zenrl.games.burgerwar.env`: :class:`BurgerWarEnv`, the Gymnasium env behind the ids
  ``zenrl/BurgerWar-v0`` and ``zenrl/BurgerWarImage-v0`` (registered by :mod:`zenrl.common.envs`);
* :mod:`~zenrl.games.burgerwar.geometry`: arena, analytic lidar, geometric marker reading;
* :mod:`~zenrl.games.burgerwar.judge`: the contest judge's rules (ownership, scores, match end);
* :mod:`~zenrl.games.burgerwar.opponents`: the scripted bots and the frozen-policy opponent;
* :mod:`~zenrl.games.burgerwar.render`: the top-down numpy renderer.

The outcome of a finished match is in the ``info`` of its last step (``terminated``, or
``truncated`` by the env's ``max_steps``): ``info["outcome"]`` "win" | "draw" | "loss" from the
agent's side, with ``info["my_score"]`` and ``info["enemy_score"]`` (ints). Generic code reads
those keys and never imports this package.

Importing this package loads nothing heavy (no pybullet); import the modules you need.
"""
