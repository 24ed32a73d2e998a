"""mte's environment-bridge worker: one environment, driven over stdin/stdout.

The `mte` runner starts this script (``python -u worker.py``) and sends requests; every
request gets exactly one response. A message is a frame:

    b"MTE1" | u32 LE header length | header (UTF-8 JSON) | arrays

The header's ``"arrays"`` lists ``{"name", "dtype", "shape"}`` (dtype ``"f32"``, ``"f64"``
or ``"u8"``); their raw little-endian bytes follow the header in that order, C-contiguous.
No pickle: any language can speak it.

Requests (``"op"``) and their responses (``"ok": true`` plus):

- ``hello`` ``{"target": str, "needs": {"env_state": bool, "image": [w, h] | null,
  "wrist_image": bool}}``: ``{"protocol": 1, "action_dim": int}``. Builds the environment;
  a need the target cannot serve (a wrist camera on a target without one, or without
  ``image``) is refused here.
- ``reset`` ``{"seed": int}``: ``{"score": float}``.
- ``observe``: arrays ``state`` (f32), ``env_state`` (f32, if needed), ``image`` (u8,
  ``(h, w, 3)``, if needed), ``wrist_image`` (u8, the same shape, if needed).
- ``expert``: array ``action`` (f32), the task's scripted expert's action for the current
  state (from ground-truth poses; robomimic tasks and the toy).
- ``step`` with array ``action`` (f32, ``action_dim``): ``{"score": float, "success": bool}``.
- ``close``: ``{}``; the worker exits.

A failure answers ``{"ok": false, "error": str}`` and the worker carries on (the runner
decides whether the episode fails); tracebacks go to stderr, which the runner keeps.

Targets:

- ``toy:<options>``: a 1-D point that moves halfway to the commanded position each step
  (score ``1 - |x - goal|``), pure Python; its frames are uniform at ``255 x``, its wrist
  camera's at ``255 - 255 x``; options ``crash-at=N`` (exit 3 at step N) and
  ``hang-at=N`` (sleep at step N) exercise the runner's failure handling.
- ``gym:<module>/<EnvId>[?key=value&...]``: ``gymnasium.make(EnvId, **kwargs)`` after
  ``import module`` (the id tried as ``<module>/<EnvId>`` first, the namespaced form
  packages such as gym-pusht register). Observations: a dict's ``agent_pos`` is the state,
  ``environment_state`` the environment state and ``pixels`` the image; a flat array is the
  state. Score: ``info["coverage"]`` if present, else the success flag; success:
  ``info["is_success"]`` (or ``"success"``). For gym-pusht the observation type follows the
  policy's needs unless ``obs_type`` is given.
- ``robomimic:<lift|can|square>``: robosuite 1.5 as robomimic and Diffusion Policy
  configure it (Panda, OSC_POSE, 20 Hz, 400 steps). State: the 9-D proprioception
  (``robot0_eef_pos``, ``robot0_eef_quat``, ``robot0_gripper_qpos``); environment state: the
  task's ``object-state``; image: ``agentview_image``, wrist image:
  ``robot0_eye_in_hand_image``, each flipped vertically as robomimic does (only the cameras
  asked for are rendered). Score and success: ``env._check_success()``.

Gymnasium targets have no wrist camera and refuse ``wrist_image`` at ``hello``.
"""

import json
import os
import struct
import sys
import time
from array import array

MAGIC = b"MTE1"
PROTOCOL = 1
DTYPES = {"f32": ("f", 4), "f64": ("d", 8), "u8": ("B", 1)}


class WorkerError(Exception):
    """A request that cannot be served (answered with ``ok: false``)."""


# -- framing ---------------------------------------------------------------------------


def read_exact(stream, n):
    buf = bytearray()
    while len(buf) < n:
        chunk = stream.read(n - len(buf))
        if not chunk:
            return None if not buf else bytes(buf)
        buf.extend(chunk)
    return bytes(buf)


