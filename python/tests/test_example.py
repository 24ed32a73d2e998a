"""The LeRobot-loop example runs and the median keeps closer to the clean plan there."""

import importlib.util
import pathlib

import numpy as np


def test_lerobot_loop_example_runs():
    path = pathlib.Path(__file__).resolve().parents[1] / "examples/lerobot_loop.py"
    spec = importlib.util.spec_from_file_location("lerobot_loop", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    ewm, median = module.run(None), module.run("median")
    assert np.isfinite(ewm) and np.isfinite(median) and ewm > 0 and median > 0
