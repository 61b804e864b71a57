"""Configuration: one frozen pydantic model per component, each field documented.

Layers, later ones win: the defaults below, then a YAML file (``--config``), then environment
variables ``ZENRL__<SECTION>__<FIELD>`` (what docker compose sets; ``ZENRL_ROUTER`` is a
shortcut for ``transport.router``), then command-line ``--set section.field=value``.
Every value is validated on construction; an error names the option and the bad value.
``zenrl config --list`` (and ``zenrl run --help``) prints every option with its description.
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path
from typing import Any, Literal, Mapping, Optional

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from zenrl.common.errors import ConfigError
from zenrl.common.protocol import MAX_REPLAY_SHARDS, MAX_SAMPLE_BATCH

ENV_PREFIX = "ZENRL__"


class _Section(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid", validate_default=True)


class TransportConfig(_Section):
    router: str = Field("tcp/127.0.0.1:7447", description="Zenoh router endpoint every process connects to (env ZENRL_ROUTER).")
    listen: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"], description="Endpoints the embedded router of `zenrl run` listens on.")
    router_config: Optional[str] = Field(None, description="JSON5 config file for the embedded router (overrides `listen`).")
    client_config: Optional[str] = Field(None, description="JSON5 file with extra Zenoh client settings (TLS root CA, user/password) merged under the ones zenrl sets.")
    shared_memory: bool = Field(False, description="Let same-host processes exchange payloads through shared memory (off: it dropped messages under CPU starvation here, and containers do not share /dev/shm).")
    close_linger_s: float = Field(0.3, ge=0, le=5, description="Pause before closing a session that published, so queued messages leave first.")
    connect_timeout_s: float = Field(30.0, ge=0, description="How long a client waits for the router at start-up.")
    query_timeout_s: float = Field(5.0, gt=0, description="Timeout of every remote query (sample requests, weight fetches, slots).")
    max_message_bytes: int = Field(64 * 1024 * 1024, ge=1024, le=1 << 30, description="Cap on one wire message; larger ones are refused on both ends.")


class EnvConfig(_Section):
    id: str = Field("CartPole-v1", description="Gymnasium environment id (zenrl/BurgerWar-v0 and zenrl/BurgerWarImage-v0 ship with zenrl).")
    kwargs: dict[str, Any] = Field(default_factory=dict, description="Keyword arguments for gymnasium.make.")
    max_episode_steps: Optional[int] = Field(None, ge=1, description="Override the env's time limit (truncation).")


class NetworkConfig(_Section):
    hidden: list[int] = Field(default_factory=lambda: [256, 256], description="Hidden layer sizes of the MLP torso (and of the head after a conv/dict encoder).")
    dueling: bool = Field(True, description="Dueling Q head (value + advantage streams).")
    conv: bool = Field(True, description="Use the Nature-DQN conv torso for uint8 image observations.")
    activation: Literal["relu", "tanh"] = Field("relu", description="Activation of the hidden MLP layers.")
    shared_torso: bool = Field(True, description="A3C: policy and value share the MLP torso; false gives each its own MLP on the shared encoder (Stable-Baselines3's default actor-critic).")
    log_std_init: float = Field(0.0, ge=-5.0, le=2.0, description="IMPALA and A3C with continuous (Box) actions: the Gaussian policy's initial log standard deviation, in actions normalised to [-1, 1] (0: a standard deviation of half the action range).")
    orthogonal_init: bool = Field(True, description="A3C: orthogonal initialisation of the actor-critic's linear layers (gain sqrt(2) hidden, 0.01 policy head, 1 value head; zero biases), the A2C/A3C convention that starts from a near-uniform policy; false keeps PyTorch's default init.")

    @model_validator(mode="after")
    def _check(self) -> "NetworkConfig":
        if not self.hidden or any(h <= 0 for h in self.hidden):
            raise ValueError(f"network.hidden must be a non-empty list of positive sizes, got {self.hidden}")
        return self


class ReplayConfig(_Section):
    capacity: int = Field(100_000, ge=1, description="Replay capacity in transitions (FIFO eviction). The replay stops at its first chunk (exit 2) if the ring could not fit in the machine's memory or the container's limit once full, and warns above 80% of it.")
    max_bytes: Optional[int] = Field(None, ge=1, description="Cap on replay storage in bytes; the ring is sized to min(capacity, max_bytes / item size).")
    alpha: float = Field(0.6, ge=0, le=1, description="Prioritization exponent (0 = uniform).")
    uniform: bool = Field(False, description="Sample uniformly instead of by priority.")
    frames_per_item: float = Field(1.05, gt=0, le=64, description="Frame mode (image envs): frame ring slots per transition slot; an actor sends about 1 + 1/episode length frames per transition (R2D2: per sequence, about sequence_length/2 + 1). Too few: the frame ring, not capacity, bounds the transitions stored.")
    min_size: int = Field(1_000, ge=1, description="No samples are served before the replay holds this many transitions.")
    samples_per_insert: Optional[float] = Field(None, gt=0, description="If set, cap sampled/inserted transitions at this ratio (Reverb-style rate limit).")
    spi_tolerance: float = Field(10_000.0, gt=0, description="How many sampled transitions the samples-per-insert limit may run ahead.")
    stats_interval_s: float = Field(2.0, gt=0, description="How often the replay publishes its stats.")
    ingest_batch_chunks: int = Field(32, ge=1, description="Queued chunks the ingest thread validates and inserts as one batch.")
    ingest_linger_s: float = Field(0.005, ge=0, le=0.1, description="When fewer chunks wait than a batch takes, the ingest thread waits this long once for more before it starts the batch (0: never): part of each batch's cost is paid per batch, so on a busy machine fewer, larger batches leave more CPU to everything else. A chunk waits at most this much longer to be sampled.")
    queue_size: int = Field(256, ge=1, description="Most chunks the replay's inbox (the Zenoh FIFO its ingest thread pulls from) holds.")
    queue_max_bytes: int = Field(256 * 1024 * 1024, ge=1024, description="Bound in bytes of the chunks waiting for the ingest thread: its inbox holds min(queue_size, max(1, queue_max_bytes // max_chunk_bytes)) chunks (64 at the defaults; a deeper inbox wakes Zenoh's receive thread once per batch, not per chunk, and rides out longer stalls of the ingest thread without holding back the senders), and a batch takes at most this many bytes (the first chunk always). With max_decoded_bytes and max_chunk_bytes it bounds what a barrage of the largest messages adds to the replay's memory (docs/architecture.md).")
    max_chunk_bytes: int = Field(4 * 1024 * 1024, ge=1024, description="Largest encoded chunk the replay takes (a larger one is refused unread, reason size; its session's Zenoh receive cap is twice this, so a larger message is dropped as its fragments arrive; an actor splits a larger chunk in halves, and one it cannot split, a frame-mode chunk, is counted and logged): 8x the largest shipped config's chunk (an 84x84x4 Atari chunk of 64 transitions is ~0.5 MB); raise it for larger frames. It also sets the depth of the replay's inbox (queue_max_bytes over this), and is independent of transport.max_message_bytes, which also bounds the sample replies the replay sends. With queue_max_bytes and max_decoded_bytes it bounds what a barrage adds to the replay's memory (docs/architecture.md).")
    max_decoded_bytes: int = Field(16 * 1024 * 1024, ge=1024, description="Most bytes the compressed arrays of one chunk may declare (checked before decompressing; the spec's shape for each field is checked too), and the decoded bytes the ingest thread holds at once before it inserts.")
    durable: bool = Field(False, description="Keep an append-only log of inserted chunks and priority snapshots so the contents survive a crash.")
    log_dir: Optional[str] = Field(None, description="Directory of the durable log (default: <runs_dir>/<run_id>/replay); with shards > 1 each shard keeps its log in a folder shard-<k> under it.")
    flush_interval_s: float = Field(1.0, gt=0, description="fsync the durable log at most this often (the loss window after a crash).")
    snapshot_interval_s: float = Field(10.0, gt=0, description="Write a priority snapshot this often.")
    segment_items: Optional[int] = Field(None, ge=1, description="Items per log segment (default capacity / 8); whole segments are deleted once overwritten.")
    durable_retry_s: float = Field(5.0, gt=0, description="While the durable log cannot be written (disk full, EIO), retry it this often; the replay keeps ingesting into memory meanwhile.")
    durable_backlog_bytes: int = Field(256 * 1024 * 1024, ge=0, description="Chunks (wire bytes) kept in memory while the durable log cannot be written, to log them when it can again; past this the oldest are dropped from the backlog (a restart then restores from the oldest kept).")
    drop_after_s: float = Field(2.0, gt=0, lt=5, description="A chunk waiting this long for a full ingest queue is dropped and counted (stays below Zenoh's 5 s BLOCK fuse).")
    check_semantics: bool = Field(True, description="Check each chunk's meaning against the run's env spec (actions in range, n in 1..actor.n_step, observation dtypes and finite Box bounds, reward and priority bounds); a chunk that fails is rejected and counted by reason and source.")
    check_obs_bounds: bool = Field(True, description="With check_semantics: also check observations against the env's finite Box bounds (turn off for an env whose observations leave its declared bounds).")
    max_abs_reward: float = Field(1e3, gt=0, description="With check_semantics: a chunk with an (n-step) reward whose magnitude exceeds this is rejected. The default is far above every shipped env's n-step sums (CartPole and Pong 1 per step, BurgerWar's +-5 win bonus and small marker gains, times n_step <= 5): it bounds what a sender can make the targets do, not honest play; raise it for an env with larger rewards.")
    max_priority: float = Field(1e6, gt=0, description="With check_semantics: a chunk with an initial priority above this is rejected, and so is a learner priority update; the learner clips its priorities to it and blames an item whose |TD| exceeds it when a step is non-finite. With |n-step reward| <= max_abs_reward, |Q| <= max_abs_reward / (1 - gamma), so an honest |TD| stays under 2 * max_abs_reward / (1 - gamma) = 2e5 at the defaults and gamma 0.99 (R2D2's rescaled TD is far smaller); beyond that it measures nothing.")
    quarantine_rejections: int = Field(20, ge=0, description="A source (the actor id in the key) with this many rejected chunks within quarantine_window_s has its traffic dropped for quarantine_s; 0 turns quarantine off.")
    quarantine_window_s: float = Field(10.0, gt=0, description="Window over which a source's rejected chunks are counted for quarantine.")
    quarantine_s: float = Field(60.0, gt=0, description="How long a quarantined source's chunks are dropped unread.")
    replays_per_machine: int = Field(1, ge=1, le=4096, description="Replay services that share this machine's memory (or its container's limit): the replay's memory check, before it allocates, gives each 1/N of it. `zenrl run` sets it to the replays it starts (shards, league agents); set it where several replay services run on one machine otherwise.")
    shards: int = Field(1, ge=1, le=MAX_REPLAY_SHARDS, description="Replay services in the run (`zenrl replay --shard k`, k in 0..shards-1): actor slot i writes to shard i % shards, the learner samples across shards in proportion to each one's total priority (docs/architecture.md). capacity, max_bytes, min_size and samples_per_insert apply to each shard. 1: one replay on the unsharded keys.")


class ActorConfig(_Section):
    num_actors: int = Field(2, ge=1, description="Number of actor processes `zenrl run` starts.")
    envs_per_actor: int = Field(16, ge=1, description="Environments per actor process, stepped as a batch.")
    n_step: int = Field(3, ge=1, description="n of the n-step returns built on the actor.")
    chunk_size: int = Field(256, ge=1, description="Transitions per message sent to the replay, rounded up to whole batched steps (a multiple of envs_per_actor); per-message costs dominate below ~256.")
    eps_base: float = Field(0.4, gt=0, le=1, description="Ape-X epsilon ladder: slot i of N uses eps_base ** (1 + eps_alpha * i / (N - 1)).")
    eps_alpha: float = Field(7.0, ge=0, description="Ape-X epsilon ladder exponent range.")
    slot: Optional[int] = Field(None, ge=0, description="Fixed exploration slot (default: assigned by the launcher / the running system).")
    ladder_size: Optional[int] = Field(None, ge=1, description="N of the epsilon ladder (default: num_actors).")
    weights_poll_steps: int = Field(1, ge=1, description="Check for new weights every this many batched steps.")
    episode_report_s: float = Field(1.0, gt=0, description="How often finished-episode statistics are published.")
    silent_restart_s: float = Field(60.0, gt=0, description="zenrl run: an actor that has published stats and then publishes none for this long while its process runs (stuck, e.g. in its env's step or reset) gets its threads' stacks written to its log and is restarted, as a container health check (zenrl.health --stats-within-s) restarts it in a cluster. One that has published nothing this long after it started is named once, with its stacks in its log, and left running (a slow start looks the same). The evaluator is watched the same way, after the larger of this and 3 evaluator.interval_s.")
    torch_threads: int = Field(1, ge=1, description="torch intra-op threads and numpy BLAS threads in each actor.")
    max_steps_per_s: Optional[float] = Field(None, gt=0, description="Cap on each actor's env steps per second (all its envs), leaving CPU to the learner on small machines; none by default.")
    frames: bool = Field(True, description="Image envs (any uint8 observation of 2+ dims): send each observation frame once with frame ids (docs/protocol.md) instead of obs/next_obs arrays; false sends full arrays.")
    frame_stack: int = Field(0, ge=0, description="Frame mode: observations are stacks of this many frames on their first axis (gymnasium FrameStackObservation), shared between neighbouring stacks; 0: not stacked.")
    compress: Literal["none", "lz4"] = Field("none", description="Compress the uint8 arrays (image frames) of the chunks sent to the replay: lz4 is ~GB/s and shrinks rendered frames many times; random-looking images do not shrink.")
    backlog_chunks: int = Field(512, ge=0, description="Chunks kept while no replay is reachable (resent when it is back); older ones are dropped and counted.")
    cut_non_greedy: bool = Field(False, description="Ape-X: an n-step window stops before a later step whose action was not the greedy one (exploring, or actor.guard_share's demonstrator) and bootstraps from there (Watkins's cut), so that the return measures the greedy policy's actions rather than the behaviour's; shorter returns where exploration is high.")
    guard_share: float = Field(0.0, ge=0, le=1, description="Ape-X actors of a match env with enemy_detector (zenrl/BurgerWar-v0, discrete actions): on this share of the steps where the env's guard rule fires (the other robot seen nearer than face_radius and more than face_angle off the heading), the actor takes the guard's turn towards it instead of its own action, and the transition records the turn: a demonstrator the learner learns from off-policy, not a part of the policy it ships; 0: off.")


class LearnerConfig(_Section):
    batch_size: int = Field(128, ge=1, description="Transitions per update.")
    lr: float = Field(5e-4, gt=0, description="Learning rate.")
    optimizer: Literal["adam", "rmsprop"] = Field("adam", description="adam, or rmsprop (centered).")
    adam_eps: float = Field(1.5e-4, gt=0, description="Adam epsilon (Ape-X / Rainbow use ~1.5e-4).")
    gamma: float = Field(0.99, gt=0, le=1, description="Discount factor.")
    grad_clip: float = Field(10.0, gt=0, description="Gradient-norm clip.")
    huber_delta: float = Field(1.0, gt=0, description="Huber loss threshold.")
    target_update_period: int = Field(500, ge=1, description="Copy online -> target network every this many updates.")
    beta0: float = Field(0.4, ge=0, le=1, description="Initial importance-sampling exponent beta.")
    beta_anneal_updates: int = Field(20_000, ge=1, description="Updates over which beta anneals linearly to 1.")
    publish_every_updates: int = Field(25, ge=1, description="Broadcast weights every this many updates.")
    requests_in_flight: int = Field(4, ge=1, description="Sample requests kept in flight by the prefetcher.")
    batches_per_request: int = Field(1, ge=1, le=64, description=(
        "Ape-X: each sample request asks for this many batches at once, split on arrival, so that the "
        "learner pays one request round trip per this many updates; a batch's priorities are then up to "
        "batches_per_request * requests_in_flight batches old."))
    send_linger_s: float = Field(0.01, ge=0, le=1.0, description=(
        "Ape-X: the priority/weights sender waits this long after the first queued item and sends all "
        "that gathered (priorities merged into one message), waking once per few updates; 0 sends at once."))
    device: str = Field("auto", description=(
        "torch device: auto (cuda if available), cpu, cuda, cuda:N. A small MLP (CartPole's) updates "
        "faster on the CPU than on a GPU, where kernel launches dominate."))
    torch_threads: int = Field(1, ge=1, description="torch intra-op threads in the learner.")
    checkpoint_interval_s: float = Field(60.0, gt=0, description="Save a checkpoint this often (and on stop).")
    keep_checkpoints: int = Field(3, ge=1, description="Keep the newest K checkpoints.")
    log_interval_s: float = Field(2.0, gt=0, description="How often the learner logs and publishes stats.")

    guard_max_bad_updates: int = Field(10, ge=1, description="Non-finite loss or gradients skip the update; after this many skipped in a row the learner rolls back to its last good checkpoint (or to the last good parameters it published).")
    guard_log_interval_s: float = Field(10.0, gt=0, description="Skipped updates are logged at most once per this many seconds (with a count).")
    init_from: str | None = Field(None, description=(
        "Ape-X/R2D2: a fresh learner starts from these weights instead of a random initialisation: a "
        "checkpoint of the same algorithm and network (read weights-only), or a `zenrl export` file with "
        "learner.init_exported. Ignored when the learner resumes from its own checkpoint."))
    init_exported: bool = Field(False, description=(
        "learner.init_from is a `zenrl export` TorchScript file: a program, loaded only because the config "
        "says so (as opponents.pool's exported: true)."))
    guard_imitation: float = Field(0.0, ge=0, description="Ape-X on a match env with enemy_detector (zenrl/BurgerWar-v0, discrete actions, dict observations): weight of a large-margin imitation loss (DQfD, Hester et al. 2018) on the sampled states where the env's guard rule fires (the other robot seen nearer than face_radius and more than face_angle off the heading): max_a [Q(s,a) + margin * (a != g)] - Q(s,g) for the guard's turn g, so the network itself learns to turn towards a nearby robot; 0: off.")
    guard_margin: float = Field(0.8, gt=0, description="learner.guard_imitation's margin: how far above every other action's Q value the guard's turn is pushed.")
    max_abs_obs: float = Field(1e6, gt=0, description="Ape-X/R2D2: a sampled item with a floating-point observation of larger magnitude is left out of the step and reported to the replay as poisoned (it removes the item and charges its sender). An env's Box may allow such values (CartPole's velocity bounds are float32's max) but they make the network's float32 forward overflow; the default is far above every shipped env's observations.")
    @model_validator(mode="after")
    def _check(self) -> "LearnerConfig":
        if self.batch_size * self.batches_per_request > MAX_SAMPLE_BATCH:
            raise ValueError(f"learner.batch_size * learner.batches_per_request = {self.batch_size} * "
                             f"{self.batches_per_request} exceeds {MAX_SAMPLE_BATCH} items per sample request")
        return self


class EvalConfig(_Section):
    enabled: bool = Field(True, description="Run the evaluator process.")
    interval_s: float = Field(10.0, gt=0, description="Evaluate the latest weights this often.")
    episodes: int = Field(10, ge=1, description="Greedy episodes per evaluation.")
    seed_offset: int = Field(1_000_000, ge=0, description="Evaluation seeds start at seed + seed_offset (separate from training seeds).")
    epsilon: float = Field(0.0, ge=0, le=1, description="Evaluation epsilon (0 = greedy).")
    policy: Literal["greedy", "sample"] = Field("greedy", description="greedy: argmax actions; sample: draw from the policy's action distribution (a3c and impala only), the policy they train.")


class A3CConfig(_Section):
    t_max: int = Field(5, ge=1, description="Rollout length per update (steps per env).")
    entropy_coef: float = Field(0.01, ge=0, description="Entropy bonus coefficient.")
    value_coef: float = Field(0.5, ge=0, description="Value loss coefficient.")
    gae_lambda: float = Field(1.0, ge=0, le=1, description="1 = n-step returns bootstrapped with V (A3C); < 1 = generalized advantage estimation with this lambda over the rollout (lower variance).")
    lr_anneal_updates: Optional[int] = Field(None, ge=1, description="Anneal learner.lr linearly over this many applied gradients down to lr * lr_final_fraction, then hold it (default: constant lr).")
    lr_final_fraction: float = Field(0.1, ge=0, le=1, description="Final lr as a fraction of learner.lr when lr_anneal_updates is set.")
    max_staleness: int = Field(8, ge=0, description="Drop gradients computed from parameters more than this many versions old.")
    broadcast_every: int = Field(1, ge=1, description="Broadcast parameters every K applied gradients.")
    max_gradient_steps: Optional[int] = Field(None, ge=1, description="Most env steps one worker's gradient message may claim (added to the learner's env_steps_trained); more is rejected and counted (rejected_steps). Default: a3c.t_max * actor.envs_per_actor, what one rollout of a worker of this config holds; raise it for workers run with more envs.")
    max_grad_norm: float = Field(1e6, gt=0, description="A worker's gradient whose norm (before clipping) exceeds this is rejected and counted, not clipped and applied: no honest worker sends one, and clipping would still apply a full-size step in its direction.")
    rmsprop_alpha: float = Field(0.99, gt=0, lt=1, description="RMSProp smoothing constant.")
    rmsprop_eps: float = Field(1e-5, gt=0, description="RMSProp epsilon.")


class ImpalaConfig(_Section):
    unroll_length: int = Field(32, ge=1, le=4096, description="T: steps per env in one unroll an actor publishes (the learner trains on B such unrolls per update).")
    batch_unrolls: int = Field(16, ge=1, le=4096, description="B: unrolls per learner update (T * B env steps per update).")
    lam: float = Field(1.0, ge=0, le=1, description="V-trace trace coefficient lambda (1: the paper's V-trace; < 1: lower-variance lambda-returns, as in rlax).")
    rho_bar: float = Field(1.0, gt=0, description="V-trace clip of the importance ratio in the value targets and policy-gradient advantages (rho-bar).")
    c_bar: float = Field(1.0, gt=0, description="V-trace clip of the importance ratio in the traces (c-bar), <= rho_bar in the paper.")
    value_coef: float = Field(0.5, ge=0, description="Value loss coefficient.")
    entropy_coef: float = Field(0.01, ge=0, description="Entropy bonus coefficient.")
    clip_eps: Optional[float] = Field(None, gt=0, lt=1, description="null: IMPALA's V-trace policy gradient; a number: APPO, PPO's clipped surrogate with ratio pi/mu clipped to [1 - clip_eps, 1 + clip_eps] on V-trace advantages.")
    normalize_advantages: bool = Field(False, description="APPO: normalize the advantages over each batch (mean 0, std 1).")
    reward_scale: float = Field(1.0, gt=0, le=1e3, description="The learner multiplies the rewards by this before V-trace (the value function learns scaled returns; evaluation returns are the env's). For envs whose rewards are large (e.g. Pendulum's -16 per step): the gradient is clipped as a whole (max_grad_norm), so a large value loss would crowd out the policy's gradient.")
    max_policy_lag: int = Field(16, ge=0, description="Drop (and count) unrolls acted with a policy more than this many weights versions behind the learner's.")
    queue_max_unrolls: int = Field(256, ge=1, description="Unrolls the learner's queue holds at most (the oldest of the biggest source is evicted first).")
    queue_max_bytes: int = Field(256 * 1024 * 1024, ge=1024, description="Decoded bytes the learner's queue holds at most.")
    broadcast_every: int = Field(1, ge=1, description="Broadcast weights every K updates.")
    max_grad_norm: float = Field(40.0, gt=0, description="Clip the gradient norm of each update to this (IMPALA used 40).")
    max_abs_reward: float = Field(1e3, gt=0, description="An unroll with a reward whose magnitude exceeds this is rejected and counted. The default is far above every shipped env's per-step reward (CartPole and Pong 1, BurgerWar's +-5 win bonus): it bounds what a sender can make the value targets do, not honest play; raise it for an env with larger rewards.")
    check_obs_bounds: bool = Field(True, description="Reject unrolls whose observations leave the env's finite Box bounds (turn off for an env whose observations leave its declared bounds).")
    quarantine_rejections: int = Field(20, ge=0, description="An actor with this many rejected unrolls within quarantine_window_s has its unrolls dropped unread for quarantine_s; 0 turns quarantine off.")
    quarantine_window_s: float = Field(10.0, gt=0, description="Window over which an actor's rejected unrolls are counted for quarantine.")
    quarantine_s: float = Field(60.0, gt=0, description="How long a quarantined actor's unrolls are dropped unread.")

    @model_validator(mode="after")
    def _check(self) -> "ImpalaConfig":
        if self.batch_unrolls > self.queue_max_unrolls:
            raise ValueError(f"impala.batch_unrolls {self.batch_unrolls} exceeds impala.queue_max_unrolls "
                             f"{self.queue_max_unrolls}: a batch could never be taken")
        return self


class SelfPlayConfig(_Section):
    enabled: bool = Field(False, description="Self-play (zenrl/BurgerWar* envs): actors also play frozen snapshots of the learner, read from its checkpoint directory (needs a filesystem shared with the learner, as in `zenrl run`).")
    snapshot_prob: float = Field(0.3, ge=0, le=1, description="Probability that an episode is played against a snapshot (once one is held) instead of opponents.pool's draw (env.kwargs.opponents' when the pool is empty).")
    snapshot_interval_s: float = Field(300.0, gt=0, description="Each actor adds the learner's newest checkpoint to its league of snapshots at most this often.")
    max_snapshots: int = Field(10, ge=1, description="Snapshots each actor keeps (the oldest is dropped first).")
    epsilon: float = Field(0.05, ge=0, le=1, description="Random-action probability of a snapshot opponent.")
    checkpoint_dir: Optional[str] = Field(None, description="Where snapshots are read from (default: <runs_dir>/<run_id>/checkpoints).")


class LeagueAgentConfig(_Section):
    """One learning agent of a league run: its own replay, learner and actors (``zenrl run``)."""

    role: Literal["main", "exploiter"] = Field("main", description="main: plays PFSP over every frozen player plus self-play; exploiter: plays only the current main agent and is reset periodically.")
    num_actors: int = Field(1, ge=1, le=64, description="Actor processes of this agent.")
    envs_per_actor: int = Field(8, ge=1, le=256, description="Envs per actor process of this agent.")
    overrides: dict[str, Any] = Field(default_factory=dict, description="Options set for this agent's processes only, as {'section.field': value} (e.g. learner.lr).")


def _default_agents() -> dict[str, "LeagueAgentConfig"]:
    return {"main": LeagueAgentConfig(role="main", num_actors=2, envs_per_actor=8),
            "exploiter": LeagueAgentConfig(role="exploiter", num_actors=1, envs_per_actor=8)}


class LeagueConfig(_Section):
    """A league of match players (docs/burgerwar.md, "League"): the league service holds the
    players and the payoff table and answers each actor's request for its next opponent."""

    enabled: bool = Field(False, description="zenrl run starts the league service and one replay + learner + actors per agent in league.agents (match envs only).")
    agents: dict[str, LeagueAgentConfig] = Field(default_factory=_default_agents, description="The learning agents by player id, each {role: main|exploiter, num_actors, envs_per_actor, overrides: {'section.field': value}}: exactly one with role main, any number of exploiters.")
    bots: list[str] = Field(default_factory=lambda: ["cheese", "teriyaki", "clubhouse", "waypoint"], description="Scripted bots that are players of the league (the env's opponent names).")
    selfplay_share: float = Field(0.35, ge=0, le=1, description="Main agent: share of its matches against its own current weights; the rest is PFSP over the frozen players.")
    bot_share: float = Field(0.0, ge=0, le=1, description="Main agent: share of its matches by PFSP over the scripted bots alone (on top of their place in the PFSP over every frozen player), so that the bots it beats are never all but dropped and forgotten; selfplay_share + bot_share + exploiter_share <= 1.")
    exploiter_share: float = Field(0.0, ge=0, le=1, description="Main agent: share of its matches against the exploiters' current (live) weights, split evenly between the exploiters available, as AlphaStar's main agents also play the main exploiters: main then trains on the very matches an exploiter is winning, not only on its snapshots once it is reset; selfplay_share + bot_share + exploiter_share <= 1.")
    pfsp_weighting: Literal["hard", "var"] = Field("hard", description="PFSP weighting of an opponent the main agent beats with probability x: hard (1-x)^p, var x(1-x).")
    pfsp_p: float = Field(2.0, gt=0, le=100, description="Exponent p of the hard weighting.")
    prior_win_rate: float = Field(0.5, ge=0, le=1, description="Win rate assumed for a pair before it has played (a prior worth prior_games matches).")
    prior_games: float = Field(1.0, gt=0, description="Weight of the prior, in matches, in every PFSP win rate.")
    decay: float = Field(0.99, gt=0, le=1, description="The win rates PFSP uses forget: each new match of a pair multiplies its earlier counts by this (the raw counts are kept too).")
    snapshot_interval_s: float = Field(600.0, gt=0, description="A learning agent's current weights join the league as a frozen snapshot at least this often.")
    min_snapshot_interval_s: float = Field(120.0, ge=0, description="... and sooner, once at least this long after its last one, when its win rate since then passes snapshot_win_rate.")
    snapshot_win_rate: float = Field(0.7, gt=0, le=1, description="Main agent: win rate against the league since its last snapshot that adds a snapshot early.")
    min_games: int = Field(30, ge=1, description="Matches since the last snapshot or reset before a win-rate rule may fire.")
    exploiter_reset_s: float = Field(900.0, gt=0, description="An exploiter is reset (a new generation: empty replay, weights as exploiter_init says) at least this often.")
    exploiter_win_rate: float = Field(0.7, gt=0, le=1, description="An exploiter whose win rate against the main agent since its reset passes this joins the league as a snapshot and is reset.")
    exploiter_init: Literal["fresh", "main"] = Field("fresh", description=(
        "Where a reset exploiter starts: fresh (random weights) or main (the main agent's newest checkpoint: "
        "it already plays the game, so its whole generation goes into finding main's weaknesses). The first "
        "generation, before main has a checkpoint, starts fresh either way."))
    exploiter_snapshot_on_timeout: bool = Field(True, description="An exploiter reset on the timer also leaves a snapshot in the league.")
    max_snapshots: int = Field(40, ge=1, le=1000, description="Frozen snapshots kept (the oldest is dropped with its table rows).")
    live_refresh_s: float = Field(30.0, gt=0, description="How often the weights of a learning agent served as an opponent (self-play, the exploiters' target) are refreshed.")
    opponent_epsilon: float = Field(0.05, ge=0, le=1, description="Random-action probability of a policy opponent in training matches.")
    prefetch: int = Field(8, ge=1, le=64, description="Opponent assignments each actor keeps requested ahead, so that a reset never waits for the league.")
    ticket_rate_per_s: float = Field(5.0, gt=0, le=10000, description="Opponent assignments (each a ticket that one match result may answer) an actor id gets per second at most, on average: it bounds the results one actor can report. An honest actor needs about envs_per_actor per match duration; raise it for envs with matches of a few seconds.")
    ticket_burst: int = Field(64, ge=1, le=100000, description="... and at most this many at once (at least prefetch).")
    open_tickets_per_actor: int = Field(256, ge=1, le=100000, description="Assignments an actor id may hold unanswered; beyond it the oldest is dropped (an actor that restarted leaves its own behind).")
    max_ticket_actors: int = Field(4096, ge=1, le=1000000, description="Actor ids whose tickets the league tracks; beyond it the least recently seen id is dropped with its tickets.")
    self_reset: bool = Field(True, description="For a cluster (compose, Kubernetes, several hosts), where no zenrl run restarts an agent's processes: a replay, learner or actor of an agent (--agent) that hears the league start a new generation of its agent deletes the old generation's files and exits with status 75, for its restart policy to start it afresh (docs/cluster.md). zenrl run turns it off for its children (it restarts a reset agent itself).")
    first_wait_s: float = Field(10.0, ge=0, le=120, description="An actor's first reset waits at most this long for the league's first assignment (later resets never wait: they fall back to the last opponent or the env's bots).")
    save_interval_s: float = Field(10.0, gt=0, description="The league writes its state this often (and on stop, and at once when a player joins or is reset).")
    stats_interval_s: float = Field(2.0, gt=0, description="How often the league publishes its stats.")
    max_weights_bytes: int = Field(64 * 1024 * 1024, ge=1024, le=1 << 30, description="Largest weights the league accepts from a learner or serves.")
    run_id: Optional[str] = Field(None, pattern=r"^[A-Za-z0-9_.\-]{1,64}$", description="Set by zenrl run for an agent's processes: the league's run id (its keys zenrl/<run_id>/league/...).")
    player: Optional[str] = Field(None, pattern=r"^[A-Za-z0-9_.\-]{1,64}$", description="Set by zenrl run for an agent's processes: the learning player they train (a key of agents); actors then take their opponents from the league.")

    @model_validator(mode="after")
    def _check(self) -> "LeagueConfig":
        mains = [k for k, a in self.agents.items() if a.role == "main"]
        if len(mains) != 1:
            raise ValueError(f"league.agents must hold exactly one agent with role main, got {mains}")
        ids = list(self.agents) + list(self.bots)
        for i in ids:
            if not isinstance(i, str) or not re.match(r"^[A-Za-z][A-Za-z0-9_\-]{0,31}$", i):
                raise ValueError(f"league player id {i!r} must be 1-32 characters of [A-Za-z0-9_-], starting with a letter")
        if len(set(ids)) != len(ids):
            raise ValueError(f"league.agents and league.bots share a player id: {ids}")
        if self.selfplay_share + self.bot_share + self.exploiter_share > 1.0 + 1e-9:
            raise ValueError(f"league.selfplay_share + league.bot_share + league.exploiter_share = {self.selfplay_share} "
                             f"+ {self.bot_share} + {self.exploiter_share} exceeds 1")
        if self.ticket_burst < self.prefetch:
            raise ValueError(f"league.ticket_burst {self.ticket_burst} is below league.prefetch {self.prefetch}: "
                             "an actor's first assignments would be refused")
        if self.player is not None and self.player not in self.agents:
            raise ValueError(f"league.player {self.player!r} is not one of league.agents {sorted(self.agents)}")
        return self

    @property
    def main_id(self) -> str:
        """The player id of the main agent."""
        return next(k for k, a in self.agents.items() if a.role == "main")


