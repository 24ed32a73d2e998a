"""Pixel fixtures from the real gym-pusht for mte-sim's renderer (tests/render_parity.rs).

Writes, under OUT_DIR (default crates/mte-sim/tests/fixtures/frames):

  frame_XX.png     gym-pusht's 96x96 `pixels` observation after reset_to_state, 20 states
  frame84_XX.png   the same at observation_width = observation_height = 84 (3 states)
  canvas_XX.png    the full 512x512 canvas (`_draw()`) for 2 states
  vis_XX*.png      `render()` visualisations with the action marker (680x680 and 300x200)
  resize_*.png     cv2.resize(INTER_LINEAR) outputs of images generated from formulas
                   (see `formula_image`) that the Rust test regenerates
  frames.json      index: for each image its file, size and the ACTUAL post-reset state

States: 20 seeded draws (numpy PCG64, seed 20240607) of diverse kinds (generic, agent touching
or overlapping the block, block near walls, block near / on the goal, agent on a wall). They
are applied with env.reset(options={"reset_to_state": s}), which also runs one physics step
that may push the block, so frames.json records the state gym-pusht actually drew: agent
position, block body position and raw (unwrapped) angle. It also records the collision
segments pymunk's debug draw adds last (short red anti-aliased lines at contacts), which
mte-sim draws only when the caller passes them.

Deterministic (fixed seeds, no wall clock); runs in a few seconds.

Usage (from the repository root):
    python3 -m venv /tmp/venv-pusht
    /tmp/venv-pusht/bin/pip install -r tools/reference/requirements-pusht.txt
    /tmp/venv-pusht/bin/python tools/reference/pusht_frames.py [OUT_DIR]

    # Optional, not committed: N random states with raw canvases and observations for the
    # exhaustive check `MTE_RENDER_DUMP=DIR cargo test -p mte-sim --test render_parity -- --ignored`
    /tmp/venv-pusht/bin/python tools/reference/pusht_frames.py --dump /tmp/pusht-dump 500

It also creates or updates its own section of crates/mte-sim/tests/fixtures/README.md.
"""
import json
import math
import os
import sys
import warnings
from importlib.metadata import version
from pathlib import Path

os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
warnings.filterwarnings("ignore")

import cv2  # noqa: E402
import gymnasium as gym  # noqa: E402
import gym_pusht  # noqa: E402,F401  (registers gym_pusht/PushT-v0)
import numpy as np  # noqa: E402
import pygame  # noqa: E402
from gym_pusht.envs import pymunk_override  # noqa: E402

SCRIPT = "tools/reference/pusht_frames.py"
REQUIREMENTS = Path(__file__).resolve().parent / "requirements-pusht.txt"
PACKAGES = ["gym-pusht", "gymnasium", "pymunk", "pygame", "numpy"]
DEFAULT_OUT = Path("crates/mte-sim/tests/fixtures/frames")
SEED = 20240607
GOAL = (256.0, 256.0, math.pi / 4)
BODY_T = [(-60.0, 0.0), (60.0, 0.0), (60.0, 30.0), (-60.0, 30.0),
          (-15.0, 30.0), (15.0, 30.0), (15.0, 120.0), (-15.0, 120.0)]

# Resize fixtures: (name, formula, src_w, src_h, channels, dst_w, dst_h).
RESIZES = [
    ("resize_a_96", "a", 512, 512, 3, 96, 96),
    ("resize_a_84", "a", 512, 512, 3, 84, 84),
    ("resize_b_96", "b", 512, 512, 3, 96, 96),
    ("resize_b_84", "b", 512, 512, 3, 84, 84),
    ("resize_b_up_c1", "b", 61, 47, 1, 150, 101),
    ("resize_a_up_c3", "a", 64, 48, 3, 97, 130),
    ("resize_b_mix_c4", "b", 64, 48, 4, 37, 77),
]


def check_versions():
    pins = {}
    for line in REQUIREMENTS.read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if "==" in line:
            name, ver = line.split("==", 1)
            pins[name.strip().lower()] = ver.strip()
    got = {p: version(p) for p in PACKAGES}
    bad = {p: (got[p], pins.get(p)) for p in PACKAGES if pins.get(p) != got[p]}
    if bad:
        sys.exit(f"version mismatch with {REQUIREMENTS.name} (installed, pinned): {bad}")
    got["cv2"] = cv2.__version__
    pin_cv = pins.get("opencv-python-headless", "")
    if not pin_cv.startswith(cv2.__version__ + "."):
        # Two wheels can share the cv2 folder; the resize arithmetic is the same in 4.12-4.14
        # (checked on random images), so this is a warning only.
        print(f"warning: cv2 {cv2.__version__} imported, {pin_cv} pinned", file=sys.stderr)
    return got


