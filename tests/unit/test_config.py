"""Config layers and validation."""

import pytest

from zenrl.common.config import describe_options, load_config
from zenrl.common.errors import ConfigError


def test_layers(tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text("learner:\n  lr: 0.001\n  batch_size: 64\nactor:\n  num_actors: 3\n")
    env = {"ZENRL__LEARNER__BATCH_SIZE": "32", "ZENRL_ROUTER": "tcp/10.0.0.1:7447"}
    cfg = load_config(f, ["actor.num_actors=5"], environ=env)
    assert cfg.learner.lr == 0.001          # file
    assert cfg.learner.batch_size == 32     # env beats file
    assert cfg.actor.num_actors == 5        # --set beats file
    assert cfg.transport.router == "tcp/10.0.0.1:7447"
    assert cfg.replay.alpha == 0.6          # default


def test_errors_name_option_and_value(tmp_path):
    with pytest.raises(ConfigError, match=r"replay\.alpha.*got 3"):
        load_config(None, ["replay.alpha=3"], environ={})
    with pytest.raises(ConfigError, match=r"learner\.bogus"):
        load_config(None, ["learner.bogus=1"], environ={})
    with pytest.raises(ConfigError, match="does not exist"):
        load_config(tmp_path / "missing.yaml", environ={})
    bad = tmp_path / "bad.yaml"
    bad.write_text("- a list\n")
    with pytest.raises(ConfigError, match="mapping"):
        load_config(bad, environ={})
    with pytest.raises(ConfigError, match="network.hidden"):
        load_config(None, ["network.hidden=[]"], environ={})
    with pytest.raises(ConfigError, match="is a directory$"):
        load_config(tmp_path, environ={})
    broken = tmp_path / "broken.yaml"
    broken.write_text("learner:\n  lr: 1e-3\n    batch_size: 2\n")
    with pytest.raises(ConfigError, match=r"is not valid YAML: mapping values are not allowed here \(line 3, column 15\)$") as e:
        load_config(broken, environ={})
    assert "\n" not in str(e.value)  # one line, not PyYAML's three
    binary = tmp_path / "model.pt"
    binary.write_bytes(b"PK\x03\x04\xd0\xff\xfe")
    with pytest.raises(ConfigError, match="cannot be read: 'utf-8' codec can't decode"):
        load_config(binary, environ={})
    with pytest.raises(ConfigError, match="must look like"):
        load_config(None, ["nonsense"], environ={})
    with pytest.raises(ConfigError, match=r"evaluator\.policy 'sample' needs algo a3c"):
        load_config(None, ["evaluator.policy=sample"], environ={})
    assert load_config(None, ["algo=a3c", "evaluator.policy=sample"], environ={}).evaluator.policy == "sample"
    with pytest.raises(ConfigError, match=r"learner\.batch_size \* learner\.batches_per_request = 4096 \* 32"):
        load_config(None, ["learner.batch_size=4096", "learner.batches_per_request=32"], environ={})
    assert load_config(None, ["learner.batch_size=4096", "learner.batches_per_request=16"], environ={}).learner.batches_per_request == 16


def test_unknown_option_suggests_the_close_one():
    with pytest.raises(ConfigError, match=r"learner\.batch_sise: Extra inputs are not permitted; did you mean 'batch_size'\?"):
        load_config(None, ["learner.batch_sise=3"], environ={})
    with pytest.raises(ConfigError, match=r"lerner: .*did you mean 'learner'\?"):
        load_config(None, ["lerner.lr=3"], environ={})
    with pytest.raises(ConfigError) as e:
        load_config(None, ["learner.zzzzzz=3"], environ={})
    assert "did you mean" not in str(e.value)  # nothing close: no guess


def test_frozen():
    cfg = load_config(None, environ={})
    with pytest.raises(Exception):
        cfg.seed = 3  # type: ignore[misc]


def test_every_option_is_documented():
    rows = describe_options()
    assert len(rows) > 40
    missing = [name for name, _, desc in rows if not desc]
    assert not missing, missing


def test_saved_config_with_removed_option_stays_readable(caplog):
    from zenrl.common.config import config_from_dict

    saved = load_config(None, ["learner.lr=0.01"], environ={}).model_dump(mode="json")
    saved["learner"]["an_option_from_an_older_version"] = 3
    cfg = config_from_dict(saved)
    assert cfg.learner.lr == 0.01
    assert "an_option_from_an_older_version" in caplog.text
    saved["learner"]["lr"] = -1
    with pytest.raises(ConfigError, match="learner.lr"):
        config_from_dict(saved)


def test_cpu_placement_off_survives_yaml(tmp_path):
    # YAML 1.1 reads a bare `off` as false; the option still means "off"
    f = tmp_path / "c.yaml"
    f.write_text("cpu_placement: off\n")
    assert load_config(f).cpu_placement == "off"
    assert load_config(None, ["cpu_placement=off"]).cpu_placement == "off"
    assert load_config(None, ["cpu_placement=auto"]).cpu_placement == "auto"
    with pytest.raises(ConfigError, match="cpu_placement"):
        load_config(None, ["cpu_placement=sometimes"])


@pytest.mark.parametrize("path", sorted(str(p) for p in (__import__("pathlib").Path(__file__).resolve().parents[2]
                                                          / "configs").glob("*.yaml")))
def test_every_shipped_config_loads_and_builds_its_env(path):
    """A shipped config with a typo or a stale option fails here, not in a user's run."""
    from zenrl.common.env_factory import make_env

    cfg = load_config(path, environ={})
    if cfg.env.id.startswith("zenrl/Atari"):
        pytest.importorskip("ale_py", reason="Atari envs need the atari extra")
    env = make_env(cfg.env)
    try:
        obs, _ = env.reset(seed=0)
        assert env.observation_space.contains(obs)
    finally:
        env.close()


def _help(capsys, *argv) -> str:
    from zenrl.cli import main

    with pytest.raises(SystemExit) as e:
        main(list(argv))
    assert e.value.code == 0
    return capsys.readouterr().out


def _listed(text: str) -> set[str]:
    names = {r[0] for r in describe_options()}
    return {line.split()[0] for line in text.splitlines() if line.startswith("  ") and line.split()[0] in names}


def test_each_roles_help_lists_the_options_it_reads_and_run_lists_all(capsys):
    from zenrl.cli import ROLE_OPTIONS

    every = {r[0] for r in describe_options()}
    sections = {n.split(".", 1)[0] for n in every}
    for role, wanted in ROLE_OPTIONS.items():
        assert all(w in every or w in sections for w in wanted), (role, wanted)  # no stale name
        listed = _listed(_help(capsys, role, "--help"))
        assert listed == {n for n in every if n in wanted or n.split(".", 1)[0] in wanted}, role
    learner = _listed(_help(capsys, "learner", "--help"))
    assert {"learner.lr", "transport.router", "network.hidden", "env.id", "a3c.max_staleness"} <= learner
    # of the replay's options the learner reads only how many shards to sample across
    assert not any(n.startswith(("replay.", "evaluator.", "selfplay.")) for n in learner - {"replay.shards"})
    assert "replay.shards" in learner
    actor = _listed(_help(capsys, "actor", "--help"))
    assert "actor.envs_per_actor" in actor and "learner.gamma" in actor and "learner.lr" not in actor
    assert _listed(_help(capsys, "run", "--help")) == every
    from zenrl.cli import main

    assert main(["config", "--list"]) == 0
    assert _listed(capsys.readouterr().out) == every