class OpponentSpec(_Section):
    """One named match opponent of ``opponents.pool``: a scripted ``bot`` or a frozen policy
    read from ``path``."""

    bot: Optional[str] = Field(None, description="A scripted bot of the match env by name (idle, random, cheese, teriyaki, clubhouse, waypoint, raider).")
    path: Optional[str] = Field(None, description="A frozen policy: a checkpoint file (read weights only), or with exported: true a `zenrl export` file. Relative to the working directory.")
    exported: bool = Field(False, description="path is a `zenrl export` TorchScript file: a program that runs code when loaded, so set it only for files you trust (e.g. models/*.pt).")
    weight: float = Field(1.0, gt=0, description="Relative probability of drawing this opponent for an episode.")
    epsilon: Optional[float] = Field(None, ge=0, le=1, description="Random-action probability of this frozen policy (default: opponents.epsilon).")

    @model_validator(mode="after")
    def _check(self) -> "OpponentSpec":
        if (self.bot is None) == (self.path is None):
            raise ValueError("an opponent is either a scripted `bot` or a policy file `path` (give exactly one)")
        if self.exported and self.path is None:
            raise ValueError("exported: true needs a `path`")
        if self.epsilon is not None and self.path is None:
            raise ValueError("epsilon applies to a policy `path`, not to a scripted bot")
        return self


