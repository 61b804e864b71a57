"""Gymnasium environments shipped with zenrl.

Importing this package registers:

* ``zenrl/BurgerWar-v0``: a simulated Burger War match, vector observations;
* ``zenrl/BurgerWarImage-v0``: the same plus the robot's camera image (``obs["image"]``).

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

__all__ = ["BurgerWarEnv"]


def __getattr__(name):
    if name == "BurgerWarEnv":
        from zenrl.common.envs.burgerwar import BurgerWarEnv

        return BurgerWarEnv
    raise AttributeError(name)
