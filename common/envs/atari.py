"""Atari games through gymnasium + ale-py (the ``atari`` extra: its wheels ship the ROMs), with
the standard DQN preprocessing: ``AtariPreprocessing`` (no-op starts, frame skip 4 with max
pooling, 84x84 grayscale) and ``FrameStackObservation`` (the last 4 frames, stacked on the first
axis: uint8[4, 84, 84]), the layout the replay's frame mode shares between neighbouring stacks
and the conv torso reads channels first."""

from __future__ import annotations

import gymnasium as gym

from zenrl.common.errors import ConfigError


def make_atari(game: str = "Pong", frame_stack: int = 4, noop_max: int = 30, frame_skip: int = 4,
               screen_size: int = 84, terminal_on_life_loss: bool = False,
               repeat_action_probability: float = 0.0, max_num_frames_per_episode: int = 108_000,
               render_mode: str | None = None) -> gym.Env:
    """``ALE/<game>-v5`` with the emulator's own frame skip off (AtariPreprocessing skips), the
    given sticky-action probability (0: the Ape-X paper's deterministic setting), and episodes
    cut at 108k emulator frames (30 minutes of play), as in the DQN papers."""
    try:
        import ale_py
    except ImportError:
        raise ConfigError("Atari envs need the atari extra: pip install 'zenrl[atari]'") from None
    gym.register_envs(ale_py)
    env = gym.make(f"ALE/{game}-v5", frameskip=1, repeat_action_probability=repeat_action_probability,
                   max_num_frames_per_episode=max_num_frames_per_episode, render_mode=render_mode)
    env = gym.wrappers.AtariPreprocessing(env, noop_max=noop_max, frame_skip=frame_skip, screen_size=screen_size,
                                          terminal_on_life_loss=terminal_on_life_loss, grayscale_obs=True)
    if frame_stack > 1:
        env = gym.wrappers.FrameStackObservation(env, frame_stack)
    return env