def formula_image(formula, w, h, channels):
    """The resize test images, regenerated bit for bit by the Rust test:
    a: (7x + 13y + 101c) % 256,  b: (x^2 + 3 y^2 c) % 251, for pixel (x, y), channel c."""
    y, x, c = np.meshgrid(np.arange(h, dtype=np.int64), np.arange(w, dtype=np.int64),
                          np.arange(channels, dtype=np.int64), indexing="ij")
    if formula == "a":
        v = (x * 7 + y * 13 + c * 101) % 256
    else:
        v = (x * x + 3 * y * y * c) % 251
    return v.astype(np.uint8)


def write_png(path, img):
    """Writes RGB / RGBA / gray u8 HWC as PNG (cv2 wants BGR order)."""
    if img.ndim == 3 and img.shape[2] == 3:
        img = img[:, :, ::-1]
    elif img.ndim == 3 and img.shape[2] == 4:
        img = img[:, :, [2, 1, 0, 3]]
    elif img.ndim == 3:
        img = img[:, :, 0]
    if not cv2.imwrite(str(path), np.ascontiguousarray(img), [cv2.IMWRITE_PNG_COMPRESSION, 9]):
        sys.exit(f"could not write {path}")


# --------------------------------------------------------------------------------------------
# States.

def world(pose, v):
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return (pose[0] + c * v[0] - s * v[1], pose[1] + s * v[0] + c * v[1])


def draw_states(rng):
    """20 requested states [agent_x, agent_y, block_x, block_y, block_angle] and their kinds."""
    out = []
    for _ in range(6):  # generic, like gym-pusht's own reset distribution
        out.append(("generic", [rng.uniform(50, 450), rng.uniform(50, 450),
                                rng.uniform(100, 400), rng.uniform(100, 400),
                                rng.uniform(-math.pi, math.pi)]))
    for i in range(5):  # agent touching / overlapping the block (a vertex or edge midpoint)
        pose = (rng.uniform(150, 360), rng.uniform(150, 360), rng.uniform(-math.pi, math.pi))
        a, b = BODY_T[rng.integers(0, 8)], BODY_T[rng.integers(0, 8)]
        t = rng.uniform(0, 1)
        p = world(pose, (a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])))
        r = [0.0, 8.0, 15.0, 16.0, 25.0][i]  # distance from that point, px
        ang = rng.uniform(0, 2 * math.pi)
        out.append(("agent_touching_block", [p[0] + r * math.cos(ang), p[1] + r * math.sin(ang),
                                             pose[0], pose[1], pose[2]]))
    for bx, by in [(70.0, 250.0), (440.0, 120.0), (260.0, 420.0)]:  # block near walls
        out.append(("block_near_wall", [rng.uniform(100, 400), rng.uniform(100, 400),
                                        bx + rng.uniform(-10, 10), by + rng.uniform(-10, 10),
                                        rng.uniform(-math.pi, math.pi)]))
    for k in range(3):  # block near the goal
        out.append(("block_near_goal", [rng.uniform(50, 150), rng.uniform(350, 450),
                                        GOAL[0] + rng.uniform(-8, 8) * (k + 1),
                                        GOAL[1] + rng.uniform(-8, 8) * (k + 1),
                                        GOAL[2] + rng.uniform(-0.1, 0.1) * (k + 1)]))
    out.append(("block_on_goal", [100.0, 420.0, GOAL[0], GOAL[1], GOAL[2]]))
    out.append(("agent_on_wall", [rng.uniform(0, 14), rng.uniform(30, 480),
                                  rng.uniform(150, 350), rng.uniform(150, 350),
                                  rng.uniform(-math.pi, math.pi)]))
    out.append(("agent_off_canvas_edge", [511.0, 3.0, rng.uniform(150, 350),
                                          rng.uniform(150, 350), rng.uniform(-math.pi, math.pi)]))
    return out