class OpponentsConfig(_Section):
    pool: dict[str, OpponentSpec] = Field(default_factory=dict, description="Named match opponents (zenrl/BurgerWar* envs), one drawn per episode by weight, on whichever side env.kwargs.side gives the agent (a frozen policy sees the match from its own side); replaces the draw from env.kwargs.opponents. Each is {bot: NAME} or {path: FILE[, exported: true]}, with an optional weight, e.g. {target: {path: models/burgerwar_league.pt, exported: true}, waypoint: {bot: waypoint}}. A missing file or one of other observation/action spaces stops the run at start. Empty: the env draws from env.kwargs.opponents.")
    epsilon: float = Field(0.0, ge=0, le=1, description="Random-action probability of the pool's frozen policies (0: greedy, the policy as it plays).")

    @field_validator("pool")
    @classmethod
    def _names(cls, v: dict[str, OpponentSpec]) -> dict[str, OpponentSpec]:
        for name in v:
            if not re.fullmatch(r"[A-Za-z0-9_.\-]{1,64}", name):
                raise ValueError(f"opponent name {name!r} must be 1-64 letters, digits, '_', '.' or '-'")
        return v


class R2D2Config(_Section):
    """R2D2 (``algo: r2d2``): recurrent Ape-X, sequences in replay (Kapturowski et al., 2019)."""

    sequence_length: int = Field(80, ge=2, le=1000, description="R2D2: steps per stored sequence (m, even); sequences start every m/2 steps of an episode and never span two. Under r2d2, replay.capacity, replay.min_size and learner.batch_size count sequences.")
    burn_in: int = Field(40, ge=0, description="R2D2: the learner unrolls this many first steps of a sequence from its stored state without gradient and without loss (at most sequence_length / 2); sequences that start their episode are trained from step 0 with train_episode_starts.")
    n_step: int = Field(5, ge=1, le=100, description="R2D2: n of the n-step double-Q targets (shortened at a sequence's end).")
    eta: float = Field(0.9, ge=0, le=1, description="R2D2: a sequence's priority is eta * max|delta| + (1 - eta) * mean|delta| over its trained steps.")
    value_rescale_eps: float = Field(1e-3, gt=0, le=1, description="R2D2: epsilon of the value rescaling h(x) = sign(x)(sqrt(|x| + 1) - 1) + eps x the Q values are learnt under.")
    train_episode_starts: bool = Field(True, description="R2D2: a sequence that starts its episode (its stored state is exactly zero) is trained from step 0 instead of after the burn-in.")
    block_steps: int = Field(16, ge=1, le=4096, description="R2D2 actors gather the sequences closed over this many batched steps at once (one gathering and priority computation per block) and send them in chunks of ceil(actor.chunk_size / sequence_length) sequences.")
    lstm_size: int = Field(128, ge=1, le=8192, description="R2D2: size of the LSTM between the torso (network.hidden) and the dueling head.")

    @model_validator(mode="after")
    def _check(self) -> "R2D2Config":
        if self.sequence_length % 2:
            raise ValueError(f"r2d2.sequence_length must be even (sequences overlap by half), got {self.sequence_length}")
        if self.burn_in > self.sequence_length // 2:
            raise ValueError(f"r2d2.burn_in must be at most sequence_length / 2 = {self.sequence_length // 2}, "
                             f"got {self.burn_in}")
        return self


