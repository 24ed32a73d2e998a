"""Loading the bundled keypoint Diffusion Policy and sampling chunks from numpy."""

import pathlib

import gymnasium as gym
import numpy as np
import pytest

import mte
from mte import policy as mp

BUNDLED = pathlib.Path(__file__).resolve().parents[2] / "assets/policies/pusht_keypoints_cpu"


def first_observation():
    env = gym.make("mte/PushT-v0", obs_type="environment_state_agent_pos", reset_stream="legacy")
    obs, _ = env.reset(seed=100000)
    return mp.observation(obs["agent_pos"], env_state=obs["environment_state"])


def test_bundled_policy_samples_a_seeded_chunk():
    p = mp.load(BUNDLED)
    assert (p.horizon, p.n_obs_steps, p.action_dim) == (16, 2, 2)
    assert p.needs() == {"env_state": True, "image": None, "wrist_image": False}
    o = first_observation()
    chunk = p.predict([o, o], seed=7)
    assert chunk.shape == (16, 2) and chunk.dtype == np.float32
    assert np.isfinite(chunk).all()
    # Targets in (a margin around) the 512 px workspace.
    assert (chunk > -100).all() and (chunk < 612).all()
    np.testing.assert_array_equal(chunk, p.predict([o, o], seed=7))
    assert np.abs(chunk - p.predict([o, o], seed=8)).max() > 0


def test_bad_queries_are_typed_errors():
    p = mp.load(BUNDLED)
    o = first_observation()
    with pytest.raises(mte.MteError, match="state"):
        p.predict([{"env_state": o["env_state"]}] * 2, seed=0)
    with pytest.raises(mte.MteError):
        p.predict([o], seed=0)  # one observation for a policy that reads two
    with pytest.raises(mte.MteError, match="config.json"):
        mp.load(BUNDLED / "missing")
    # A wrist frame of the wrong dtype is named, not ignored.
    bad = dict(o, wrist_image=np.zeros((4, 4, 3), dtype=np.float32))
    with pytest.raises(mte.MteError, match="wrist_image"):
        p.predict([bad, bad], seed=0)


def test_the_wrist_frame_passes_through_the_helper():
    frame = np.arange(4 * 4 * 3).reshape(4, 4, 3)
    o = mp.observation([1.0, 2.0], image=frame, wrist_image=255 - frame)
    assert o["wrist_image"].dtype == np.uint8 and o["wrist_image"].flags["C_CONTIGUOUS"]
    np.testing.assert_array_equal(o["wrist_image"], 255 - frame)
