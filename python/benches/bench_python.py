"""Side-by-side timings from Python, one process, peers and mte in turn.

- PushT steps/s: ``mte/PushT-v0`` against ``gym_pusht/PushT-v0`` (gym-pusht 0.1.8), state and
  pixels observations, single environment; and ``mte.envs.VecPushT`` (Rust threads) against
  gymnasium's ``SyncVectorEnv`` of gym-pusht, state observations.
- The ensembler's ``update``: ``mte.ACTTemporalEnsembler`` (ewm and median) against LeRobot
  0.4.4's ``ACTTemporalEnsembler`` at chunk 100, action dimension 14, batch 1.

Needs an environment with mte installed plus gym-pusht, lerobot and torch (the peers).
Prints one table; every figure is the median of ``--reps`` repetitions.

    python python/benches/bench_python.py --reps 3
"""

import argparse
import statistics
import time

import gymnasium as gym
import numpy as np

import mte


def rate(fn, n, reps):
    """Median calls per second of ``fn`` over ``reps`` runs of ``n`` calls."""
    out = []
    for _ in range(reps):
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        out.append(n / (time.perf_counter() - t0))
    return statistics.median(out)


def env_rate(env_id, obs_type, steps, reps):
    env = gym.make(env_id, obs_type=obs_type)
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    actions = rng.uniform(0, 512, (steps, 2)).astype(np.float32)
    i = [0]

    def step():
        _, _, term, trunc, _ = env.step(actions[i[0] % steps])
        i[0] += 1
        if term or trunc:
            env.reset(seed=i[0])

    return rate(step, steps, reps)


def vec_rate(n_envs, steps, reps):
    import gym_pusht  # noqa: F401

    vec = gym.vector.SyncVectorEnv([lambda: gym.make("gym_pusht/PushT-v0", obs_type="state") for _ in range(n_envs)])
    vec.reset(seed=list(range(n_envs)))
    ours = mte.envs.VecPushT(n_envs)
    ours.reset(list(range(n_envs)))
    a = np.random.default_rng(0).uniform(0, 512, (n_envs, 2))
    theirs = rate(lambda: vec.step(a.astype(np.float32)), steps, reps) * n_envs
    mine = rate(lambda: ours.step(a), steps, reps) * n_envs
    return theirs, mine


def ensembler_rate(reps, steps=2000):
    import torch
    from lerobot.policies.act.modeling_act import ACTTemporalEnsembler as Theirs

    chunks = np.random.default_rng(0).standard_normal((steps, 1, 100, 14)).astype(np.float32)
    tchunks = torch.from_numpy(chunks)
    results = {}
    for name, make, data in [
        ("LeRobot (mean)", lambda: Theirs(0.01, 100), tchunks),
        ("mte ewm:0.01", lambda: mte.ACTTemporalEnsembler(0.01, 100), chunks),
        ("mte median", lambda: mte.ACTTemporalEnsembler(0.01, 100, aggregator="median"), chunks),
    ]:
        e = make()
        i = [0]

        def upd():
            e.update(data[i[0] % steps])
            i[0] += 1

        results[name] = rate(upd, steps, reps)
    return results


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--steps", type=int, default=600)
    args = ap.parse_args()
    import gym_pusht  # noqa: F401

    print("| figure | peer | mte | ratio |\n|---|---|---|---|")
    for obs in ["state", "pixels"]:
        p = env_rate("gym_pusht/PushT-v0", obs, args.steps, args.reps)
        m = env_rate("mte/PushT-v0", obs, args.steps, args.reps)
        print(f"| PushT steps/s, {obs}, 1 env | {p:.0f} | {m:.0f} | {m / p:.1f}x |")
    for n in [2, 16]:
        p, m = vec_rate(n, args.steps // 4, args.reps)
        print(f"| PushT steps/s, state, {n} envs (SyncVectorEnv vs VecPushT) | {p:.0f} | {m:.0f} | {m / p:.1f}x |")
    r = ensembler_rate(args.reps)
    base = r["LeRobot (mean)"]
    for name in ["mte ewm:0.01", "mte median"]:
        print(f"| ensembler update/s, chunk 100, d 14 ({name}) | {base:.0f} | {r[name]:.0f} | {r[name] / base:.1f}x |")


if __name__ == "__main__":
    main()