class RunConfig(_Section):
    algo: Literal["apex", "a3c", "r2d2", "impala"] = Field("apex", description="Algorithm family: apex (Ape-X DQN), a3c, r2d2 (recurrent Ape-X), or impala (IMPALA / APPO with impala.clip_eps).")
    run_id: Optional[str] = Field(None, pattern=r"^[A-Za-z0-9_.\-]{1,64}$", description="Run id (key prefix zenrl/<run_id>/ and runs/<run_id>/); default: generated.")
    runs_dir: str = Field("runs", description="Directory holding runs/<run_id>/.")
    seed: int = Field(0, ge=0, le=2**31 - 1, description="Base random seed (0 to 2^31-1: each process adds its offset, and every library it reaches takes the sum).")
    max_env_steps: Optional[int] = Field(None, ge=1, description="Stop the run after this many env steps (all actors).")
    max_updates: Optional[int] = Field(None, ge=1, description="Stop the run after this many learner updates.")
    max_wall_s: Optional[float] = Field(None, gt=0, description="Stop the run after this many seconds.")
    target_return: Optional[float] = Field(None, description="Stop the run once the greedy eval mean return reaches this.")
    progress: bool = Field(True, description="Show live progress in the terminal (zenrl run).")
    cpu_placement: Literal["auto", "off"] = Field("off", description="zenrl run, Ape-X, on a machine with 2-4 usable CPUs: auto reserves the last learner.torch_threads CPUs for the learner and runs the other processes on the rest, actors at nice +5, so that cheap actors do not starve the learner; off (the default) leaves scheduling to the OS, which suits envs whose actors need those CPUs, such as the Burger War match. Larger machines are left alone.")
    env: EnvConfig = Field(default_factory=EnvConfig)
    network: NetworkConfig = Field(default_factory=NetworkConfig)
    transport: TransportConfig = Field(default_factory=TransportConfig)
    replay: ReplayConfig = Field(default_factory=ReplayConfig)
    actor: ActorConfig = Field(default_factory=ActorConfig)
    learner: LearnerConfig = Field(default_factory=LearnerConfig)
    evaluator: EvalConfig = Field(default_factory=EvalConfig)
    a3c: A3CConfig = Field(default_factory=A3CConfig)
    impala: ImpalaConfig = Field(default_factory=ImpalaConfig)
    selfplay: SelfPlayConfig = Field(default_factory=SelfPlayConfig)
    opponents: OpponentsConfig = Field(default_factory=OpponentsConfig)
    r2d2: R2D2Config = Field(default_factory=R2D2Config)
    league: LeagueConfig = Field(default_factory=LeagueConfig)

    @field_validator("cpu_placement", mode="before")
    @classmethod
    def _yaml_off(cls, v: Any) -> Any:
        # YAML 1.1 reads a bare `off` / `on` as a boolean
        return {False: "off", True: "auto"}.get(v, v) if isinstance(v, bool) else v

    @model_validator(mode="after")
    def _check(self) -> "RunConfig":
        if self.evaluator.policy == "sample" and self.algo not in ("a3c", "impala"):
            raise ValueError("evaluator.policy 'sample' needs algo a3c or impala (a Q network has no action distribution)")
        if self.learner.init_from and self.algo not in ("apex", "r2d2"):
            raise ValueError(f"learner.init_from is for algo apex or r2d2, not {self.algo}")
        for name in ("guard_share", "cut_non_greedy"):
            if getattr(self.actor, name) and self.algo != "apex":
                raise ValueError(f"actor.{name} is for algo apex, not {self.algo}")
        if self.learner.guard_imitation and self.algo != "apex":
            raise ValueError(f"learner.guard_imitation is for algo apex, not {self.algo}")
        return self


