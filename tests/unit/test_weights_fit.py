"""A policy network whose weights cannot travel in one message is a configuration error, found
before anything is allocated (torch's meta device) by the launcher and by every learner."""

from __future__ import annotations

import pytest

from zenrl.common.checkpoints import check_weights_fit, weights_cap
from zenrl.common.config import load_config
from zenrl.common.errors import ConfigError
from zenrl.common.specs import ArraySpec

SPEC = {"obs": ArraySpec((4,), "float32")}


def _cfg(tmp_path, *sets):
    return load_config(None, [f"runs_dir={tmp_path}", *sets], environ={})


@pytest.mark.parametrize("algo", ["apex", "r2d2", "impala", "a3c"])
def test_a_network_past_the_message_cap_is_named(tmp_path, algo):
    # [1100, 1100]: ~1.2 M parameters, 4.7-9.3 MiB as float32: past a 4 MiB cap, within the default 64 MiB
    cfg = _cfg(tmp_path, f"algo={algo}", "network.hidden=[1100,1100]", "transport.max_message_bytes=4194304")
    with pytest.raises(ConfigError, match=r"network.hidden = \[1100, 1100\]: the \w+ network has [\d,]+ parameters .* "
                                          r"\(transport.max_message_bytes = 4.0 MiB\): lower network.hidden"):
        check_weights_fit(cfg, SPEC, 2)
    check_weights_fit(_cfg(tmp_path, f"algo={algo}", "network.hidden=[1100,1100]"), SPEC, 2)  # 64 MiB: fits


def test_the_check_allocates_nothing(tmp_path):
    """10^10 parameters (40 GB as float32): refused by the check, never by the allocator."""
    cfg = _cfg(tmp_path, "network.hidden=[100000,100000]")
    with pytest.raises(ConfigError, match=r"10,000,\d{3},\d{3} parameters \(38,\d{3}\.\d MiB\)"):
        check_weights_fit(cfg, SPEC, 2)


def test_a_league_caps_by_its_snapshot_limit_too(tmp_path):
    cfg = _cfg(tmp_path, "league.enabled=true", "league.max_weights_bytes=1048576", "network.hidden=[600,600]")
    assert weights_cap(cfg) == 1048576
    with pytest.raises(ConfigError, match=r"transport.max_message_bytes / league.max_weights_bytes = 1.0 MiB"):
        check_weights_fit(cfg, SPEC, 2)


def test_a_learner_refuses_it_before_building_its_network(tmp_path):
    from zenrl.learner.apex import ApexLearner

    cfg = _cfg(tmp_path, "network.hidden=[100000,100000]")  # CartPole's spec, from the config's env
    with pytest.raises(ConfigError, match="more than one weights message may carry"):
        ApexLearner(cfg, node=None, run_id="w")


def test_a_learner_whose_start_failed_closes_without_a_second_error():
    """close() after a start that raised before the prefetcher and the sender existed: the start's
    error is the one the log shows (it was an AttributeError on ``_pf``)."""
    from zenrl.learner.apex import ApexLearner

    ApexLearner.__new__(ApexLearner).close()


def test_a_device_this_machine_lacks_is_a_configuration_error():
    import torch

    from zenrl.common.networks import resolve_device

    assert resolve_device("cpu") == torch.device("cpu") and resolve_device("auto").type in ("cpu", "cuda")
    with pytest.raises(ConfigError, match=r"learner.device = 'banana' is not a torch device"):
        resolve_device("banana")
    with pytest.raises(ConfigError, match=r"learner.device = 'xla': zenrl trains on cpu, cuda or mps"):
        resolve_device("xla")
    n = torch.cuda.device_count() if torch.cuda.is_available() else 0
    with pytest.raises(ConfigError, match=r"learner.device = 'cuda:\d+', but this (torch sees no CUDA device|machine has \d+ CUDA)"):
        resolve_device(f"cuda:{n}")  # one past the last (the first, where there is none)
    if not n:
        with pytest.raises(ConfigError, match=r"use learner.device=auto or cpu"):
            resolve_device("cuda")


def test_a_seed_past_what_every_library_takes_is_refused(tmp_path):
    assert _cfg(tmp_path, f"seed={2**31 - 1}").seed == 2**31 - 1
    with pytest.raises(ConfigError, match=r"seed: Input should be less than or equal to 2147483647"):
        _cfg(tmp_path, f"seed={2**64}")
