"""The trained policies shipped in models/ (docs/burgerwar.md): each is a `zenrl export` file
that `zenrl evaluate` plays as it is, and each still wins its matches. A damaged, untrained or
mismatched file fails here (an untrained policy loses to cheese: it never reads a marker)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
MODELS = {
    # file: (env id it was trained on, opponent, matches, wins needed)
    "burgerwar_league.pt": ("zenrl/BurgerWar-v0", "waypoint", 4, 3),
    "burgerwar_camera.pt": ("zenrl/BurgerWarImage-v0", "cheese", 4, 3),
    "burgerwar_pfsp.pt": ("zenrl/BurgerWar-v0", "clubhouse", 4, 3),
}


def test_models_folder_lists_its_files():
    shipped = sorted(p.name for p in (ROOT / "models").glob("*.pt"))
    assert shipped == sorted(MODELS), "models/ and this test disagree on the shipped files"
    readme = (ROOT / "models" / "README.md").read_text()
    for name in MODELS:
        assert name in readme, f"models/README.md does not describe {name}"


@pytest.mark.parametrize("name", sorted(MODELS))
def test_shipped_model_evaluates_and_wins(name, tmp_path):
    env_id, opponent, matches, need = MODELS[name]
    out = tmp_path / "eval.json"
    r = subprocess.run([sys.executable, "-m", "zenrl.cli", "evaluate", "--exported", "--checkpoint", str(ROOT / "models" / name),
                        "--opponents", opponent, "--episodes", str(matches), "--workers", "1", "--seed", "1000000",
                        "--no-progress", "--json", str(out)], capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    summary = json.loads(r.stdout.strip().splitlines()[-1])
    assert summary["env"] == env_id
    row = summary["rows"][0]
    assert row["opponent"] == opponent and row["episodes"] == matches
    assert row["wins"] >= need, f"{name} won {row['wins']}/{matches} against {opponent}: {row}"
    assert {e["side"] for e in json.loads(out.read_text())["results"]} == {"red", "blue"}


def test_shipped_models_of_different_observations_meet_in_a_round_robin(tmp_path):
    """burgerwar_pfsp.pt observes `enemy_seen` (the lidar enemy detector), burgerwar_league.pt
    does not: both play in the env of the first, which gives the key (each reads its own
    observation keys), in whichever order they are listed. An env without the key, forced by
    --env-kwargs, suits neither file's env for both, and the error says why."""
    pfsp, league = str(ROOT / "models" / "burgerwar_pfsp.pt"), str(ROOT / "models" / "burgerwar_league.pt")
    cmd = [sys.executable, "-m", "zenrl.cli", "evaluate", "--exported", "--episodes", "2", "--workers", "1",
           "--seed", "1000000", "--no-progress", "--env-kwargs", '{"match_time": 20}', "--round-robin"]
    for players in (f"{pfsp},{league}", f"{league},{pfsp}"):
        r = subprocess.run([*cmd, players], capture_output=True, text=True, timeout=600, cwd=tmp_path)
        assert r.returncode == 0, r.stderr[-3000:]
        summary = json.loads(r.stdout.strip().splitlines()[-1])
        assert summary["env_from"] == "burgerwar_pfsp.pt", summary
        (pair,) = summary["pairs"]
        assert pair["matches"] == 2 and pair["a_wins"] + pair["draws"] + pair["b_wins"] == 2, summary
    cmd[cmd.index('{"match_time": 20}')] = '{"match_time": 20, "enemy_detector": false}'
    r = subprocess.run([*cmd, f"{league},{pfsp}"], capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert r.returncode != 0 and "enemy_seen" in r.stderr, r.stderr[-3000:]
