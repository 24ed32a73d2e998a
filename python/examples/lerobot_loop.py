"""Swapping mte's median into a LeRobot-style ACT evaluation loop: one line changes.

Runs as is with a stand-in policy (no weights are needed): a chunk predictor whose queries
are occasionally corrupted, on mte's native PushT. With a real LeRobot ACT policy, replace
``predict_chunk`` by ``policy.model(batch)[0]`` and keep the rest.

    python python/examples/lerobot_loop.py
"""

import gymnasium as gym
import numpy as np

import mte

CHUNK = 20


def predict_chunk(obs, rng, corrupted):
    """Stand-in ACT: a straight path from the agent towards the block, as a (1, CHUNK, 2) chunk."""
    agent, block = obs[:2], obs[2:4]
    path = agent + np.linspace(0.0, 1.0, CHUNK)[:, None] * (block - agent)
    if corrupted:
        path = path + rng.normal(0, 150, 2)  # one bad query moves its whole chunk
    return path[None].astype(np.float32)


def run(aggregator):
    env = gym.make("mte/PushT-v0", obs_type="state")
    # LeRobot: ACTTemporalEnsembler(temporal_ensemble_coeff=0.01, chunk_size=CHUNK)
    ensembler = mte.ACTTemporalEnsembler(0.01, CHUNK, aggregator=aggregator)
    rng = np.random.default_rng(0)
    obs, _ = env.reset(seed=0)
    worst = 0.0
    for step in range(60):
        chunk = predict_chunk(obs, rng, corrupted=step % 10 == 5)
        action = ensembler.update(chunk)[0]
        worst = max(worst, float(np.linalg.norm(action - predict_chunk(obs, rng, False)[0, 0])))
        obs, *_ = env.step(action)
    return worst


if __name__ == "__main__":
    for agg in [None, "median"]:
        print(f"{agg or 'ewm (LeRobot)':>14}: largest deviation from the clean plan {run(agg):.1f} px")
