"""Gymnasium environments shipped with zenrl.

Importing this package registers:

* ``zenrl/BurgerWar-v0``: a simulated Burger War match, vector observations;
* ``zenrl/BurgerWarImage-v0``: the same plus the robot's camera image (``obs["image"]``);
* ``zenrl/StatelessCartPole-v1``: CartPole-v1 with the velocities hidden (observation: cart
  position and pole angle), a partially observable task for recurrent agents
  (:mod:`zenrl.common.envs.stateless_cartpole`);
* ``zenrl/Atari-v0``: an Atari game (``game="Pong"``) with the DQN preprocessing and a 4-frame
  stack (:func:`zenrl.common.envs.atari.make_atari`; needs the ``atari`` extra).

Use ``gymnasium.make(id, **options)``. The Burger War game lives in its own package,
:mod:`zenrl.games.burgerwar` (options: :class:`zenrl.games.burgerwar.env.BurgerWarEnv` and
docs/burgerwar.md); it is registered here by entry-point string only, so importing
``zenrl.common`` never loads the game (gymnasium imports it on the first ``make``). The env ends
the match itself (``terminated``), so no TimeLimit wrapper is added; the last step's ``info``
carries the match's ``outcome`` ("win" | "draw" | "loss"), ``my_score`` and ``enemy_score``.
"""

import gymnasium

_ENVS = {
    "zenrl/BurgerWar-v0": {"image": False},
    "zenrl/BurgerWarImage-v0": {"image": True},
}

for _id, _kwargs in _ENVS.items():
    if _id not in gymnasium.registry:
        gymnasium.register(id=_id, entry_point="zenrl.games.burgerwar.env:BurgerWarEnv",
                           kwargs=_kwargs, max_episode_steps=None, disable_env_checker=False)

if "zenrl/Atari-v0" not in gymnasium.registry:
    gymnasium.register(id="zenrl/Atari-v0", entry_point="zenrl.common.envs.atari:make_atari",
                       max_episode_steps=None, disable_env_checker=True)

if "zenrl/StatelessCartPole-v1" not in gymnasium.registry:
    gymnasium.register(id="zenrl/StatelessCartPole-v1",
                       entry_point="zenrl.common.envs.stateless_cartpole:StatelessCartPoleEnv",
                       max_episode_steps=500, reward_threshold=475.0)
