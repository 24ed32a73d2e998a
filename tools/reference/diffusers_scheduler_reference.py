"""Golden outputs of diffusers' DDPMScheduler / DDIMScheduler for mte-policy's scheduler tests.

Drives the real `diffusers` schedulers (diffusers==0.35.2, torch, numpy; see
requirements-diffusers.txt) on the CPU in float32 and records, per scheduler configuration:
the `betas` and `alphas_cumprod` tables, `set_timesteps(n)` for a few n, single `step()` calls
at fixed timesteps with fixed model_output / sample / noise vectors, and `add_noise()` for a
few timesteps. Every configuration is written in the exact serde layout of
`mte_policy::scheduler::SchedulerConfig`, so the Rust test deserialises it directly.

Noise is explicit everywhere:
- DDIM: `step(..., eta=eta, variance_noise=noise)` (diffusers' own argument).
- DDPM: `step()` draws its variance noise with `randn_tensor(shape, generator=...)`; we
  monkeypatch `diffusers.schedulers.scheduling_ddpm.randn_tensor` to return our noise vector,
  count the calls (exactly one per step with t > 0, none at t == 0), and check once that the
  patch is equivalent to the real generator path (same noise drawn from a seeded
  `torch.Generator` gives bit-identical prev_sample).

Vectors: numpy `RandomState(0)` standard normals cast to float32, shape (1, 16, 2) (LeRobot's
(batch, horizon, action_dim) for PushT); the flattened values are stored in the fixture so the
Rust test does not depend on numpy's generator. Floats are written with `json.dumps`, i.e.
Python `repr` of the float64 widening of each float32 value, which round-trips exactly.

`chains` replays whole sampling loops (see CHAINS) so the Rust test covers the timestep
sequence and the step-to-step hand-off, not only isolated steps.

Usage (from the repository root):
    python3 -m venv /tmp/venv-diffusers
    /tmp/venv-diffusers/bin/pip install --extra-index-url https://download.pytorch.org/whl/cpu \
        -r tools/reference/requirements-diffusers.txt
    /tmp/venv-diffusers/bin/python tools/reference/diffusers_scheduler_reference.py \
        > crates/mte-policy/tests/fixtures/diffusers_schedulers.json
"""
import json
import sys
from importlib.metadata import version

import numpy as np
import torch
import diffusers.schedulers.scheduling_ddpm as ddpm_module
from diffusers import DDIMScheduler, DDPMScheduler

SHAPE = (1, 16, 2)
TIMESTEP_COUNTS = [1, 7, 10, 30, 100]


def base_config(**over):
    """A config in mte's serde layout; defaults = LeRobot's PushT DDPM scheduler."""
    cfg = {
        "kind": "ddpm",
        "num_train_timesteps": 100,
        "beta_start": 0.0001,
        "beta_end": 0.02,
        "beta_schedule": "squaredcos_cap_v2",
        "prediction_type": "epsilon",
        "clip_sample": True,
        "clip_sample_range": 1.0,
        "set_alpha_to_one": True,
        "eta": 0.0,
    }
    cfg.update(over)
    return cfg


# (name, config, [(num_inference_steps, [t...])], add_noise timesteps, store tables?)
CASES = [
    # LeRobot diffusion_pusht: DDPM, exactly the kwargs `_make_noise_scheduler` passes.
    ("pusht_ddpm", base_config(),
     [(100, [99, 98, 50, 1, 0]), (10, [90, 50, 10, 0])], [0, 1, 50, 98, 99]),
    # Same kwargs with noise_scheduler_type = "DDIM" (diffusers defaults: set_alpha_to_one
    # True, steps_offset 0, leading spacing); LeRobot never passes eta, so 0.
    ("pusht_ddim_eta0", base_config(kind="ddim"),
     [(10, [90, 95, 50, 10, 0]), (100, [99, 1, 0])], []),
    ("pusht_ddim_eta1", base_config(kind="ddim", eta=1.0),
     [(10, [90, 50, 10, 0]), (100, [99, 1, 0])], []),
    ("ddim_no_final_alpha_eta05", base_config(kind="ddim", set_alpha_to_one=False, eta=0.5),
     [(10, [90, 10, 0])], []),
    # Plain linear schedule (diffusers' default family), same N and beta range as PushT.
    ("linear_ddpm", base_config(beta_schedule="linear"),
     [(100, [99, 50, 1, 0]), (10, [90, 0])], [0, 50, 99]),
    # Diffusers' default N = 1000 linear, and the latent-diffusion scaled_linear schedule.
    ("linear_ddpm_1000", base_config(beta_schedule="linear", num_train_timesteps=1000),
     [(50, [980, 500, 0])], [999]),
    ("scaled_linear_ddim_1000",
     base_config(kind="ddim", beta_schedule="scaled_linear", num_train_timesteps=1000,
                 beta_start=0.00085, beta_end=0.012, clip_sample=False),
     [(50, [980, 500, 0])], [999]),
    # Sample prediction, with and without clipping, other clip range.
    ("sample_ddpm_clip05", base_config(prediction_type="sample", clip_sample_range=0.5),
     [(100, [99, 50, 0]), (10, [50, 0])], []),
    ("sample_ddim_noclip_eta05",
     base_config(kind="ddim", prediction_type="sample", clip_sample=False, eta=0.5),
     [(10, [90, 50, 0])], []),
    ("epsilon_ddpm_noclip", base_config(clip_sample=False),
     [(100, [99, 50, 1]), (10, [90, 10])], []),
]


