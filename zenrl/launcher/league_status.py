"""``zenrl league status``: a running league's players (kind, version, generation), their
Bradley-Terry ratings on the Elo scale with 95% intervals (:mod:`zenrl.common.ratings`, from
the payoff table; a learning agent's rating pools every version it played with), games
played, each player's result against the main agent, and the main agent's current opponent
distribution (PFSP plus self-play), from the league's ``league/table`` queryable."""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

import yaml

from zenrl import strict_json
from zenrl.common import protocol as P
from zenrl.common.errors import RemoteTimeout, TransportError
from zenrl.common.ratings import PairRecord, fit_ratings


def rows_of(table: P.LeagueTable) -> list[dict[str, Any]]:
    """One row per player, in join order: ``id, kind, role, version, generation, games``
    (every match it played), ``vs_main`` [wins, draws, losses] of the main agent against it
    (None for the main agent itself) and ``pfsp`` (its probability as the main agent's next
    opponent)."""
    ids = sorted(table.ids, key=lambda i: table.ids[i])
    c = table.counts
    main = next((i for i in ids if table.kinds[i] == "learner" and table.roles[i] == "main"), None)
    out = []
    for i in ids:
        n = table.ids[i]
        # a self-play match is one count on the diagonal; any other match is in row i
        games = int(c[n].sum())
        row: dict[str, Any] = {"id": i, "kind": table.kinds[i], "role": table.roles[i], "version": table.versions[i],
                               "generation": table.generations[i], "games": games,
                               "pfsp": float(table.main_pfsp.get(i, 0.0))}
        if main is not None and i != main:
            row["vs_main"] = [int(x) for x in c[table.ids[main], n]]
        out.append(row)
    return out


def ratings_of(table: P.LeagueTable) -> tuple[dict[str, Any], str | None]:
    """Ratings (Elo scale, the players' mean at 0) of every player from the table's matches
    (each pair once; self-play left out), and None, or ({}, why) when they cannot be fitted
    (players in groups that never met)."""
    ids = sorted(table.ids, key=lambda i: table.ids[i])
    recs = []
    for a in ids:
        for b in ids:
            i, j = table.ids[a], table.ids[b]
            if i < j and table.counts[i, j].sum() > 0:
                w, d, l_ = (int(x) for x in table.counts[i, j])
                recs.append(PairRecord(a, b, w, d, l_))
    try:
        return fit_ratings(ids, recs), None
    except ValueError as e:
        return {}, str(e)


def fetch_table(node: Any, run_id: str, timeout_s: float) -> P.LeagueTable:
    return P.LeagueTable.decode(node.query(P.LeagueKeys(run_id).table, None, timeout_s))


def saved_table(run_dir: Path) -> P.LeagueTable | None:
    """The table of the league state saved in ``run_dir`` (a run that has stopped), or None."""
    from zenrl.common.config import config_from_dict
    from zenrl.league.service import table_message
    from zenrl.league.store import LeagueStore

    try:
        cfg = config_from_dict(yaml.safe_load((run_dir / "config.yaml").read_text()))
    except (OSError, yaml.YAMLError):
        return None
    lg = LeagueStore(run_dir / "league", cfg.league.max_weights_bytes).load(cfg.league, time.time(),
                                                                            list(cfg.opponents.pool))
    return None if lg is None else table_message(lg, {"saved": True})


def league_status(endpoint: str, run_id: str, connect_timeout_s: float = 5.0, client_config: str | None = None,
                  as_json: bool = False, timeout_s: float = 5.0, run_dir: Path | None = None) -> int:
    """Print the league of ``run_id`` (table or ``--json``): asked of the running league at
    ``endpoint``, or, with ``run_dir`` and no endpoint, read from the state it saved; 1 when
    there is none."""
    from zenrl.common.transport import Node

    where = endpoint
    if not endpoint and run_dir is not None:
        table = saved_table(run_dir)
        where = f"saved in {run_dir / 'league'}"
        if table is None:
            sys.stderr.write(f"zenrl league status: {run_dir} holds no league state\n")
            return 1
    else:
        try:
            with Node(endpoint, connect_timeout_s, config_file=client_config) as node:
                table = fetch_table(node, run_id, timeout_s)
        except (RemoteTimeout, TransportError) as e:
            sys.stderr.write(f"zenrl league status: no league of run {run_id!r} answered at {endpoint}: {e}\n")
            return 1
    rows = rows_of(table)
    ratings, why = ratings_of(table)
    for r in rows:
        rt = ratings.get(r["id"])
        if rt is not None and rt.games:
            r.update(elo=rt.elo, elo_ci95=list(rt.ci95))
    out = {"run_id": run_id, "router": where, "players": rows, "values": table.values,
           **({"ratings_error": why} if why else {})}
    if as_json:
        sys.stdout.write(strict_json.dumps(out, default=float) + "\n")
        return 0
    from rich.console import Console
    from rich.table import Table

    t = Table(title=f"league {run_id} ({where}): {table.values.get('results_total', 0)} results")
    for col in ("player", "kind", "version", "Elo [95%]", "games", "main W/D/L vs it", "main's PFSP"):
        t.add_column(col, justify="left" if col in ("player", "kind") else "right")
    for r in rows:
        kind = r["kind"] if r["kind"] != "learner" else f"learner ({r['role']}, gen {r['generation']})"
        wdl = "/".join(map(str, r["vs_main"])) if "vs_main" in r else "-"
        elo = f"{r['elo']:+.0f} [{r['elo_ci95'][0]:+.0f}, {r['elo_ci95'][1]:+.0f}]" if "elo" in r else "-"
        t.add_row(r["id"], kind, "-" if r["version"] < 0 else str(r["version"]), elo, str(r["games"]), wdl,
                  f"{r['pfsp']:.1%}")
    Console().print(t)
    if why:
        sys.stderr.write(f"zenrl league status: no ratings: {why}\n")
    if table.values.get("saved"):
        sys.stderr.write("zenrl league status: the league is not running; its saved state shows no self-play share "
                         "(the learning agents serve no weights)\n")
    return 0
