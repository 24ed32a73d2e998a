"""mte's environment-bridge worker: one environment, driven over stdin/stdout.

The `mte` runner starts this script (``python -u worker.py``) and sends requests; every
request gets exactly one response. A message is a frame:

    b"MTE1" | u32 LE header length | header (UTF-8 JSON) | arrays

The header's ``"arrays"`` lists ``{"name", "dtype", "shape"}`` (dtype ``"f32"``, ``"f64"``
or ``"u8"``); their raw little-endian bytes follow the header in that order, C-contiguous.
No pickle: any language can speak it.

Requests (``"op"``) and their responses (``"ok": true`` plus):

- ``hello`` ``{"target": str, "needs": {"env_state": bool, "image": [w, h] | null}}``:
  ``{"protocol": 1, "action_dim": int}``. Builds the environment.
- ``reset`` ``{"seed": int}``: ``{"score": float}``.
- ``observe``: arrays ``state`` (f32), ``env_state`` (f32, if needed), ``image`` (u8,
  ``(h, w, 3)``, if needed).
- ``step`` with array ``action`` (f32, ``action_dim``): ``{"score": float, "success": bool}``.
- ``close``: ``{}``; the worker exits.

A failure answers ``{"ok": false, "error": str}`` and the worker carries on (the runner
decides whether the episode fails); tracebacks go to stderr, which the runner keeps.

Targets:

- ``toy:<options>``: a 1-D point that moves halfway to the commanded position each step
  (score ``1 - |x - goal|``), pure Python; options ``crash-at=N`` (exit 3 at step N) and
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
  task's ``object-state``; image: ``agentview_image`` flipped vertically as robomimic does.
  Score and success: ``env._check_success()``.
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
        return out

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

        self.np, self.suite, self.needs = np, suite, needs
        image = needs.get("image")
        if image and tuple(image) != (84, 84):
            raise WorkerError(f"robomimic images are 84 x 84; the policy asks for {image}")
        self.kwargs = dict(
            env_name=ROBOMIMIC[task],
            robots="Panda",
            controller_configs=load_composite_controller_config(controller="BASIC", robot="Panda"),
            has_renderer=False,
            has_offscreen_renderer=bool(image),
            use_camera_obs=bool(image),
            camera_names=["agentview", "robot0_eye_in_hand"],
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
        return float(self.env._check_success())

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
        return out

    def step(self, action):
        self.obs, _, _, _ = self.env.step(self.np.asarray(action, dtype=self.np.float64))
        success = bool(self.env._check_success())
        return float(success), success


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
                write_frame(out, {"ok": True}, [(k, *obs[k]) for k in ("state", "env_state", "image") if k in obs])
            elif op == "step":
                action = floats(arrays, "action")
                if len(action) != env.action_dim:
                    raise WorkerError(f"action of {len(action)} values: expected {env.action_dim}")
                score, success = env.step(action)
                write_frame(out, {"ok": True, "score": float(score), "success": bool(success)})
            else:
                raise WorkerError(f"unknown op {op!r}: expected hello, reset, observe, step or close")
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