# Whole sampling loops: (case name, num_inference_steps). The "model" is the fixed linear map
# model_output = 0.5 * x + 0.1 * vectors.model_output, and step k (0-based) uses
# noise = roll(vectors.noise, k) (flattened), so the Rust test can replay the loop exactly.
CHAINS = [("pusht_ddpm", 100), ("pusht_ddpm", 10), ("pusht_ddim_eta0", 10),
          ("pusht_ddim_eta1", 10), ("linear_ddpm", 100)]


def make_scheduler(cfg):
    kwargs = dict(
        num_train_timesteps=cfg["num_train_timesteps"],
        beta_start=cfg["beta_start"],
        beta_end=cfg["beta_end"],
        beta_schedule=cfg["beta_schedule"],
        clip_sample=cfg["clip_sample"],
        clip_sample_range=cfg["clip_sample_range"],
        prediction_type=cfg["prediction_type"],
    )
    if cfg["kind"] == "ddpm":
        return DDPMScheduler(**kwargs)
    return DDIMScheduler(set_alpha_to_one=cfg["set_alpha_to_one"], **kwargs)


class PatchedNoise:
    """Replaces scheduling_ddpm.randn_tensor; returns a fixed tensor and counts calls."""

    def __init__(self, noise):
        self.noise = noise
        self.calls = 0

    def __call__(self, shape, generator=None, device=None, dtype=None, layout=None):
        assert tuple(shape) == tuple(self.noise.shape), shape
        assert dtype == torch.float32, dtype
        self.calls += 1
        return self.noise.clone()


def ddpm_step(sched, model_output, t, sample, noise):
    original = ddpm_module.randn_tensor
    patch = PatchedNoise(noise)
    ddpm_module.randn_tensor = patch
    try:
        out = sched.step(model_output, t, sample)
    finally:
        ddpm_module.randn_tensor = original
    assert patch.calls == (1 if t > 0 else 0), (t, patch.calls)
    return out


def check_patch_matches_generator(model_output, sample):
    """The monkeypatched path equals diffusers' real generator path bit for bit."""
    sched = make_scheduler(base_config())
    sched.set_timesteps(100)
    real = sched.step(model_output, 50, sample,
                      generator=torch.Generator().manual_seed(1234)).prev_sample
    drawn = torch.randn(SHAPE, generator=torch.Generator().manual_seed(1234),
                        dtype=torch.float32)
    patched = ddpm_step(sched, model_output, 50, sample, drawn).prev_sample
    assert torch.equal(real, patched)
    # and the noise really matters at t = 50
    zero = ddpm_step(sched, model_output, 50, sample, torch.zeros(SHAPE)).prev_sample
    assert not torch.equal(real, zero)


def run_chain(cfg, n, vecs):
    sched = make_scheduler(cfg)
    sched.set_timesteps(n)
    x = torch.from_numpy(vecs["sample"].copy())
    mo = torch.from_numpy(vecs["model_output"].copy())
    for k, t in enumerate(sched.timesteps.tolist()):
        eps = 0.5 * x + 0.1 * mo
        noise = torch.from_numpy(np.roll(vecs["noise"].reshape(-1), k).reshape(SHAPE).copy())
        if cfg["kind"] == "ddpm":
            x = ddpm_step(sched, eps, t, x, noise).prev_sample
        else:
            kw = {"variance_noise": noise} if cfg["eta"] > 0 else {}
            x = sched.step(eps, t, x, eta=cfg["eta"], **kw).prev_sample
    assert x.dtype == torch.float32
    return x