# --------------------------------------------------------------------------------------------
def _set_path(tree: dict[str, Any], path: str, value: Any) -> None:
    parts = path.split(".")
    node = tree
    for p in parts[:-1]:
        nxt = node.get(p)
        if not isinstance(nxt, dict):
            nxt = {}
            node[p] = nxt
        node = nxt
    node[parts[-1]] = value


def _parse_value(text: str) -> Any:
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError:
        return text


def _did_you_mean(loc: tuple[Any, ...]) -> str:
    """``; did you mean 'batch_size'?`` for an unknown option close to a known one's name."""
    import difflib

    model: Any = RunConfig
    for part in loc[:-1]:
        field = getattr(model, "model_fields", {}).get(part)
        model = getattr(field, "annotation", None) if field is not None else None
        if not isinstance(model, type) or not issubclass(model, BaseModel):
            return ""
    close = difflib.get_close_matches(str(loc[-1]), list(model.model_fields), n=1)
    return f"; did you mean {close[0]!r}?" if close else ""


def _format_errors(e: ValidationError, source: str) -> str:
    lines = []
    for err in e.errors():
        loc = ".".join(str(x) for x in err["loc"]) or "(top level)"
        val = err.get("input")
        hint = _did_you_mean(tuple(err["loc"])) if err["type"] == "extra_forbidden" and err["loc"] else ""
        lines.append(f"  {loc}: {err['msg']}{hint} (got {val!r})")
    return f"invalid configuration ({source}):\n" + "\n".join(lines)