def read_frame(stream):
    """(header dict, {name: (dtype, shape, bytes)}) or None at end of input."""
    head = read_exact(stream, 8)
    if head is None:
        return None
    if len(head) < 8 or head[:4] != MAGIC:
        raise WorkerError(f"bad frame start {head[:4]!r}: expected {MAGIC!r}")
    (n,) = struct.unpack("<I", head[4:8])
    header = json.loads(read_exact(stream, n).decode("utf-8"))
    arrays = {}
    for spec in header.pop("arrays", []):
        code, size = DTYPES[spec["dtype"]]
        count = 1
        for s in spec["shape"]:
            count *= s
        data = read_exact(stream, count * size) if count else b""
        if data is None or len(data) != count * size:
            raise WorkerError(f"array {spec['name']!r} truncated")
        arrays[spec["name"]] = (spec["dtype"], list(spec["shape"]), data)
    return header, arrays


def to_bytes(dtype, values):
    """Raw little-endian bytes of a flat sequence or a numpy array."""
    if hasattr(values, "tobytes"):
        import numpy as np

        np_dtype = {"f32": "<f4", "f64": "<f8", "u8": "u1"}[dtype]
        return np.ascontiguousarray(values, dtype=np_dtype).tobytes()
    a = array(DTYPES[dtype][0], values)
    if sys.byteorder != "little":
        a.byteswap()
    return a.tobytes()


def write_frame(stream, header, arrays=()):
    """`arrays`: (name, dtype, shape, raw bytes)."""
    header = dict(header)
    header["arrays"] = [{"name": n, "dtype": d, "shape": list(s)} for n, d, s, _ in arrays]
    text = json.dumps(header).encode("utf-8")
    stream.write(MAGIC + struct.pack("<I", len(text)) + text)
    for *_, data in arrays:
        stream.write(data)
    stream.flush()


def floats(arrays, name):
    if name not in arrays:
        raise WorkerError(f"request without array {name!r}")
    dtype, shape, data = arrays[name]
    if dtype != "f32":
        raise WorkerError(f"array {name!r} of dtype {dtype}: expected f32")
    a = array("f")
    a.frombytes(data)
    if sys.byteorder != "little":
        a.byteswap()
    return list(a)


# -- environments ----------------------------------------------------------------------


class Toy:
    """A 1-D point moving halfway to its target each step; reset puts it at
    ``(seed % 7) / 7`` with the goal at 0.9."""

    def __init__(self, options, needs):
        self.crash_at = int(options.get("crash-at", -1))
        self.hang_at = int(options.get("hang-at", -1))
        self.needs = needs
        self.x, self.steps = 0.0, 0

    action_dim = 1

    def reset(self, seed):
        self.x, self.steps = (seed % 7) / 7.0, 0
        return self.score()

    def score(self):
        return max(0.0, 1.0 - abs(self.x - 0.9))

    def observe(self):
        out = {"state": ("f32", [1], to_bytes("f32", [self.x]))}
        if self.needs.get("env_state"):
            out["env_state"] = ("f32", [2], to_bytes("f32", [0.9, float(self.steps)]))
        if self.needs.get("image"):
            w, h = self.needs["image"]
            level = int(255 * min(1.0, max(0.0, self.x)))
            out["image"] = ("u8", [h, w, 3], bytes([level]) * (w * h * 3))
            if self.needs.get("wrist_image"):
                out["wrist_image"] = ("u8", [h, w, 3], bytes([255 - level]) * (w * h * 3))
        return out

    def expert_action(self):
        return [0.9]

    def step(self, action):
        self.steps += 1
        if self.steps == self.crash_at:
            print(f"toy: crashing at step {self.steps} as asked", file=sys.stderr, flush=True)
            os._exit(3)
        if self.steps == self.hang_at:
            print(f"toy: hanging at step {self.steps} as asked", file=sys.stderr, flush=True)
            time.sleep(3600)
        self.x += 0.5 * (action[0] - self.x)
        s = self.score()
        return s, s > 0.99


