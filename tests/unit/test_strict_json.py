"""zenrl.strict_json: what the commands print for other programs is JSON that strict readers take."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from zenrl.strict_json import dumps, finite


def _strict_load(text: str):
    def refuse(name: str):
        raise ValueError(f"non-standard JSON constant {name}")
    return json.loads(text, parse_constant=refuse)


def test_non_finite_floats_become_null_everywhere():
    obj = {"ci": (math.nan, 1.5), "nested": [{"x": math.inf, "y": -math.inf}], "np": np.float32("nan"),
           "arr": np.array([1.0, np.nan]), "i": np.int64(3), "b": np.bool_(True), "s": "NaN", "n": None}
    out = _strict_load(dumps(obj))
    assert out == {"ci": [None, 1.5], "nested": [{"x": None, "y": None}], "np": None, "arr": [1.0, None],
                   "i": 3, "b": True, "s": "NaN", "n": None}
    assert obj["ci"][0] != obj["ci"][0]  # the input is left as it was


def test_plain_json_would_have_been_refused():
    with pytest.raises(ValueError, match="NaN"):
        _strict_load(json.dumps({"ci": [math.nan]}))
    assert finite(2.5) == 2.5 and finite([1, "a"]) == [1, "a"]