def _yaml_problem(e: yaml.YAMLError) -> str:
    """A YAML error in one line: what is wrong and where (PyYAML's own text spans several)."""
    problem = getattr(e, "problem", None) or getattr(e, "context", None)
    mark = getattr(e, "problem_mark", None) or getattr(e, "context_mark", None)
    if problem and mark is not None:
        return f"{problem} (line {mark.line + 1}, column {mark.column + 1})"
    return " ".join(str(e).split())


def load_config(path: str | os.PathLike[str] | None = None, overrides: list[str] | None = None,
                environ: Mapping[str, str] | None = None, base: dict[str, Any] | None = None) -> RunConfig:
    """Resolve a :class:`RunConfig` from the layers described in the module docstring.

    ``overrides`` are ``"section.field=value"`` strings (values parsed as YAML scalars).
    Raises :class:`ConfigError` naming every bad option.
    """
    tree: dict[str, Any] = dict(base or {})
    sources = ["defaults"]
    if path is not None:
        p = Path(path)
        if not p.is_file():
            raise ConfigError(f"config file {str(p)!r} " + ("is a directory" if p.is_dir() else "does not exist"))
        try:
            loaded = yaml.safe_load(p.read_text()) or {}
        except yaml.YAMLError as e:
            raise ConfigError(f"config file {str(p)!r} is not valid YAML: {_yaml_problem(e)}") from None
        except (OSError, UnicodeDecodeError) as e:  # unreadable, or not text at all
            raise ConfigError(f"config file {str(p)!r} cannot be read: {e}") from None
        if not isinstance(loaded, dict):
            raise ConfigError(f"config file {str(p)!r} must hold a mapping, got {type(loaded).__name__}")
        tree.update(loaded)
        sources.append(str(p))
    env = os.environ if environ is None else environ
    if env.get("ZENRL_ROUTER"):
        _set_path(tree, "transport.router", env["ZENRL_ROUTER"])
    for k, v in env.items():
        if k.startswith(ENV_PREFIX):
            _set_path(tree, k[len(ENV_PREFIX):].lower().replace("__", "."), _parse_value(v))
            sources.append(k)
    for o in overrides or []:
        if "=" not in o:
            raise ConfigError(f"override {o!r} must look like section.field=value")
        k, v = o.split("=", 1)
        _set_path(tree, k.strip(), _parse_value(v))
        sources.append(f"--set {k.strip()}")
    try:
        return RunConfig.model_validate(tree)
    except ValidationError as e:
        raise ConfigError(_format_errors(e, ", ".join(sources))) from None