class Gym:
    """Any gymnasium environment (``gym:<module>/<EnvId>?key=value``)."""

    def __init__(self, spec, needs):
        import importlib

        import gymnasium as gym
        import numpy as np

        self.np = np
        path, _, query = spec.partition("?")
        module, _, env_id = path.rpartition("/")
        if not module or not env_id:
            raise WorkerError(f"gym target {spec!r}: expected gym:<module>/<EnvId>")
        importlib.import_module(module)
        kwargs = {}
        for item in filter(None, query.split("&")):
            k, _, v = item.partition("=")
            kwargs[k] = _literal(v)
        if module == "gym_pusht" and "obs_type" not in kwargs:
            if needs.get("image"):
                kwargs["obs_type"] = "pixels_agent_pos"
                w, h = needs["image"]
                kwargs.setdefault("observation_width", w)
                kwargs.setdefault("observation_height", h)
            else:
                kwargs["obs_type"] = "environment_state_agent_pos"
        # Packages register namespaced ids (gym-pusht: "gym_pusht/PushT-v0"); plain ids too.
        try:
            self.env = gym.make(f"{module}/{env_id}", **kwargs)
        except gym.error.NameNotFound:
            self.env = gym.make(env_id, **kwargs)
        self.needs = needs
        shape = self.env.action_space.shape
        self.action_dim = int(np.prod(shape)) if shape else 1
        self.obs = None

    def reset(self, seed):
        self.obs, info = self.env.reset(seed=int(seed))
        return _score(info, False)

    def observe(self):
        np, o = self.np, self.obs
        if o is None:
            raise WorkerError("observe before reset")
        if isinstance(o, dict):
            state, env_state, image = o.get("agent_pos"), o.get("environment_state"), o.get("pixels")
        else:
            state, env_state, image = o, None, None
        out = {"state": _f32(np, state)}
        if self.needs.get("env_state"):
            if env_state is None:
                raise WorkerError("the policy needs an environment state; the observation has none")
            out["env_state"] = _f32(np, env_state)
        if self.needs.get("image"):
            if image is None:
                raise WorkerError("the policy needs images; the observation has no 'pixels'")
            out["image"] = _image(np, image, self.needs["image"])
        return out

    def expert_action(self):
        raise WorkerError("gymnasium targets have no scripted expert")

    def step(self, action):
        a = self.np.asarray(action, dtype=self.np.float32).reshape(self.env.action_space.shape)
        self.obs, _, terminated, _, info = self.env.step(a)
        success = bool(info.get("is_success", info.get("success", False)))
        return _score(info, success), success


ROBOMIMIC = {"lift": "Lift", "can": "PickPlaceCan", "square": "NutAssemblySquare"}


