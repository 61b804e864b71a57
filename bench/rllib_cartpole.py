"""RLlib's own CartPole-v1 settings, trained until a training mean, for ``bench/vs_rllib.py``.

Run by the Python of a virtual environment with ``ray[rllib]`` (not zenrl's: RLlib pins its own
gymnasium and numpy). Prints one JSON object per training iteration on stdout::

    {"iter": 3, "t": 12.41, "env_steps": 3000, "return_mean": 23.4}

``t``: seconds since the first ``train()`` call began (Ray's start-up and the algorithm's build,
its env runners included, come before it), ``env_steps``: env steps sampled so far,
``return_mean``: RLlib's training mean (``env_runners/episode_return_mean``, its last 100
episodes). It stops at the first iteration whose mean reaches ``--target`` or after ``--cap-s``.

The settings are those of RLlib's tuned examples (``rllib/tuned_examples/dqn/cartpole_dqn.py``,
``.../appo/cartpole_appo.py``, ``.../impala/cartpole_impala.py``), on one env runner: on two cores, two env
runners and the learner ask Ray for more CPUs than there are (APPO made no training iteration in 70 s).

    /work/rlvenv/bin/python bench/rllib_cartpole.py --algo dqn --seed 0 --cap-s 300
"""

from __future__ import annotations

import argparse
import json
import time


def build(algo: str, seed: int, report_s: float):
    from ray.rllib.core.rl_module.default_model_config import DefaultModelConfig

    if algo == "dqn":
        from ray.rllib.algorithms.dqn import DQNConfig

        cfg = (DQNConfig().environment("CartPole-v1")
               .training(lr=0.0005, train_batch_size_per_learner=32,
                         replay_buffer_config={"type": "PrioritizedEpisodeReplayBuffer", "capacity": 50000,
                                               "alpha": 0.6, "beta": 0.4},
                         n_step=(2, 5), double_q=True, dueling=True, epsilon=[(0, 1.0), (10000, 0.02)])
               .rl_module(model_config=DefaultModelConfig(
                   fcnet_hiddens=[256], fcnet_activation="tanh", fcnet_bias_initializer="zeros_",
                   head_fcnet_bias_initializer="zeros_", head_fcnet_hiddens=[256])))
    elif algo == "appo":
        from ray.rllib.algorithms.appo import APPOConfig

        cfg = (APPOConfig().environment("CartPole-v1")
               .training(vf_loss_coeff=0.05, entropy_coeff=0.0)
               .rl_module(model_config=DefaultModelConfig(vf_share_layers=True)))
    elif algo == "impala":
        from ray.rllib.algorithms.impala import IMPALAConfig

        cfg = (IMPALAConfig().environment("CartPole-v1")
               .training(train_batch_size_per_learner=500, grad_clip=40.0, grad_clip_by="global_norm", lr=0.0005,
                         vf_loss_coeff=0.05, entropy_coeff=0.0)
               .rl_module(model_config=DefaultModelConfig(vf_share_layers=True)))
    else:
        raise SystemExit(f"--algo must be dqn, appo or impala, got {algo!r}")
    # one env runner (see the docstring); iterations of at least report_s (APPO's default is 10 s,
    # too coarse a clock for a solve time)
    cfg = cfg.env_runners(num_env_runners=1).reporting(min_time_s_per_iteration=report_s).debugging(seed=seed)
    return cfg.build_algo()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--algo", required=True, choices=["dqn", "appo", "impala"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cap-s", type=float, default=300.0)
    ap.add_argument("--target", type=float, default=450.0)
    ap.add_argument("--report-s", type=float, default=1.0, help="least seconds per training iteration")
    args = ap.parse_args()
    import ray

    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        algo = build(args.algo, args.seed, args.report_s)
        t0 = time.monotonic()
        for i in range(1_000_000):
            r = algo.train()
            er = r.get("env_runners", {})
            ret = er.get("episode_return_mean")
            print(json.dumps({"iter": i, "t": round(time.monotonic() - t0, 3),
                              "env_steps": er.get("num_env_steps_sampled_lifetime"),
                              "return_mean": None if ret is None else float(ret)}), flush=True)
            if (ret is not None and ret >= args.target) or time.monotonic() - t0 > args.cap_s:
                break
        algo.stop()
    finally:
        ray.shutdown()


if __name__ == "__main__":
    main()
