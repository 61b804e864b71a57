"""common/ratings.py against cases computed by hand."""

import math

import pytest

from zenrl.common.ratings import PairRecord, expected_score, fit_ratings, records_from_table


def test_two_players_match_the_closed_form():
    # A wins 30 of 40: log-odds ln 3; Elo gap 400 log10 3 = 190.85; information n p (1-p) = 7.5,
    # so the gap's standard error is 1 / sqrt(7.5) nats = 63.43 Elo
    r = fit_ratings(["A", "B"], [PairRecord("A", "B", 30, 0, 10)], anchor="B", virtual_draws=0)
    assert r["B"].elo == 0 and r["B"].se == 0
    assert r["A"].elo == pytest.approx(400 * math.log10(3), abs=1e-6)
    assert r["A"].se == pytest.approx(400 / math.log(10) / math.sqrt(7.5), abs=1e-6)
    assert r["A"].ci95 == pytest.approx((r["A"].elo - 1.959964 * r["A"].se, r["A"].elo + 1.959964 * r["A"].se))
    assert (r["A"].games, r["A"].score, r["B"].score) == (40, 0.75, 0.25)
    # against the mean instead: half the gap each side, half the standard error
    m = fit_ratings(["A", "B"], [PairRecord("B", "A", 10, 0, 30)], virtual_draws=0)
    assert m["A"].elo == pytest.approx(400 * math.log10(3) / 2, abs=1e-6) and m["B"].elo == pytest.approx(-m["A"].elo)
    assert m["A"].se == pytest.approx(r["A"].se / 2, abs=1e-6)


def test_three_players_with_draws_recover_consistent_strengths():
    # strengths 4 : 2 : 1 and records whose frequencies are exactly the model's: the likelihood's
    # gradient is zero there, so A = 400 log10 4 = 240.82 and B = 400 log10 2 = 120.41 above C
    table = {("A", "B"): (18, 4, 8),    # A scores 20 of 30 = 4 / (4 + 2)
             ("B", "C"): (20, 0, 10),   # 2 / (2 + 1)
             ("C", "A"): (5, 2, 23)}    # A scores 24 of 30 = 4 / (4 + 1)
    r = fit_ratings(["A", "B", "C"], records_from_table(table), anchor="C", virtual_draws=0)
    assert r["A"].elo == pytest.approx(400 * math.log10(4), abs=1e-6)
    assert r["B"].elo == pytest.approx(400 * math.log10(2), abs=1e-6)
    assert expected_score(r["A"].elo, r["B"].elo) == pytest.approx(4 / 6)
    assert r["A"].ci95[0] < r["A"].elo < r["A"].ci95[1]


def test_the_prior_keeps_a_perfect_record_finite():
    # one virtual draw: 10.5 of 11 points, a gap of 400 log10 21 = 528.9 Elo
    r = fit_ratings(["A", "B"], [PairRecord("A", "B", 10, 0, 0)], anchor="B", virtual_draws=1)
    assert r["A"].elo == pytest.approx(400 * math.log10(21), abs=1e-6)
    with pytest.raises(ValueError, match="did not converge: without virtual_draws"):
        fit_ratings(["A", "B"], [PairRecord("A", "B", 10, 0, 0)], virtual_draws=0)


def test_unplayed_and_split_players():
    r = fit_ratings(["A", "B", "new"], [PairRecord("A", "B", 3, 1, 2)])
    assert math.isnan(r["new"].elo) and r["new"].games == 0 and not math.isnan(r["A"].elo)
    with pytest.raises(ValueError, match="never met, so they have no common scale: A, B \\| C, D"):
        fit_ratings(["A", "B", "C", "D"], [PairRecord("A", "B", 1, 0, 1), PairRecord("C", "D", 1, 0, 1)])
    with pytest.raises(ValueError, match="unknown player 'Z'"):
        fit_ratings(["A"], [PairRecord("A", "Z", 1, 0, 0)])