class Robomimic:
    """robosuite 1.5 as robomimic configures it (see the module docs)."""

    def __init__(self, task, needs):
        import numpy as np

        if task not in ROBOMIMIC:
            raise WorkerError(f"robomimic task {task!r}: expected one of {sorted(ROBOMIMIC)}")
        os.environ.setdefault("MUJOCO_GL", "egl")
        import robosuite as suite
        from robosuite.controllers import load_composite_controller_config

        self.np, self.suite, self.needs, self.task = np, suite, needs, task
        image = needs.get("image")
        if image and tuple(image) != (84, 84):
            raise WorkerError(f"robomimic images are 84 x 84; the policy asks for {image}")
        # Only the cameras a policy observes are rendered (rendering is most of a step's time
        # without a GPU; each camera adds about as much again).
        cameras = ["agentview"] + (["robot0_eye_in_hand"] if needs.get("wrist_image") else [])
        self.kwargs = dict(
            env_name=ROBOMIMIC[task],
            robots="Panda",
            controller_configs=load_composite_controller_config(controller="BASIC", robot="Panda"),
            has_renderer=False,
            has_offscreen_renderer=bool(image),
            use_camera_obs=bool(image),
            camera_names=cameras,
            camera_heights=84,
            camera_widths=84,
            control_freq=20,
            horizon=400,
            ignore_done=True,
            reward_shaping=False,
            use_object_obs=True,
        )
        self.env = None
        self.action_dim = 7
        self.obs = None

    def reset(self, seed):
        # robosuite 1.5 places objects and perturbs the arm's initial joints with numpy's
        # global generator: seeding it before each reset makes the episode a function of
        # `seed` (robomimic's `env.reset()` after `np.random.seed`, as Diffusion Policy's
        # runner seeds its test episodes). The model is built once (`hard_reset=False`, as
        # Diffusion Policy sets it).
        if self.env is None:
            # Building draws too (lift's cube size is uniform in [0.020, 0.022] m): seed it,
            # so that every worker builds the same scene.
            self.np.random.seed(0)
            self.env = self.suite.make(hard_reset=False, **self.kwargs)
            # The first reset after building settles the scene differently from every
            # later one (0.75 mm on lift's cube): spend it, so that an episode does not
            # depend on whether its worker was fresh.
            self.env.reset()
        # A soft reset keeps the gripper model's smoothed command (`current_action`) from
        # the last episode, so an episode would depend on the one before it: zero it, as a
        # freshly built model has it.
        for robot in self.env.robots:
            grippers = robot.gripper.values() if isinstance(robot.gripper, dict) else [robot.gripper]
            for g in grippers:
                g.current_action = self.np.zeros(g.dof)
        self.np.random.seed(int(seed) % 2**32)
        self.obs = self.env.reset()
        self.expert = EXPERTS[self.task](self)
        return float(self.env._check_success())

    def expert_action(self):
        if self.obs is None:
            raise WorkerError("expert before reset")
        return [float(v) for v in self.expert.act()]

    def observe(self):
        np, o = self.np, self.obs
        if o is None:
            raise WorkerError("observe before reset")
        state = np.concatenate([o["robot0_eef_pos"], o["robot0_eef_quat"], o["robot0_gripper_qpos"]])
        out = {"state": _f32(np, state)}
        if self.needs.get("env_state"):
            out["env_state"] = _f32(np, o["object-state"])
        if self.needs.get("image"):
            out["image"] = _image(np, o["agentview_image"][::-1], (84, 84))
        if self.needs.get("wrist_image"):
            out["wrist_image"] = _image(np, o["robot0_eye_in_hand_image"][::-1], (84, 84))
        return out

    def step(self, action):
        self.obs, _, _, _ = self.env.step(self.np.asarray(action, dtype=self.np.float64))
        success = bool(self.env._check_success())
        return float(success), success


class Expert:
    """A scripted expert from ground-truth poses: a list of phases, each a target for the
    gripper site (m, world frame), a yaw change (rad), a gripper command (-1 open, +1
    close), and a condition that ends it. Actions are OSC_POSE deltas, proportional to the
    error and clipped to the controller's input range [-1, 1] (0.05 m and 0.5 rad per step
    at full scale)."""

    def __init__(self, env):
        self.env, self.np = env, env.np
        self.phase, self.count = 0, 0

    def sim(self):
        return self.env.env.sim

    def eef(self):
        return self.np.asarray(self.env.obs["robot0_eef_pos"], dtype=float)

    def eef_yaw(self):
        return _yaw(self.np, self.env.obs["robot0_eef_quat"])

    def act(self):
        np = self.np
        while True:
            plan = self.plan()
            if plan is None:
                return np.zeros(7)
            target, yaw, grip, done = plan
            if done or self.count > 120:
                self.phase, self.count = self.phase + 1, 0
                continue
            break
        self.count += 1
        a = np.zeros(7)
        a[:3] = np.clip((np.asarray(target) - self.eef()) / 0.05, -1, 1)
        a[5] = np.clip(yaw / 0.5, -1, 1)
        a[6] = grip
        return a


def _yaw(np, q):
    x, y, z, w = q
    return float(np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))


def _wrap(np, a, period):
    """`a` wrapped to [-period / 2, period / 2)."""
    return float((a + period / 2) % period - period / 2)