class ContactLog:
    """Records the collision segments pymunk's debug draw passes to draw_segment."""

    def __init__(self):
        self.segments = []
        orig = pymunk_override.DrawOptions.draw_segment
        log = self

        def draw_segment(self_, a, b, color):
            log.segments.append([float(a[0]), float(a[1]), float(b[0]), float(b[1])])
            return orig(self_, a, b, color)

        pymunk_override.DrawOptions.draw_segment = draw_segment


def make_env(size):
    return gym.make("gym_pusht/PushT-v0", obs_type="pixels_agent_pos",
                    observation_width=size, observation_height=size)


def reset_to(env, state, log):
    log.segments.clear()
    obs, _ = env.reset(options={"reset_to_state": np.array(state, dtype=np.float64)})
    u = env.unwrapped
    actual = {
        "agent": [float(u.agent.position[0]), float(u.agent.position[1])],
        "block": [float(u.block.position[0]), float(u.block.position[1]), float(u.block.angle)],
        "contacts": list(log.segments),
    }
    return obs["pixels"], actual


def canvas(env):
    screen = env.unwrapped._draw()
    return np.transpose(np.array(pygame.surfarray.pixels3d(screen)), axes=(1, 0, 2))


# --------------------------------------------------------------------------------------------

def dump(out_dir, n):
    """Raw (uncommitted) data for an exhaustive check: n random states, canvases, 96x96 obs."""
    out_dir.mkdir(parents=True, exist_ok=True)
    log = ContactLog()
    env = make_env(96)
    rng = np.random.default_rng(SEED + 1)
    index = []
    for i in range(n):
        state = [rng.uniform(0, 512), rng.uniform(0, 512), rng.uniform(40, 472),
                 rng.uniform(40, 472), rng.uniform(-4 * math.pi, 4 * math.pi)]
        if i % 3 == 0:  # agent near the block origin, often overlapping
            state[0] = state[2] + rng.uniform(-60, 60)
            state[1] = state[3] + rng.uniform(-20, 80)
        pixels, actual = reset_to(env, state, log)
        (out_dir / f"canvas_{i:04}.rgb").write_bytes(canvas(env).tobytes())
        (out_dir / f"obs96_{i:04}.rgb").write_bytes(np.ascontiguousarray(pixels).tobytes())
        index.append({"canvas": f"canvas_{i:04}.rgb", "obs96": f"obs96_{i:04}.rgb", **actual})
    (out_dir / "dump.json").write_text(json.dumps(index, indent=1) + "\n")
    print(f"wrote {n} states to {out_dir}")


def main_fixtures(out_dir):
    versions = check_versions()
    out_dir.mkdir(parents=True, exist_ok=True)
    log = ContactLog()
    rng = np.random.default_rng(SEED)
    states = draw_states(rng)
    env96, env84 = make_env(96), make_env(84)
    frames = []
    for i, (kind, state) in enumerate(states):
        pixels, actual = reset_to(env96, state, log)
        name = f"frame_{i:02}.png"
        write_png(out_dir / name, pixels)
        frames.append({"png": name, "kind": kind, "width": 96, "height": 96, **actual})
        if i in (2, 11, 16):
            pixels84, actual84 = reset_to(env84, state, log)
            name = f"frame84_{i:02}.png"
            write_png(out_dir / name, pixels84)
            frames.append({"png": name, "kind": kind, "width": 84, "height": 84, **actual84})
        if i in (3, 11):
            name = f"canvas_{i:02}.png"
            write_png(out_dir / name, canvas(env96))
            frames.append({"png": name, "kind": kind, "width": 512, "height": 512, **actual})
        if i == 7:
            u = env96.unwrapped
            action = [float(u.agent.position[0]) + 40.0, float(u.agent.position[1]) - 25.0]
            u._last_action = np.array(action)
            vis = env96.render()
            name = f"vis_{i:02}.png"
            write_png(out_dir / name, vis)
            frames.append({"png": name, "kind": kind, "width": vis.shape[1],
                           "height": vis.shape[0], "action": action, **actual})
            # Non-square: gym-pusht scales the marker's x by the height (and y by the width).
            env_wide = gym.make("gym_pusht/PushT-v0", obs_type="pixels_agent_pos",
                                visualization_width=300, visualization_height=200)
            _, actual_wide = reset_to(env_wide, state, log)
            env_wide.unwrapped._last_action = np.array(action)
            vis = env_wide.render()
            name = f"vis_{i:02}_300x200.png"
            write_png(out_dir / name, vis)
            frames.append({"png": name, "kind": kind, "width": vis.shape[1],
                           "height": vis.shape[0], "action": action, **actual_wide})
    resizes = []
    for name, formula, sw, sh, cn, dw, dh in RESIZES:
        src = formula_image(formula, sw, sh, cn)
        dst = cv2.resize(src, (dw, dh))
        if dst.ndim == 2:
            dst = dst[:, :, None]
        write_png(out_dir / f"{name}.png", dst)
        resizes.append({"png": f"{name}.png", "formula": formula, "src_width": sw,
                        "src_height": sh, "channels": cn, "width": dw, "height": dh})
    index = {
        "generator": SCRIPT,
        "versions": versions,
        "seed": SEED,
        "goal": list(GOAL),
        "frames": frames,
        "resize": resizes,
    }
    (out_dir / "frames.json").write_text(json.dumps(index, indent=1) + "\n")
    update_readme(out_dir.parent, versions)
    print(f"wrote {len(frames)} frames and {len(resizes)} resize fixtures to {out_dir}")


