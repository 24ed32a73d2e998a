"""The LeRobot-loop example runs and the median keeps closer to the clean plan there."""

import numpy as np

import repo_script


def test_lerobot_loop_example_runs():
    module = repo_script.load("python/examples/lerobot_loop.py")
    ewm, median = module.run(None), module.run("median")
    assert np.isfinite(ewm) and np.isfinite(median) and ewm > 0 and median > 0