class LiftExpert(Expert):
    """Above the cube, down, close, raise."""

    def plan(self):
        np, cube = self.np, self.np.asarray(self.env.obs["object-state"][:3], dtype=float)
        near = lambda t, tol: np.linalg.norm(np.asarray(t) - self.eef()) < tol
        p = self.phase
        if p == 0:
            t = cube + [0, 0, 0.06]
            return t, 0.0, -1, near(t, 0.01)
        if p == 1:
            t = cube + [0, 0, -0.005]
            return t, 0.0, -1, near(t, 0.008) or self.count > 40
        if p == 2:
            return cube + [0, 0, -0.005], 0.0, 1, self.count >= 12
        if p == 3:
            return np.array([cube[0], cube[1], 1.05]), 0.0, 1, False
        return None


class CanExpert(Expert):
    """Above the can, down, close, up, over the can's bin region, down, open, away."""

    def plan(self):
        np, env = self.np, self.env.env
        can = np.asarray(env.sim.data.body_xpos[env.obj_body_id["Can"]], dtype=float)
        goal = np.asarray(env.target_bin_placements[env.object_to_id["can"]], dtype=float)
        near = lambda t, tol: np.linalg.norm(np.asarray(t) - self.eef()) < tol
        p = self.phase
        if p == 0:
            t = can + [0, 0, 0.08]
            return t, 0.0, -1, near(t, 0.01)
        if p == 1:
            t = can + [0, 0, 0.0]
            return t, 0.0, -1, near(t, 0.008) or self.count > 40
        if p == 2:
            return can, 0.0, 1, self.count >= 15
        if p == 3:
            t = np.array([can[0], can[1], 1.05])
            return t, 0.0, 1, self.eef()[2] > 1.0
        if p == 4:
            t = np.array([goal[0], goal[1], 1.05])
            return t, 0.0, 1, near(t, 0.015)
        if p == 5:
            t = np.array([goal[0], goal[1], 0.95])
            return t, 0.0, 1, near(t, 0.015)
        if p == 6:
            return np.array([goal[0], goal[1], 0.95]), 0.0, -1, self.count >= 10
        if p == 7:
            return np.array([goal[0], goal[1], 1.1]), 0.0, -1, False
        return None


class SquareExpert(Expert):
    """Turn the gripper along the handle, grasp it, raise the nut, turn it square to the
    peg (the nut's yaw to a multiple of 90 degrees), bring its centre over the peg, lower
    it down the peg, open."""

    def poses(self):
        np, env = self.np, self.env.env
        nut = env.nuts[0]
        body = env.obj_body_id[nut.name]
        centre = np.asarray(env.sim.data.body_xpos[body], dtype=float)
        w, x, y, z = env.sim.data.body_xquat[body]
        yaw = _yaw(np, (x, y, z, w))
        handle = np.asarray(env.sim.data.site_xpos[env.sim.model.site_name2id(nut.important_sites["handle"])], dtype=float)
        peg = np.asarray(env.sim.data.body_xpos[env.peg1_body_id], dtype=float)
        return centre, yaw, handle, peg

    def plan(self):
        np = self.np
        centre, nut_yaw, handle, peg = self.poses()
        near = lambda t, tol: np.linalg.norm(np.asarray(t) - self.eef()) < tol
        turn_to_handle = _wrap(np, nut_yaw - self.eef_yaw(), np.pi)
        square = -_wrap(np, nut_yaw, np.pi / 2)
        # Where the gripper must be for the nut's centre to sit over the peg.
        over = self.eef() + np.array([peg[0] - centre[0], peg[1] - centre[1], 0.0])
        p = self.phase
        if p == 0:
            t = handle + [0, 0, 0.08]
            return t, turn_to_handle, -1, near(t, 0.01) and abs(turn_to_handle) < 0.03
        if p == 1:
            t = handle + [0, 0, 0.0]
            return t, turn_to_handle, -1, near(t, 0.006) or self.count > 40
        if p == 2:
            return handle, 0.0, 1, self.count >= 15
        if p == 3:
            t = np.array([handle[0], handle[1], 1.0])
            return t, 0.0, 1, self.eef()[2] > 0.97
        if p == 4:
            t = np.array([over[0], over[1], 1.0])
            done = np.hypot(*(peg[:2] - centre[:2])) < 0.004 and abs(square) < 0.02
            return t, square, 1, done
        if p == 5:
            t = np.array([over[0], over[1], 0.86 + (self.eef()[2] - centre[2])])
            return t, square, 1, centre[2] < 0.87 or self.count > 60
        if p == 6:
            return self.eef(), 0.0, -1, self.count >= 10
        if p == 7:
            return self.eef() + [0, 0, 0.05], 0.0, -1, False
        return None


