"""mte's policies from Python: ``mte.policy.load(dir).predict(history, seed)``.

A checkpoint directory in LeRobot's layout (``config.json`` with ``"type": "diffusion"`` or
``"act"``, weights, normaliser files), e.g. ``assets/policies/pusht_keypoints_cpu``. A query
is a list of ``n_obs_steps`` observations, oldest first, each a dict with ``"state"`` (the
agent position, px, float32) and, as the policy reads them, ``"env_state"`` (16 keypoint
coordinates, px, float32) or ``"image"`` (``(96, 96, 3)`` uint8), and ``"wrist_image"`` (the
wrist camera, at the image's size) for a policy that reads it. The chunk is a float32
``(horizon, action_dim)`` array whose row ``r`` is the action (target position, px) for
control time ``t - (n_obs_steps - 1) + r``. ``seed`` fixes the sampling noise. The GIL is
released while the policy runs.
"""

from __future__ import annotations

from typing import Any, Dict

import numpy as np

from ._native import Policy

__all__ = ["Policy", "load", "observation"]


def load(path: Any) -> Policy:
    """Load the checkpoint directory ``path``."""
    return Policy.load(str(path))


def observation(
    state: Any, env_state: Any = None, image: Any = None, wrist_image: Any = None
) -> Dict[str, Any]:
    """One observation dict with the dtypes ``Policy.predict`` expects."""
    obs: Dict[str, Any] = {"state": np.ascontiguousarray(state, dtype=np.float32)}
    if env_state is not None:
        obs["env_state"] = np.ascontiguousarray(env_state, dtype=np.float32)
    if image is not None:
        obs["image"] = np.ascontiguousarray(image, dtype=np.uint8)
    if wrist_image is not None:
        obs["wrist_image"] = np.ascontiguousarray(wrist_image, dtype=np.uint8)
    return obs
