"""PushT for gymnasium, on mte's native simulator (gym-pusht 0.1.8's physics in Rust).

``import mte`` registers ``mte/PushT-v0`` (300-step time limit, as gym-pusht registers its
own). Observation types as gym-pusht: ``"state"`` (``[agent_x, agent_y, block_x, block_y,
block_angle]``, px and rad), ``"environment_state_agent_pos"`` (16 keypoint coordinates and
the agent position), ``"pixels"`` (``observation_height x observation_width x 3`` uint8) and
``"pixels_agent_pos"``. Actions are target positions of the agent in px, ``[0, 512]^2``.
Reward ``clip(coverage / 0.95, 0, 1)``; ``terminated`` when coverage exceeds 0.95.

Seeded resets draw the initial state from gymnasium's ``np_random`` as gym-pusht 0.1.8 does,
so they equal gym-pusht's; ``reset_stream="legacy"`` draws instead from
``np.random.RandomState(seed)`` (Diffusion Policy's test seeds 100000-100049 use it, and it
needs a seed). ``options={"reset_to_state": [...]}`` resets to a given state.
"""

from __future__ import annotations

from typing import Any, Dict, Optional, Tuple

import numpy as np

import gymnasium as gym
from gymnasium import spaces

from . import _native

OBS_TYPES = ("state", "environment_state_agent_pos", "pixels", "pixels_agent_pos")


class PushTEnv(gym.Env):
    """Native PushT with gym-pusht's interface (see the module docstring)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        obs_type: str = "state",
        render_mode: str = "rgb_array",
        observation_width: int = 96,
        observation_height: int = 96,
        visualization_width: int = 680,
        visualization_height: int = 680,
        reset_stream: str = "pcg64",
    ) -> None:
        if obs_type not in OBS_TYPES:
            raise _native.MteError(f"obs_type {obs_type!r}: expected one of {', '.join(OBS_TYPES)}")
        if render_mode not in self.metadata["render_modes"]:
            raise _native.MteError(f"render_mode {render_mode!r}: expected 'rgb_array'")
        if reset_stream not in ("pcg64", "legacy"):
            raise _native.MteError(f"reset_stream {reset_stream!r}: expected 'pcg64' or 'legacy'")
        self.obs_type = obs_type
        self.render_mode = render_mode
        self.observation_width, self.observation_height = observation_width, observation_height
        self.visualization_width, self.visualization_height = visualization_width, visualization_height
        self.reset_stream = reset_stream
        self.observation_space = _observation_space(obs_type, observation_height, observation_width)
        self.action_space = spaces.Box(low=0, high=512, shape=(2,), dtype=np.float32)
        self._core = _native.PushT()

    def reset(self, *, seed: Optional[int] = None, options: Optional[Dict[str, Any]] = None) -> Tuple[Any, Dict[str, Any]]:
        super().reset(seed=seed)
        if options is not None and options.get("reset_to_state") is not None:
            self._core.reset_to_state([float(v) for v in options["reset_to_state"]])
        elif self.reset_stream == "legacy":
            if seed is None:
                raise _native.MteError("reset_stream 'legacy' needs a seed: expected reset(seed=...)")
            self._core.reset(int(seed), "legacy")
        else:
            rng = self.np_random
            state = [
                rng.integers(50, 450),
                rng.integers(50, 450),
                rng.integers(100, 400),
                rng.integers(100, 400),
                rng.uniform(-np.pi, np.pi),
            ]
            self._core.reset_to_state([float(v) for v in state])
        info = self._info_at_reset()
        return self._observation(), info

    def step(self, action: Any) -> Tuple[Any, float, bool, bool, Dict[str, Any]]:
        a = np.asarray(action, dtype=np.float64).reshape(-1)
        if a.shape != (2,):
            raise _native.MteError(f"action of shape {np.shape(action)}: expected (2,) target [x, y] in px")
        info = self._core.step([float(a[0]), float(a[1])])
        reward = float(info.pop("reward"))
        info.pop("steps")
        terminated = bool(info["is_success"])
        return self._observation(), reward, terminated, False, info

    def render(self) -> np.ndarray:
        return self._core.render(self.visualization_width, self.visualization_height)

    def _observation(self) -> Any:
        if self.obs_type == "state":
            return self._core.state()
        if self.obs_type == "environment_state_agent_pos":
            return {"environment_state": self._core.keypoints(), "agent_pos": self._core.agent_pos()}
        pixels = self._core.pixels(self.observation_width, self.observation_height)
        if self.obs_type == "pixels":
            return pixels
        return {"pixels": pixels, "agent_pos": self._core.agent_pos()}

    def _info_at_reset(self) -> Dict[str, Any]:
        s = self._core.state()
        return {
            "pos_agent": s[:2].copy(),
            "vel_agent": np.zeros(2),
            "block_pose": s[2:].copy(),
            "goal_pose": np.array([256.0, 256.0, np.pi / 4]),
            "n_contacts": 0,
            "is_success": False,
        }


def _observation_space(obs_type: str, height: int, width: int) -> spaces.Space:
    agent = spaces.Box(low=np.array([0, 0]), high=np.array([512, 512]), dtype=np.float64)
    pixels = spaces.Box(low=0, high=255, shape=(height, width, 3), dtype=np.uint8)
    if obs_type == "state":
        return spaces.Box(low=np.zeros(5), high=np.array([512, 512, 512, 512, 2 * np.pi]), dtype=np.float64)
    if obs_type == "environment_state_agent_pos":
        keypoints = spaces.Box(low=np.zeros(16), high=np.full((16,), 512), dtype=np.float64)
        return spaces.Dict({"environment_state": keypoints, "agent_pos": agent})
    if obs_type == "pixels":
        return pixels
    return spaces.Dict({"pixels": pixels, "agent_pos": agent})


class VecPushT:
    """``num_envs`` PushT environments stepped together in Rust, state observations.

    ``reset(seeds)`` takes one seed per environment and returns the ``(n, 5)`` states;
    ``step(actions)`` takes ``(n, 2)`` targets in px and returns ``(states, rewards,
    coverages, successes)``. Environments are stepped on several threads from 8 on, with the
    GIL released.
    """

    def __init__(self, num_envs: int) -> None:
        self._inner = _native.VecPushT(int(num_envs))
        self.num_envs = int(num_envs)

    def reset(self, seeds: Any, stream: str = "pcg64") -> np.ndarray:
        return self._inner.reset([int(s) for s in seeds], stream)

    def step(self, actions: Any):
        return self._inner.step(np.ascontiguousarray(actions, dtype=np.float64))


def register_envs() -> None:
    """Registers ``mte/PushT-v0`` with gymnasium (idempotent)."""
    if "mte/PushT-v0" not in gym.registry:
        gym.register(
            id="mte/PushT-v0",
            entry_point="mte.envs:PushTEnv",
            max_episode_steps=300,
            kwargs={"obs_type": "state"},
        )
