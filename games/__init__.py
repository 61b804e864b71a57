"""Games that ship with zenrl, each a package of its own (``zenrl.games.<name>``).

A game holds its env, rules and scripted opponents. Generic code (``zenrl.actor``,
``zenrl.learner``, ``zenrl.replay``, ``zenrl.common``) never imports a game: it makes envs by
gym id (registered in :mod:`zenrl.common.envs` with entry-point strings) and learns a match's
outcome from the final step's ``info`` (``info["outcome"]``, see :mod:`zenrl.games.burgerwar`).
"""
