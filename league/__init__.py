"""The match league (``zenrl league``): players, the payoff table, prioritized fictitious
self-play (PFSP) and the league service over Zenoh. Imports only ``zenrl.common``.

* :mod:`~zenrl.league.core`: pure logic (players, payoff with counts, PFSP, the roles' mixes,
  snapshot and reset rules, persistence); no network.
* :mod:`~zenrl.league.service`: the league process (queryables for the next opponent, a frozen
  player's weights and the table; match results in; learners' weights followed for snapshots).
"""
