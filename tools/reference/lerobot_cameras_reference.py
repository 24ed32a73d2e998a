"""Reference fixtures of LeRobot's two-camera Diffusion Policy for mte-policy's parity test.

The observation the paper's robomimic policies have: a scene camera
(`observation.images.agentview_image`) and a wrist camera
(`observation.images.robot0_eye_in_hand_image`), both 3 x 84 x 84 with a 76 x 76 crop, and a
9-D proprioceptive state; 7-D actions. Uses the REAL lerobot (0.4.4) / torch (2.10.0) code,
pinned in requirements-lerobot-dp.txt, and writes into the fixtures folder given as the argument:

  tiny_cams_shared/    a tiny two-camera DiffusionPolicy with one ResNet-18 (GroupNorm) encoder
  tiny_cams_separate/  the same with one encoder per camera (use_separate_rgb_encoder_per_camera)
                       each saved as a lerobot 0.4.4 training run saves `pretrained_model/`
                       (policy.save_pretrained + the pre/post-processors with their statistics)
                       but WITHOUT model.safetensors: ResNet-18 has 11 M weights, so every
                       parameter is filled from a formula instead (`weight_rule` in the JSON) and
                       the test rebuilds the file from the state-dict listing.
  tiny_cams_reference.json  state-dict keys/shapes with the rule's first values and sums, the
                       non-parameter buffers' values, the raw observations' formulas, LeRobot's
                       normalised states and global conditioning (float32, and float64 to
                       size the float32 tolerance), and a 10-step DDPM sample with every noise
                       tensor captured, for both encoder layouts.

Everything is re-loaded and re-checked in Python before the script exits (assertions). Floats
are float32 values written as JSON doubles (exact: parse as f64, cast to f32).

Usage (from the repository root; the environment of lerobot_diffusion_reference.py):
    python3 -m venv /tmp/venv-lerobot-dp
    /tmp/venv-lerobot-dp/bin/pip install -r tools/reference/requirements-lerobot-dp.txt
    /tmp/venv-lerobot-dp/bin/python tools/reference/lerobot_cameras_reference.py \
        crates/mte-policy/tests/fixtures/lerobot_dp
"""
import json
import shutil
import sys
from pathlib import Path

import numpy as np
import torch

from lerobot_diffusion_reference import VERSIONS, NoiseRecorder, fl, manual_ddpm_loop  # noqa: E402

from lerobot.configs.types import FeatureType, NormalizationMode, PolicyFeature  # noqa: E402
from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig  # noqa: E402
from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy  # noqa: E402
from lerobot.policies.factory import make_pre_post_processors  # noqa: E402
from safetensors.torch import save_file  # noqa: E402

GENERATOR = "tools/reference/lerobot_cameras_reference.py"
STATE, ACTION, IMAGES = "observation.state", "action", "observation.images"
SCENE = "observation.images.agentview_image"
WRIST = "observation.images.robot0_eye_in_hand_image"
SIDE, CROP, STATE_DIM, ACTION_DIM = 84, 76, 9, 7
WEIGHTS = "model.safetensors"

WEIGHT_RULE = (
    "k = index of the tensor among the state dict's parameters (named_parameters() order, 0-based); "
    "j = flat C-order element index; h = (j * 2654435761 + c_k) mod 2^32 with "
    "c_k = ((k + 1) * 40503 * 65536 + 12345) mod 2^32, in unsigned 64-bit integers; "
    "u = h / 2^32 * 2 - 1 in float64 (exact); a tensor of two or more dimensions gets "
    "u / sqrt(numel / shape[0]) (torch's default bound 1/sqrt(fan_in), fan_in = numel / shape[0]); "
    "a GroupNorm weight gets 1 + u / 10; every other one-dimensional tensor u / 10; computed in "
    "float64, then cast to float32")


