"""tools/history_probe.py (docs/experiments/act_obs_steps): frame bookkeeping, the k-nearest
vote, and on a synthetic dataset where the next actions depend on a direction that only the
agent's motion shows, that the probe finds it."""

import json
import pathlib

import numpy as np

import repo_script


def load_tool():
    return repo_script.load("tools/history_probe.py")


def test_previous_frames_and_chunks_stay_in_their_episode():
    t = load_tool()
    episode = np.array([0, 0, 0, 1, 1])
    assert t.previous_frame(episode).tolist() == [0, 0, 1, 3, 3]
    action = np.arange(10, dtype=float).reshape(5, 2)
    got = t.chunk_targets(action, episode, np.array([1, 3]), 3)
    assert got[:, :, 0].tolist() == [[2, 4, 4], [6, 8, 8]]


def test_the_vote_is_the_median_of_the_nearest():
    t = load_tool()
    x = np.array([[0.0], [1.0], [2.0], [10.0]])
    y = np.array([[[0.0, 0.0]], [[1.0, 5.0]], [[3.0, 1.0]], [[100.0, 100.0]]])
    vote = t.knn_vote(x, y, np.array([[1.1], [9.0]]), k=3)
    assert vote[0].tolist() == [[1.0, 1.0]]
    assert vote[1].tolist() == [[3.0, 5.0]]


def write_dataset(root: pathlib.Path, episodes: int, steps: int):
    """Agents sweep the same 1-D line right or left (by episode parity); each action is the
    position 10 px ahead in the direction of travel, which one frame cannot show."""
    state, env, action, episode = [], [], [], []
    for e in range(episodes):
        direction = 1.0 if e % 2 == 0 else -1.0
        start = 100.0 if direction > 0 else 300.0
        for f in range(steps):
            x = start + direction * 2.0 * f + (e % 7) * 0.1
            state.append([x, 50.0])
            env.append([x * 0.5] * 16)
            action.append([x + direction * 10.0, 50.0])
            episode.append(e)
    d = root / "data"
    d.mkdir(parents=True)
    np.save(d / "observation.state.npy", np.array(state, dtype=np.float32))
    np.save(d / "observation.environment_state.npy", np.array(env, dtype=np.float32))
    np.save(d / "action.npy", np.array(action, dtype=np.float32))
    np.save(d / "episode_index.npy", np.array(episode, dtype=np.int64))


def test_motion_resolves_a_direction_one_frame_hides(tmp_path, capsys):
    write_dataset(tmp_path, episodes=40, steps=100)
    args = [str(tmp_path), "--train-episodes", "30", "--test-frames", "300", "--chunk", "1", "--k", "4"]
    assert load_tool().main(args) == 0
    rows = {r["features"]: r for r in json.loads(capsys.readouterr().out)["rows"]}
    one, motion = rows["one step"], rows["one step + agent motion"]
    # One frame: half the neighbours travel the other way, the vote is about 10 px off.
    assert one["chunk_l1_px"] > 5.0
    # With the motion the direction is known: off by less than a px (positions differ by
    # at most a few tenths between neighbours).
    assert motion["chunk_l1_px"] < 1.0
    assert motion["paired_diff_vs_one_step"] < -4.0
    assert rows["two steps"]["dims"] == 36


def test_an_empty_split_is_refused(tmp_path, capsys):
    write_dataset(tmp_path, episodes=2, steps=5)
    assert load_tool().main([str(tmp_path), "--train-episodes", "5"]) == 2
    assert "--train-episodes 5" in capsys.readouterr().err
