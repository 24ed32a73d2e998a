"""mte/PushT-v0 through gymnasium, and VecPushT."""

import gymnasium as gym
import numpy as np
import pytest

import mte
from mte import _native
from mte.envs import VecPushT


@pytest.mark.parametrize("obs_type", ["state", "environment_state_agent_pos", "pixels", "pixels_agent_pos"])
def test_every_observation_type_lies_in_its_space(obs_type):
    env = gym.make("mte/PushT-v0", obs_type=obs_type)
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs), obs_type
    assert info["is_success"] is False
    for _ in range(5):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert env.observation_space.contains(obs)
        assert 0.0 <= reward <= 1.0 and 0.0 <= info["coverage"] <= 1.0
        assert reward == pytest.approx(min(info["coverage"] / 0.95, 1.0))
        assert terminated == info["is_success"]
    assert env.render().shape == (680, 680, 3)


def test_seeded_resets_are_the_native_pcg64_resets():
    # The gymnasium env draws the initial state from np_random as gym-pusht 0.1.8 does; the
    # Rust reset reproduces gym-pusht's draws (tested in mte-sim against gym-pusht): they agree.
    env = gym.make("mte/PushT-v0").unwrapped
    core = _native.PushT()
    for seed in range(20):
        obs, _ = env.reset(seed=seed)
        np.testing.assert_array_equal(obs, core.reset(seed, "pcg64"))


def test_legacy_stream_gives_diffusion_policys_seeds_and_needs_a_seed():
    env = gym.make("mte/PushT-v0", reset_stream="legacy").unwrapped
    obs, _ = env.reset(seed=100000)
    np.testing.assert_array_equal(obs, _native.PushT().reset(100000, "legacy"))
    with pytest.raises(mte.MteError, match="needs a seed"):
        env.reset()


def test_time_limit_truncates_at_300_steps():
    env = gym.make("mte/PushT-v0")
    env.reset(seed=1)
    for step in range(300):
        _, _, terminated, truncated, _ = env.step(np.array([256.0, 256.0], dtype=np.float32))
        if terminated:
            break
    assert truncated or terminated


def test_reset_to_state_option():
    env = gym.make("mte/PushT-v0").unwrapped
    obs, _ = env.reset(options={"reset_to_state": [100.0, 100.0, 300.0, 300.0, 0.0]})
    np.testing.assert_allclose(obs, [100.0, 100.0, 300.0, 300.0, 0.0], atol=1e-9)


def test_bad_arguments_are_typed_errors():
    with pytest.raises(mte.MteError, match="obs_type 'rgb'"):
        mte.envs.PushTEnv(obs_type="rgb")
    env = mte.envs.PushTEnv()
    env.reset(seed=0)
    with pytest.raises(mte.MteError, match="expected \\(2,\\)"):
        env.step([1.0, 2.0, 3.0])


def test_vec_env_steps_like_single_envs():
    n = 9  # above the threshold where VecEnv uses threads
    vec = VecPushT(n)
    singles = [_native.PushT() for _ in range(n)]
    seeds = list(range(40, 40 + n))
    states = vec.reset(seeds)
    for s, env, row in zip(seeds, singles, states):
        np.testing.assert_array_equal(env.reset(s, "pcg64"), row)
    rng = np.random.default_rng(3)
    for _ in range(10):
        actions = rng.uniform(0, 512, (n, 2))
        states, rewards, coverages, successes = vec.step(actions)
        for i, env in enumerate(singles):
            info = env.step(list(actions[i]))
            np.testing.assert_array_equal(states[i], env.state())
            assert rewards[i] == info["reward"] and coverages[i] == info["coverage"]
    with pytest.raises(mte.MteError, match="expected \\(9, 2\\)"):
        vec.step(np.zeros((3, 2)))


def test_gym_pusht_parity_when_installed():
    """Against gym-pusht 0.1.8 itself (installed by the pinned test requirements; skipped
    where it is not): seeded resets equal, and the block's position under the same random
    actions within the bounds mte-sim's parity tests use (crates/mte-sim/tests/parity.rs:
    after 10 steps median <= 0.5 px and max <= 3 px over the episodes, after 20 the median
    <= 0.5 px). Measured here: 0.10 / 2.11 px after 10 steps, median 0.19 px after 20. Two
    physics engines drift apart after impacts, so later steps are not bounded."""
    pytest.importorskip("gym_pusht")
    after = {10: [], 20: []}
    for seed in range(10):
        theirs = gym.make("gym_pusht/PushT-v0", obs_type="state")
        ours = gym.make("mte/PushT-v0", obs_type="state")
        o_t, _ = theirs.reset(seed=seed)
        o_o, _ = ours.reset(seed=seed)
        np.testing.assert_array_equal(o_o, o_t)
        rng = np.random.default_rng(seed)
        for step in range(1, 21):
            a = rng.uniform(0, 512, 2).astype(np.float32)
            o_t, *_ = theirs.step(a)
            o_o, *_ = ours.step(a)
            if step in after:
                after[step].append(float(np.hypot(*(o_o[2:4] - o_t[2:4]))))
    assert np.median(after[10]) <= 0.5 and max(after[10]) <= 3.0, after[10]
    assert np.median(after[20]) <= 0.5, after[20]