def config_from_dict(d: Mapping[str, Any]) -> RunConfig:
    """Validate a resolved config saved by zenrl (a run directory or checkpoint). Options that
    this version no longer has are dropped with a warning, so older runs stay readable."""
    tree = _plain(d)
    for _ in range(64):
        try:
            return RunConfig.model_validate(tree)
        except ValidationError as e:
            gone = [err["loc"] for err in e.errors() if err["type"] == "extra_forbidden"]
            if not gone or len(gone) != len(e.errors()):
                raise ConfigError(_format_errors(e, "saved config")) from None
            for loc in gone:
                node = tree
                for part in loc[:-1]:
                    node = node[part]
                node.pop(loc[-1], None)
                logging.getLogger(__name__).warning("saved config option %s is unknown to this version; ignored",
                                                    ".".join(map(str, loc)))
    raise ConfigError("saved config could not be read")


def _plain(d: Mapping[str, Any]) -> dict[str, Any]:
    return {k: _plain(v) if isinstance(v, Mapping) else v for k, v in d.items()}


def describe_options(model: type[BaseModel] = RunConfig, prefix: str = "") -> list[tuple[str, str, str]]:
    """``[(dotted name, default, description)]`` of every option, for ``--help``."""
    rows = []
    for name, f in model.model_fields.items():
        ann = f.annotation
        dotted = f"{prefix}{name}"
        if isinstance(ann, type) and issubclass(ann, BaseModel):
            rows.extend(describe_options(ann, dotted + "."))
        else:
            default = f.get_default(call_default_factory=True)
            rows.append((dotted, repr(default), f.description or ""))
    return rows
