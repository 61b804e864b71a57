"""Gymnasium environments shipped with zenrl.

Importing this package registers:

* ``zenrl/BurgerWar-v0``: a simulated Burger War match, vector observations;
* ``zenrl/BurgerWarImage-v0``: the same plus the robot's camera image (``obs["image"]``);
* ``zenrl/Atari-v0``: an Atari game (``game="Pong"``) with the DQN preprocessing and a 4-frame
  stack (:func:`zenrl.common.envs.atari.make_atari`; needs the ``atari`` extra).

Use ``gymnasium.make(id, **options)``; options are documented in
:class:`zenrl.common.envs.burgerwar.BurgerWarEnv` and docs/burgerwar.md. The env ends the match
itself (``terminated``), so no TimeLimit wrapper is added.
"""

import gymnasium

_ENVS = {
    "zenrl/BurgerWar-v0": {"image": False},
    "zenrl/BurgerWarImage-v0": {"image": True},
}

for _id, _kwargs in _ENVS.items():
    if _id not in gymnasium.registry:
        gymnasium.register(id=_id, entry_point="zenrl.common.envs.burgerwar:BurgerWarEnv",
                           kwargs=_kwargs, max_episode_steps=None, disable_env_checker=False)

if "zenrl/Atari-v0" not in gymnasium.registry:
    gymnasium.register(id="zenrl/Atari-v0", entry_point="zenrl.common.envs.atari:make_atari",
                       max_episode_steps=None, disable_env_checker=True)

__all__ = ["BurgerWarEnv"]


def __getattr__(name):
    if name == "BurgerWarEnv":
        from zenrl.common.envs.burgerwar import BurgerWarEnv

        return BurgerWarEnv
    raise AttributeError(name)
