"""``zenrl play``: one greedy episode rendered to a GIF (pillow) or an MP4 (imageio-ffmpeg)."""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any, Mapping, Sequence

import gymnasium as gym
import numpy as np

from zenrl.actor.env_guard import reward_number
from zenrl.common.errors import ZenrlError
from zenrl.common.policy_io import GreedyPolicy
from zenrl.tools.loading import is_match_env, load_policy_env, need, resolve_checkpoint

#: a GIF viewer shows frames no faster than this (browsers stretch shorter frame delays)
MAX_GIF_FPS = 25.0
SIDE_RGB = {"red": (220, 30, 30), "blue": (30, 60, 220)}


def _overlay(frame: np.ndarray, lines: Sequence[str], colour: tuple[int, int, int] = (0, 0, 0),
             border: tuple[int, int, int] | None = None) -> np.ndarray:
    """Draw text lines in the top-left corner of an RGB uint8[H, W, 3] frame (pillow), and a
    ``border`` of that colour around it if given."""
    Image = need("PIL.Image", "drawing text on frames")
    ImageDraw = need("PIL.ImageDraw", "drawing text on frames")
    img = Image.fromarray(frame)
    d = ImageDraw.Draw(img)
    if border is not None:
        w, h = img.size
        d.rectangle([0, 0, w - 1, h - 1], outline=border, width=max(2, min(w, h) // 64))
    y = 4
    for line in lines:
        d.text((6, y), line, fill=colour)
        y += 12
    return np.asarray(img)


def record_episode(policy: GreedyPolicy, env: gym.Env, seed: int, options: Mapping[str, Any] | None = None,
                   max_steps: int | None = None) -> tuple[list[np.ndarray], dict[str, Any]]:
    """Play one greedy episode, rendering after reset and every step: (frames uint8[H, W, 3],
    summary {return, steps, winner, scores, side, opponent}). A match frame is framed in the
    agent's colour and captioned with its side, opponent and score."""
    match = is_match_env(env)
    policy.reseed(seed)  # what the policy draws (a mixed policy's member) follows the episode's seed
    policy.reset()  # a recurrent policy starts the episode from a zero state
    obs, info = env.reset(seed=seed, options=dict(options) if options else None)
    ret, n, done = 0.0, 0, False

    name = env.spec.id if env.spec else "this env"

    def frame() -> np.ndarray:
        try:
            img = env.render()
        except gym.error.DependencyNotInstalled as e:  # classic-control envs draw with pygame
            raise ZenrlError(f"rendering {name} needs an extra package: {e}") from None
        except NotImplementedError:
            img = None
        f = None if img is None else np.asarray(img)
        if f is None or f.ndim != 3 or f.shape[-1] not in (3, 4):
            modes = env.metadata.get("render_modes", [])
            raise ZenrlError(f"{name} renders no rgb_array frames (render() gave "
                             f"{'nothing' if f is None else f'an array of shape {f.shape}'}; its render_modes: {modes}): "
                             "zenrl play needs an env whose render(render_mode='rgb_array') returns an image")
        f = f[..., :3].astype(np.uint8)
        if not match:
            return _overlay(f, [f"step {n}", f"return {ret:.1f}"])
        side = str(info.get("side", ""))
        return _overlay(f, [f"agent: {side} vs {info.get('opponent', '?')}"], SIDE_RGB.get(side, (0, 0, 0)),
                        border=SIDE_RGB.get(side))

    frames = [frame()]
    while not done and (max_steps is None or n < max_steps):
        obs, r, term, trunc, info = env.step(policy(obs))
        ret += reward_number(r, name)
        n += 1
        done = term or trunc
        frames.append(frame())
    out: dict[str, Any] = {"return": ret, "steps": n}
    if match:
        out.update({"winner": info.get("winner"), "scores": info["war_state"]["scores"], "side": info["side"],
                    "opponent": info["opponent"]})
    return frames, out


def speed_up(frames: Sequence[np.ndarray], fps: float, speedup: float, max_fps: float) -> tuple[list[np.ndarray], float]:
    """Frames and frame rate for playing ``speedup`` times faster than ``fps``: above ``max_fps``
    every k-th frame is kept (always the last, the final state) instead of shortening frames."""
    if speedup <= 0:
        raise ZenrlError(f"--speedup must be > 0, got {speedup}")
    want = fps * speedup
    k = max(1, math.ceil(want / max_fps - 1e-9))
    kept = list(frames[::k])
    if (len(frames) - 1) % k:
        kept.append(frames[-1])
    return kept, want / k


def write_video(frames: Sequence[np.ndarray], out: str | os.PathLike[str], fps: float) -> None:
    """``.gif`` via pillow, ``.mp4`` via imageio with imageio-ffmpeg (a clear error if absent)."""
    path = Path(out)
    if path.suffix.lower() == ".gif":
        Image = need("PIL.Image", "writing a GIF")
        imgs = [Image.fromarray(f) for f in frames]
        imgs[0].save(path, save_all=True, append_images=imgs[1:], duration=max(20, int(round(1000 / fps))), loop=0)
    elif path.suffix.lower() == ".mp4":
        iio = need("imageio.v3", "writing an MP4")
        try:
            import imageio_ffmpeg  # noqa: F401
        except ImportError:
            raise ZenrlError("writing an MP4 needs imageio-ffmpeg: pip install imageio-ffmpeg (or write a .gif)") from None
        iio.imwrite(path, np.stack(frames), fps=fps, codec="libx264", macro_block_size=1)
    else:
        raise ZenrlError(f"--out must end in .gif or .mp4, got {str(path)!r}")


def play(checkpoint: str, out: str, env_id: str | None = None, env_kwargs: Mapping[str, Any] | None = None,
         opponent: str | None = None, side: str | None = None, seed: int = 0, fps: float | None = None,
         max_steps: int | None = None, speedup: float = 1.0, allow_exported: bool = False) -> dict[str, Any]:
    """Render one greedy episode of ``checkpoint`` (a file, or a folder's newest checkpoint) to
    ``out`` (.gif / .mp4). For the match, ``opponent`` (default: the env's draw) and ``side`` pick
    the game; ``fps`` defaults to real time (the match's control_hz; the env's render_fps
    otherwise); ``speedup`` plays that many times faster (a GIF drops frames above 25 fps)."""
    if Path(out).suffix.lower() not in (".gif", ".mp4"):
        raise ZenrlError(f"--out must end in .gif or .mp4, got {out!r}")
    if speedup <= 0:
        raise ZenrlError(f"--speedup must be > 0, got {speedup}")
    checkpoint = str(resolve_checkpoint(checkpoint))
    opps = [opponent] if opponent else None
    policy, env, _ = load_policy_env(checkpoint, env_id, env_kwargs, render_mode="rgb_array", opponents=opps,
                                    allow_exported=allow_exported)
    try:
        options = {}
        if is_match_env(env):
            if side:
                options["side"] = side
            rate = float(env.unwrapped.control_hz)
        else:
            rate = float(env.metadata.get("render_fps") or 30)
        frames, summary = record_episode(policy, env, seed, options, max_steps)
    finally:
        env.close()
    steps_recorded = len(frames)
    max_fps = MAX_GIF_FPS if Path(out).suffix.lower() == ".gif" else 60.0
    frames, out_fps = speed_up(frames, fps or rate, speedup, max(max_fps, fps or rate))
    write_video(frames, out, out_fps)
    summary.update({"out": str(out), "checkpoint": checkpoint, "frames": len(frames), "recorded_frames": steps_recorded,
                    "fps": out_fps, "speedup": speedup, "size": list(frames[0].shape[:2])})
    return summary