EXPERTS = {"lift": LiftExpert, "can": CanExpert, "square": SquareExpert}


def _literal(v):
    for cast in (int, float):
        try:
            return cast(v)
        except ValueError:
            pass
    return {"true": True, "false": False}.get(v.lower(), v)


def _score(info, success):
    if "coverage" in info:
        return float(info["coverage"])
    if "score" in info:
        return float(info["score"])
    return float(success)


def _f32(np, v):
    a = np.asarray(v, dtype=np.float32).reshape(-1)
    return ("f32", [a.size], to_bytes("f32", a))


def _image(np, img, wh):
    a = np.asarray(img)
    w, h = wh
    if a.shape != (h, w, 3) or a.dtype != np.uint8:
        raise WorkerError(f"image of shape {a.shape} and dtype {a.dtype}: expected ({h}, {w}, 3) uint8")
    return ("u8", [h, w, 3], to_bytes("u8", a))


def make(target, needs):
    kind, _, rest = target.partition(":")
    if needs.get("wrist_image") and not needs.get("image"):
        raise WorkerError("the wrist camera is rendered at the image's size: ask for image too")
    if needs.get("wrist_image") and kind == "gym":
        raise WorkerError(f"target {target!r} has no wrist camera; robomimic targets do")
    if kind == "toy":
        options = dict(o.partition("=")[::2] for o in filter(None, rest.split(",")))
        return Toy(options, needs)
    if kind == "gym":
        return Gym(rest, needs)
    if kind == "robomimic":
        return Robomimic(rest, needs)
    raise WorkerError(f"target {target!r}: expected toy:, gym:<module>/<EnvId> or robomimic:<task>")


# -- the loop --------------------------------------------------------------------------


def serve(inp, out):
    env = None
    while True:
        msg = read_frame(inp)
        if msg is None:
            return
        header, arrays = msg
        op = header.get("op")
        try:
            if op == "close":
                write_frame(out, {"ok": True})
                return
            if op == "hello":
                env = make(header["target"], header.get("needs") or {})
                write_frame(out, {"ok": True, "protocol": PROTOCOL, "action_dim": env.action_dim})
                continue
            if env is None:
                raise WorkerError(f"{op!r} before hello")
            if op == "reset":
                write_frame(out, {"ok": True, "score": float(env.reset(header["seed"]))})
            elif op == "observe":
                obs = env.observe()
                write_frame(out, {"ok": True}, [(k, *obs[k]) for k in ("state", "env_state", "image", "wrist_image") if k in obs])
            elif op == "expert":
                action = env.expert_action()
                write_frame(out, {"ok": True}, [("action", "f32", [len(action)], to_bytes("f32", action))])
            elif op == "step":
                action = floats(arrays, "action")
                if len(action) != env.action_dim:
                    raise WorkerError(f"action of {len(action)} values: expected {env.action_dim}")
                score, success = env.step(action)
                write_frame(out, {"ok": True, "score": float(score), "success": bool(success)})
            else:
                raise WorkerError(f"unknown op {op!r}: expected hello, reset, observe, expert, step or close")
        except Exception as e:  # answered, logged; the runner decides
            import traceback

            traceback.print_exc(file=sys.stderr)
            sys.stderr.flush()
            write_frame(out, {"ok": False, "error": f"{type(e).__name__}: {e}"})


def main():
    # The protocol owns the original stdout; anything else printed (a library's banner, a
    # stray print) goes to stderr, which the runner keeps for error reports.
    proto = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    sys.stdout = sys.stderr
    serve(sys.stdin.buffer, proto)


if __name__ == "__main__":
    main()
