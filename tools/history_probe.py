"""How much does a second observed step tell about the scripted expert's next actions?

A model-free probe of an `mte data generate` PushT dataset (keypoint observations): the
expert commits to a push primitive and replans only when it ends, so its next actions may
depend on a plan that the current observation does not show. For held-out frames, the
k nearest training frames (Euclidean distance on standardised features, brute force) vote
on the next `chunk` actions (coordinate-wise median, the L1-optimal vote, as ACT's L1 loss
asks for); the error is the mean L1 distance in px per action between the vote and the
expert's actions, averaged over the chunk (and for the first action alone). Features:

- `one step`: agent position (2) and block keypoints (16) at t, what LeRobot's ACT sees;
- `one step + agent motion`: the same and the agent's displacement from t - 1;
- `two steps`: both steps' agent position and keypoints (what a two-step policy sees).

Steps before an episode's first frame repeat that frame; chunk actions past the episode's
end repeat its last action. Training frames come from the first `--train-episodes` episodes,
held-out frames from the rest; both are subsampled with a seeded generator.

    python tools/history_probe.py runs/kp_demos1800 --train-episodes 1500
"""

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def load(root: Path):
    d = root / "data"
    state = np.load(d / "observation.state.npy").astype(np.float64)
    env = np.load(d / "observation.environment_state.npy").astype(np.float64)
    action = np.load(d / "action.npy").astype(np.float64)
    episode = np.load(d / "episode_index.npy")
    return state, env, action, episode


def previous_frame(episode: np.ndarray) -> np.ndarray:
    """Index of each frame's previous frame in its episode (its own at the first)."""
    prev = np.arange(len(episode)) - 1
    first = np.r_[True, episode[1:] != episode[:-1]]
    prev[first] = np.arange(len(episode))[first]
    return prev


def chunk_targets(action: np.ndarray, episode: np.ndarray, frames: np.ndarray, chunk: int):
    """The `chunk` actions from each frame on, `(n, chunk, 2)`, clamped to its episode."""
    last = np.nonzero(np.r_[episode[1:] != episode[:-1], True])[0]
    ends = last[np.searchsorted(last, frames)]
    rows = np.minimum(frames[:, None] + np.arange(chunk)[None, :], ends[:, None])
    return action[rows]


def features(state, env, prev, kind: str) -> np.ndarray:
    now = np.concatenate([state, env], axis=1)
    if kind == "one step":
        return now
    if kind == "one step + agent motion":
        return np.concatenate([now, state - state[prev]], axis=1)
    if kind == "two steps":
        return np.concatenate([now, now[prev]], axis=1)
    raise ValueError(f"unknown feature set {kind!r}")


def knn_vote(train_x, train_y, test_x, k: int, block: int = 256) -> np.ndarray:
    """Coordinate-wise median of the k nearest training targets of each test row."""
    sq = (train_x**2).sum(axis=1)
    out = np.empty((len(test_x),) + train_y.shape[1:])
    for lo in range(0, len(test_x), block):
        q = test_x[lo : lo + block]
        d = sq[None, :] - 2.0 * q @ train_x.T
        near = np.argpartition(d, k, axis=1)[:, :k]
        out[lo : lo + block] = np.median(train_y[near], axis=1)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--train-episodes", type=int, default=1500)
    ap.add_argument("--train-frames", type=int, default=120_000)
    ap.add_argument("--test-frames", type=int, default=5_000)
    ap.add_argument("--chunk", type=int, default=20)
    ap.add_argument("--k", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    state, env, action, episode = load(a.dataset)
    prev = previous_frame(episode)
    rng = np.random.default_rng(a.seed)
    train_pool = np.nonzero(episode < a.train_episodes)[0]
    test_pool = np.nonzero(episode >= a.train_episodes)[0]
    if len(train_pool) == 0 or len(test_pool) == 0:
        print(f"error: --train-episodes {a.train_episodes} leaves no training or no held-out frame", file=sys.stderr)
        return 2
    tr = np.sort(rng.choice(train_pool, min(a.train_frames, len(train_pool)), replace=False))
    te = np.sort(rng.choice(test_pool, min(a.test_frames, len(test_pool)), replace=False))
    y_tr = chunk_targets(action, episode, tr, a.chunk)
    y_te = chunk_targets(action, episode, te, a.chunk)
    result = {
        "dataset": str(a.dataset),
        "train_frames": int(len(tr)),
        "test_frames": int(len(te)),
        "chunk": a.chunk,
        "k": a.k,
        "seed": a.seed,
        "rows": [],
    }
    for kind in ["one step", "one step + agent motion", "two steps"]:
        x = features(state, env, prev, kind)
        mu, sd = x[tr].mean(axis=0), x[tr].std(axis=0) + 1e-9
        z = (x - mu) / sd
        vote = knn_vote(z[tr], y_tr, z[te], a.k)
        err = np.abs(vote - y_te).sum(axis=2)  # (n, chunk) L1 px per action
        per_frame = err.mean(axis=1)
        se = per_frame.std(ddof=1) / np.sqrt(len(per_frame))
        result["rows"].append(
            {
                "features": kind,
                "dims": int(x.shape[1]),
                "chunk_l1_px": float(per_frame.mean()),
                "chunk_l1_se": float(se),
                "first_action_l1_px": float(err[:, 0].mean()),
                "per_frame": per_frame.tolist(),
            }
        )
    base = np.array(result["rows"][0]["per_frame"])
    for r in result["rows"]:
        diff = np.array(r["per_frame"]) - base
        r["paired_diff_vs_one_step"] = float(diff.mean())
        r["paired_diff_se"] = float(diff.std(ddof=1) / np.sqrt(len(diff)))
        del r["per_frame"]
    json.dump(result, sys.stdout, indent=1)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