README_BEGIN = "<!-- BEGIN pusht_frames.py -->"
README_END = "<!-- END pusht_frames.py -->"


def readme_section(versions):
    vs = ", ".join(f"{k} {v}" for k, v in versions.items())
    return f"""{README_BEGIN}
## `frames/` — gym-pusht pixels (renderer parity)

Written by `{SCRIPT}` ({vs}); checked by `crates/mte-sim/tests/render_parity.rs`.

- `frames.json`: for every PNG its size and the state gym-pusht actually drew after
  `reset(options={{"reset_to_state": ...}})` (agent position; block body position and raw
  angle), the kind of state, and the collision segments `[ax, ay, bx, by]` pymunk's debug draw
  added (red anti-aliased lines at contacts; mte-sim draws them only when given, via the
  `*_with_contacts` methods); `resize` lists the cv2 resize fixtures and their source formula.
- `frame_XX.png` (96x96, 20 states), `frame84_XX.png` (84x84, 3 states): `pixels`
  observations. `canvas_XX.png`: full 512x512 canvases (2 states). `vis_07.png`,
  `vis_07_300x200.png`: `render()` frames (680x680 default, and 300x200) with the action
  cross. `resize_*.png`: `cv2.resize(img, (w, h))` of formula images
  (a: `(7x + 13y + 101c) % 256`, b: `(x^2 + 3y^2 c) % 251`).

The test requires every image to be bit-exact when drawn with its recorded contact segments
and reports (and bounds) the error without them. Regenerate (deterministic):

```bash
python3 -m venv /tmp/venv-pusht
/tmp/venv-pusht/bin/pip install -r tools/reference/requirements-pusht.txt
/tmp/venv-pusht/bin/python tools/reference/pusht_frames.py
# optional exhaustive check on N random states (raw dump, not committed):
/tmp/venv-pusht/bin/python tools/reference/pusht_frames.py --dump /tmp/pusht-dump 400
MTE_RENDER_DUMP=/tmp/pusht-dump cargo test -p mte-sim --test render_parity -- --ignored
```
{README_END}
"""


def update_readme(fixtures_dir, versions):
    path = fixtures_dir / "README.md"
    section = readme_section(versions)
    text = path.read_text() if path.exists() else ""
    if README_BEGIN in text and README_END in text:
        a = text.index(README_BEGIN)
        b = text.index(README_END) + len(README_END)
        if text[b:b + 1] == "\n":
            b += 1
        text = text[:a] + section + text[b:]
    else:
        if not text:
            text = "# mte-sim test fixtures\n\n"
        elif not text.endswith("\n"):
            text += "\n"
        if not text.endswith("\n\n"):
            text += "\n"
        text += section
    path.write_text(text)


def main():
    args = sys.argv[1:]
    if args and args[0] == "--dump":
        if len(args) != 3:
            sys.exit("usage: pusht_frames.py --dump DIR N")
        dump(Path(args[1]), int(args[2]))
    else:
        main_fixtures(Path(args[0]) if args else DEFAULT_OUT)


if __name__ == "__main__":
    main()