def flat(x):
    return [float(v) for v in x.reshape(-1).tolist()]


def dumps(value, indent=""):
    """JSON with one line per list of scalars (small, diff-friendly); floats via repr."""
    inner = indent + " "
    if isinstance(value, dict):
        items = [f"{inner}{json.dumps(k)}: {dumps(v, inner)}" for k, v in value.items()]
        return "{\n" + ",\n".join(items) + "\n" + indent + "}"
    if isinstance(value, list) and any(isinstance(v, (dict, list)) for v in value):
        return "[\n" + ",\n".join(inner + dumps(v, inner) for v in value) + "\n" + indent + "]"
    return json.dumps(value, separators=(",", ":"), allow_nan=False)


def main():
    torch.set_num_threads(1)
    rng = np.random.RandomState(0)
    vecs = {name: rng.standard_normal(SHAPE).astype(np.float32)
            for name in ["model_output", "sample", "noise", "x0"]}
    # Keep x0 mostly inside [-1, 1] like normalised actions.
    vecs["x0"] = np.clip(vecs["x0"] * np.float32(0.5), -1, 1).astype(np.float32)
    t_vecs = {k: torch.from_numpy(v.copy()) for k, v in vecs.items()}
    check_patch_matches_generator(t_vecs["model_output"], t_vecs["sample"])

    out = {
        "generator": "tools/reference/diffusers_scheduler_reference.py",
        "versions": {p: version(p) for p in ["diffusers", "torch", "numpy"]},
        "shape": list(SHAPE),
        "vectors": {k: flat(v) for k, v in vecs.items()},
        "cases": [],
    }
    seen_tables = {}
    for name, cfg, step_plan, noise_ts in CASES:
        sched = make_scheduler(cfg)
        assert sched.betas.dtype == torch.float32
        assert sched.alphas_cumprod.dtype == torch.float32
        table_key = (cfg["beta_schedule"], cfg["num_train_timesteps"], cfg["beta_start"],
                     cfg["beta_end"])
        case = {"name": name, "config": cfg}
        # Tables are stored once per distinct schedule (the file must stay small); later
        # cases with the same schedule store null and the test checks them against the first.
        if table_key in seen_tables:
            assert torch.equal(seen_tables[table_key][0], sched.betas)
            assert torch.equal(seen_tables[table_key][1], sched.alphas_cumprod)
            case["betas"] = None
            case["alphas_cumprod"] = None
        else:
            seen_tables[table_key] = (sched.betas.clone(), sched.alphas_cumprod.clone())
            case["betas"] = flat(sched.betas)
            case["alphas_cumprod"] = flat(sched.alphas_cumprod)
        case.update({
            "timesteps": [],
            "steps": [],
            "add_noise": [],
        })
        for n in TIMESTEP_COUNTS:
            if n > cfg["num_train_timesteps"]:
                continue
            sched.set_timesteps(n)
            case["timesteps"].append(
                {"num_inference_steps": n, "timesteps": [int(t) for t in sched.timesteps]})
        for n, ts in step_plan:
            sched.set_timesteps(n)
            for t in ts:
                if cfg["kind"] == "ddpm":
                    res = ddpm_step(sched, t_vecs["model_output"], t, t_vecs["sample"],
                                    t_vecs["noise"])
                else:
                    kw = {}
                    if cfg["eta"] > 0:
                        kw["variance_noise"] = t_vecs["noise"]
                    res = sched.step(t_vecs["model_output"], t, t_vecs["sample"],
                                     eta=cfg["eta"], **kw)
                assert res.prev_sample.dtype == torch.float32
                case["steps"].append({
                    "num_inference_steps": n,
                    "t": t,
                    "prev_sample": flat(res.prev_sample),
                })
        for t in noise_ts:
            noisy = sched.add_noise(t_vecs["x0"], t_vecs["noise"], torch.tensor([t]))
            assert noisy.dtype == torch.float32
            case["add_noise"].append({"t": t, "out": flat(noisy)})
        out["cases"].append(case)
    configs = {name: cfg for name, cfg, _, _ in CASES}
    out["chains"] = [
        {"case": name, "num_inference_steps": n,
         "final_sample": flat(run_chain(configs[name], n, vecs))}
        for name, n in CHAINS
    ]
    sys.stdout.write(dumps(out) + "\n")


if __name__ == "__main__":
    main()
