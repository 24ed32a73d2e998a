"""robosuite stepped directly in Python, beside `mte env bench` (the same environment
through the bridge): the same task, seed, scripted expert actions and observation
extraction, in one process with no bridge, so the difference of the two is what the bridge
costs (a frame each way per request, the worker's request loop).

    MUJOCO_GL=egl target/envs/robomimic/bin/python tools/reference/bench_robosuite_direct.py \
        --env robomimic:lift --steps 400 [--image 84x84]
    target/release/mte env bench --env robomimic:lift --steps 400 [--image 84x84]

Pins: tools/envs/robomimic-requirements.txt (robosuite 1.5.1, mujoco 3.3.0). Prints the
steps per second of the timed loop (after one reset, as `mte env bench` times it).
"""

import argparse
import importlib.util
import os
import pathlib
import time

ROOT = pathlib.Path(__file__).resolve().parents[2]


def load_worker():
    path = ROOT / "crates" / "mte-eval" / "src" / "bridge" / "worker.py"
    spec = importlib.util.spec_from_file_location("mte_bridge_worker", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--env", default="robomimic:lift")
    p.add_argument("--steps", type=int, default=400)
    p.add_argument("--image", default=None, help="WxH, e.g. 84x84")
    p.add_argument("--seed", type=int, default=100000)
    a = p.parse_args()
    os.environ.setdefault("MUJOCO_GL", "egl")
    worker = load_worker()
    needs = {"env_state": False, "image": [int(v) for v in a.image.split("x")] if a.image else None}
    env = worker.make(a.env, needs)
    env.reset(a.seed)
    t0 = time.perf_counter()
    for _ in range(a.steps):
        env.observe()
        env.step(env.expert_action())
    secs = time.perf_counter() - t0
    print(f"{a.env}: {a.steps} steps (observe + expert + step, direct) in {secs:.2f} s, {a.steps / secs:.1f} steps/s")


if __name__ == "__main__":
    main()