def rule_values(k: int, shape, groupnorm_weight: bool) -> np.ndarray:
    n = int(np.prod(shape))
    j = np.arange(n, dtype=np.uint64)
    c = np.uint64(((k + 1) * 40503 * 65536 + 12345) % 2**32)
    h = (j * np.uint64(2654435761) + c) % np.uint64(2**32)
    u = h.astype(np.float64) / 2.0**32 * 2.0 - 1.0
    if len(shape) >= 2:
        v = u / np.sqrt(float(n // shape[0]))
    elif groupnorm_weight:
        v = 1.0 + u / 10.0
    else:
        v = u / 10.0
    return v.astype(np.float32).reshape(shape)


def frame(camera: int, k: int) -> np.ndarray:
    """Camera `camera`'s (0 scene, 1 wrist) frame at control step k: HWC uint8, as mte's
    `Observation` carries it."""
    y = np.arange(SIDE).reshape(SIDE, 1, 1)
    x = np.arange(SIDE).reshape(1, SIDE, 1)
    c = np.arange(3).reshape(1, 1, 3)
    if camera == 0:
        n = (7 * x + 13 * y + 101 * c + 17 * k) % 256
    else:
        n = (x * x + 3 * x * y + 31 * c * (y + 1) + 5 + 29 * k) % 256
    return np.broadcast_to(n, (SIDE, SIDE, 3)).astype(np.uint8)


def frame_tensor(camera: int, k: int) -> torch.Tensor:
    """The frame as LeRobot's dataset gives it: CHW float32 in [0, 1] (n / 255 in float32)."""
    n = torch.from_numpy(frame(camera, k).transpose(2, 0, 1).copy())
    return n.to(torch.float32) / 255.0


def state(k: int) -> torch.Tensor:
    i = np.arange(STATE_DIM, dtype=np.float64)
    return torch.from_numpy((0.1 * (i + 1) - 0.2 + 0.05 * k * (i % 3)).astype(np.float32))


def made_up_stats():
    """Statistics shaped as lerobot 0.4.4's compute_stats writes them: images per channel as
    (3, 1, 1); state and action per coordinate."""
    def entry(mn, mx, mean, std, shape):
        t = {k: torch.tensor(v, dtype=torch.float32).reshape(shape)
             for k, v in (("min", mn), ("max", mx), ("mean", mean), ("std", std))}
        t["count"] = torch.tensor([20000])
        return t
    si = np.arange(STATE_DIM, dtype=np.float64)
    ai = np.arange(ACTION_DIM, dtype=np.float64)
    return {
        SCENE: entry([0.0] * 3, [1.0] * 3, [0.45, 0.40, 0.35], [0.25, 0.22, 0.20], (3, 1, 1)),
        WRIST: entry([0.0] * 3, [1.0] * 3, [0.30, 0.35, 0.40], [0.20, 0.21, 0.23], (3, 1, 1)),
        STATE: entry(-0.5 - 0.1 * si, 1.0 + 0.2 * si, 0.2 + 0 * si, 0.5 + 0 * si, (STATE_DIM,)),
        ACTION: entry(-0.8 - 0.05 * ai, 0.9 + 0.1 * ai, 0 * ai, 0.5 + 0 * ai, (ACTION_DIM,)),
    }


def config(separate: bool) -> DiffusionConfig:
    visual = PolicyFeature(FeatureType.VISUAL, (3, SIDE, SIDE))
    return DiffusionConfig(
        input_features={STATE: PolicyFeature(FeatureType.STATE, (STATE_DIM,)),
                        SCENE: visual, WRIST: visual},
        output_features={ACTION: PolicyFeature(FeatureType.ACTION, (ACTION_DIM,))},
        normalization_mapping={"VISUAL": NormalizationMode.MEAN_STD,
                               "STATE": NormalizationMode.MIN_MAX,
                               "ACTION": NormalizationMode.MIN_MAX},
        n_obs_steps=2, horizon=16, n_action_steps=8,
        vision_backbone="resnet18", pretrained_backbone_weights=None, use_group_norm=True,
        crop_shape=(CROP, CROP), crop_is_random=True, spatial_softmax_num_keypoints=32,
        use_separate_rgb_encoder_per_camera=separate,
        down_dims=(8, 16), kernel_size=5, n_groups=4, diffusion_step_embed_dim=8,
        use_film_scale_modulation=True, noise_scheduler_type="DDPM", num_train_timesteps=100,
        beta_schedule="squaredcos_cap_v2", clip_sample=True, clip_sample_range=1.0,
        prediction_type="epsilon", num_inference_steps=10, device="cpu", push_to_hub=False)


def fill_by_rule(policy: DiffusionPolicy):
    """Fills every parameter from WEIGHT_RULE; returns the listing the test rebuilds it from."""
    gn = {f"{m}.weight" for m, mod in policy.named_modules() if isinstance(mod, torch.nn.GroupNorm)}
    params = []
    with torch.no_grad():
        for k, (name, p) in enumerate(policy.named_parameters()):
            v = torch.from_numpy(rule_values(k, tuple(p.shape), name in gn))
            p.copy_(v)
            params.append({"index": k, "key": name, "shape": list(p.shape), "groupnorm_weight": name in gn,
                           "first": fl(p.flatten()[:3]), "sum": float(p.double().sum())})
    names = {p["key"] for p in params}
    buffers = [{"key": n, "shape": list(b.shape), "values": fl(b)}
               for n, b in policy.state_dict().items() if n not in names]
    return params, buffers


def observation(pre, k: int):
    """Step k's raw observation through LeRobot's preprocessor (normalised, batch of one)."""
    return pre({STATE: state(k), SCENE: frame_tensor(0, k), WRIST: frame_tensor(1, k)})


def conditioning(policy, normed):
    """LeRobot's global conditioning of a two-step history, stacked as select_action stacks it."""
    batch = {STATE: torch.stack([o[STATE] for o in normed], dim=1),
             IMAGES: torch.stack([torch.stack([o[c] for c in (SCENE, WRIST)], dim=-4) for o in normed], dim=1)}
    assert batch[IMAGES].shape == (1, 2, 2, 3, SIDE, SIDE)
    return policy.diffusion._prepare_global_conditioning(batch)


def build(out_dir: Path, separate: bool):
    name = "tiny_cams_separate" if separate else "tiny_cams_shared"
    cfg = config(separate)
    torch.manual_seed(0)
    policy = DiffusionPolicy(cfg)
    policy.eval()
    params, buffers = fill_by_rule(policy)
    stats = made_up_stats()
    pre, post = make_pre_post_processors(cfg, dataset_stats=stats)
    d = out_dir / name
    if d.exists():
        shutil.rmtree(d)
    policy.save_pretrained(d)
    pre.save_pretrained(d)
    post.save_pretrained(d)

    with torch.no_grad():
        normed = [observation(pre, k) for k in (0, 1)]
        for o, k in zip(normed, (0, 1)):
            for cam, idx in ((SCENE, 0), (WRIST, 1)):
                expect = (frame_tensor(idx, k) - stats[cam]["mean"]) / (stats[cam]["std"] + 1e-8)
                assert torch.allclose(o[cam][0], expect, atol=1e-6), cam
        gc = conditioning(policy, normed)
        feat = 2 * 32
        assert gc.shape == (1, 2 * (STATE_DIM + 2 * feat)), gc.shape
        # the layout: per step [state, scene features, wrist features]
        assert torch.equal(gc[0, :STATE_DIM], normed[0][STATE][0])
        p64 = DiffusionPolicy(cfg)
        p64.load_state_dict(policy.state_dict())
        p64 = p64.double().eval()
        gc64 = conditioning(p64, [{k: o[k].double() for k in (STATE, SCENE, WRIST)} for o in normed])
        f32_vs_f64 = float((gc.double() - gc64).abs().max())

        rec = NoiseRecorder()
        with rec.active():
            chunk = policy.diffusion.conditional_sample(
                1, global_cond=gc, generator=torch.Generator().manual_seed(1234))
        assert [k for k, _ in rec.calls] == ["randn"] + ["ddpm_variance_noise"] * 9
        init_noise, var_noises = rec.calls[0][1], [t for _, t in rec.calls[1:]]
        sched = policy.diffusion.noise_scheduler
        manual = manual_ddpm_loop(policy.diffusion.unet, sched, gc, init_noise, var_noises)
        assert torch.allclose(manual, chunk, atol=1e-6)
        unnorm = post(chunk.clone())
    timesteps = [int(t) for t in sched.timesteps]

    # Reload check: a policy loaded from the folder plus the rule's weights reproduces it.
    sd = policy.state_dict()
    save_file({k: v.contiguous() for k, v in sd.items()}, str(d / WEIGHTS), metadata={"format": "pt"})
    again = DiffusionPolicy.from_pretrained(d).eval()
    pre2, _ = make_pre_post_processors(again.config, pretrained_path=str(d))
    with torch.no_grad():
        assert torch.equal(conditioning(again, [observation(pre2, k) for k in (0, 1)]), gc)
    (d / WEIGHTS).unlink()
    return name, {
        "image_features_order": list(cfg.image_features),
        "parameters": params,
        "buffers": buffers,
        "normalized_state": [fl(o[STATE][0]) for o in normed],
        "global_cond": fl(gc[0]),
        "global_cond_float64": [float(v) for v in gc64[0]],
        "global_cond_float32_vs_float64_max_abs": f32_vs_f64,
        "sampling": {
            "generator_seed": 1234,
            "timesteps": timesteps,
            "initial_noise": fl(init_noise[0]),
            "variance_noise": [{"t": t, "noise": fl(v[0])} for t, v in zip(timesteps, var_noises)],
            "chunk_normalized": fl(chunk[0]),
            "chunk_unnormalized": fl(unnorm[0]),
        },
    }


def main():
    out_dir = Path(sys.argv[1])
    out_dir.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(1)
    ref = {
        "generator": GENERATOR, "versions": VERSIONS, "weight_rule": WEIGHT_RULE,
        "raw": {
            "state": "step k: state[i] = f32(0.1*(i+1) - 0.2 + 0.05*k*(i mod 3)) (f64 math, cast), i = 0..8",
            "scene_frame": "step k: HWC uint8, n = (7*x + 13*y + 101*c + 17*k) mod 256",
            "wrist_frame": "step k: HWC uint8, n = (x*x + 3*x*y + 31*c*(y+1) + 5 + 29*k) mod 256",
            "to_lerobot": "CHW float32 n / 255 (float32 division); history = steps [0, 1], oldest first",
        },
        "notes": {
            "global_cond_layout": "per obs step (oldest first): [state (9), scene camera features (64), wrist camera features (64)] -> 2 * 137 = 274",
            "image_normalization": "MEAN_STD per channel: (x - mean) / (std + 1e-8), stats shaped (3, 1, 1)",
            "crop": "eval: centre crop 76 x 76 of 84 x 84 (top = left = 4)",
            "sampling": "policy.diffusion.conditional_sample(1, global_cond, generator=torch.Generator().manual_seed(1234)); noise captured",
        },
    }
    for separate in (False, True):
        name, r = build(out_dir, separate)
        ref[name] = r
    text = json.dumps(ref, separators=(",", ":")) + "\n"
    (out_dir / "tiny_cams_reference.json").write_text(text)
    back = json.loads(text)
    assert back["tiny_cams_shared"]["global_cond"] == ref["tiny_cams_shared"]["global_cond"]
    for name in ("tiny_cams_shared", "tiny_cams_separate"):
        print(name, "float32 vs float64 conditioning:", ref[name]["global_cond_float32_vs_float64_max_abs"])
    print("ok:", sorted(p.name for p in out_dir.iterdir()))


if __name__ == "__main__":
    main()
