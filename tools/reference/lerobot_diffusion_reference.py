"""Reference fixtures of LeRobot's Diffusion Policy for mte-policy's loader/parity tests.

Uses the REAL lerobot (0.4.4) / diffusers (0.35.2) / torch (2.10.0) code, pinned in
requirements-lerobot-dp.txt, to write into the fixtures folder given as the argument:

  tiny_state/                 a tiny image-free DiffusionPolicy (torch.manual_seed(0) init) saved
                              exactly as a lerobot 0.4.4 training run saves `pretrained_model/`:
                              policy.save_pretrained() -> config.json + model.safetensors, and
                              make_pre_post_processors(cfg, dataset_stats).save_pretrained() ->
                              policy_{pre,post}processor.json + their normaliser safetensors.
  tiny_state_old/             the same weights in the OLD (lerobot < 0.4) layout: config.json +
                              model.safetensors with the normalisation buffers inside, under
                              normalize_inputs.buffer_<feat>.{min,max}, normalize_targets.buffer_action.*,
                              unnormalize_outputs.buffer_action.*.
  tiny_state_reference.json   state-dict keys/shapes, scheduler tables, U-Net parity cases,
                              normalisation + global conditioning, sampling with every noise tensor
                              captured (direct call with a seeded generator, and a 9-step
                              select_action rollout), training loss with captured eps/timesteps.
  resnet_gn_encoder.json      parity data for DiffusionRgbEncoder (resnet18 + GroupNorm, spatial
                              softmax 32 kp, 84x84 centre crop) with formula-generated weights.

Every fixture is re-loaded and re-checked in Python before the script exits (assertions).
Floats are float32 values written as JSON doubles (exact: parse as f64, cast to f32).

Usage (from the repository root):
    python3 -m venv /tmp/venv-lerobot-dp
    /tmp/venv-lerobot-dp/bin/pip install -r tools/reference/requirements-lerobot-dp.txt \
        --extra-index-url https://download.pytorch.org/whl/cpu
    /tmp/venv-lerobot-dp/bin/python tools/reference/lerobot_diffusion_reference.py \
        crates/mte-policy/tests/fixtures/lerobot_dp
"""
import contextlib
import json
import math
import shutil
import sys
from importlib.metadata import version
from pathlib import Path

import numpy as np
import torch

torch.set_num_threads(1)

import diffusers.schedulers.scheduling_ddpm as ddpm_mod  # noqa: E402
from lerobot.configs.types import FeatureType, NormalizationMode, PolicyFeature  # noqa: E402
from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig  # noqa: E402
from lerobot.policies.diffusion.modeling_diffusion import (  # noqa: E402
    DiffusionPolicy,
    DiffusionRgbEncoder,
)
from lerobot.policies.factory import make_pre_post_processors  # noqa: E402
from lerobot.processor import migrate_policy_normalization as migrate  # noqa: E402
from safetensors.torch import load_file, save_file  # noqa: E402

GENERATOR = "tools/reference/lerobot_diffusion_reference.py"
VERSIONS = {p: version(p) for p in ["lerobot", "torch", "diffusers", "numpy", "safetensors", "torchvision"]}

STATE, ENV, ACTION = "observation.state", "observation.environment_state", "action"


def fl(t):
    """float32 tensor -> nested lists of python floats (exact f32 values)."""
    return torch.as_tensor(t).detach().to(torch.float64).tolist()


def shape(t):
    return list(t.shape)


# --------------------------------------------------------------------------------------------
# 1. tiny state-only policy
# --------------------------------------------------------------------------------------------

def tiny_config():
    return DiffusionConfig(
        input_features={
            STATE: PolicyFeature(FeatureType.STATE, (2,)),
            ENV: PolicyFeature(FeatureType.ENV, (16,)),
        },
        output_features={ACTION: PolicyFeature(FeatureType.ACTION, (2,))},
        # ENV must be listed explicitly: DiffusionConfig's default mapping has no ENV entry, which
        # would leave observation.environment_state un-normalised (IDENTITY).
        normalization_mapping={
            "VISUAL": NormalizationMode.MEAN_STD,
            "STATE": NormalizationMode.MIN_MAX,
            "ENV": NormalizationMode.MIN_MAX,
            "ACTION": NormalizationMode.MIN_MAX,
        },
        n_obs_steps=2,
        horizon=16,
        n_action_steps=8,
        down_dims=(8, 16),
        kernel_size=5,
        n_groups=4,
        diffusion_step_embed_dim=8,
        use_film_scale_modulation=True,
        noise_scheduler_type="DDPM",
        num_train_timesteps=100,
        beta_schedule="squaredcos_cap_v2",
        clip_sample=True,
        clip_sample_range=1.0,
        prediction_type="epsilon",
        num_inference_steps=10,
        device="cpu",
        push_to_hub=False,
    )


def made_up_stats():
    """min/max as the brief; the remaining keys mimic what lerobot 0.4.4's compute_stats writes
    (mean, std, count, q01..q99) so a loader is exercised on a realistic stats file. Only min/max
    are used (MIN_MAX everywhere)."""
    raw = {
        STATE: ([13.4, 32.9], [496.1, 510.9]),
        ENV: ([0.0] * 16, [512.0] * 16),
        ACTION: ([12.0, 25.0], [511.0, 511.0]),
    }
    stats = {}
    for key, (mn, mx) in raw.items():
        mn, mx = np.asarray(mn, np.float64), np.asarray(mx, np.float64)
        s = {"min": mn, "max": mx, "mean": (mn + mx) / 2, "std": (mx - mn) / 4,
             "count": np.array([25650])}
        for q in (1, 10, 50, 90, 99):
            s[f"q{q:02d}"] = mn + (q / 100) * (mx - mn)
        stats[key] = {k: torch.as_tensor(v, dtype=torch.float32) if k != "count"
                      else torch.as_tensor(v) for k, v in s.items()}
    return stats


class NoiseRecorder:
    """Records every torch.randn / torch.randint output while active (optionally replays a list).

    LeRobot draws the DDPM prior with `torch.randn(...)` in DiffusionModel.conditional_sample and the
    per-step variance noise with diffusers' `randn_tensor`, which itself calls `torch.randn`; the
    training loss draws eps with `torch.randn` and timesteps with `torch.randint`. Patching the two
    torch functions therefore captures all randomness of both paths; the variance-noise calls are
    additionally tagged by wrapping scheduling_ddpm.randn_tensor."""

    def __init__(self, replay=None):
        self.calls = []  # (kind, tensor)
        self.replay = list(replay) if replay is not None else None
        self._in_sched = False

    @contextlib.contextmanager
    def active(self):
        orig_randn, orig_randint, orig_rt = torch.randn, torch.randint, ddpm_mod.randn_tensor
        rec = self

        def randn(*args, **kwargs):
            out = orig_randn(*args, **kwargs)
            kind = "ddpm_variance_noise" if rec._in_sched else "randn"
            if rec.replay is not None:
                rk, rt = rec.replay.pop(0)
                assert rk == kind and rt.shape == out.shape, (rk, kind, rt.shape, out.shape)
                out = rt.clone()
            rec.calls.append((kind, out.clone()))
            return out

        def randint(*args, **kwargs):
            out = orig_randint(*args, **kwargs)
            if rec.replay is not None:
                rk, rt = rec.replay.pop(0)
                assert rk == "randint" and rt.shape == out.shape
                out = rt.clone()
            rec.calls.append(("randint", out.clone()))
            return out

        def randn_tensor(*args, **kwargs):
            rec._in_sched = True
            try:
                return orig_rt(*args, **kwargs)
            finally:
                rec._in_sched = False

        torch.randn, torch.randint, ddpm_mod.randn_tensor = randn, randint, randn_tensor
        try:
            yield self
        finally:
            torch.randn, torch.randint, ddpm_mod.randn_tensor = orig_randn, orig_randint, orig_rt


def raw_observation(k):
    """Deterministic raw (un-normalised) observation for control step k."""
    state = torch.tensor([100.0 + 30.0 * k, 200.0 + 10.0 * k], dtype=torch.float32)
    i = torch.arange(16, dtype=torch.float64)
    env = (256.0 + 200.0 * torch.sin(0.3 * i + 0.5 * k)).to(torch.float32)
    return state, env


def manual_ddpm_loop(unet, sched, global_cond, init_noise, variance_noises):
    """Plain re-statement of diffusers' DDPMScheduler.step (epsilon, fixed_small, clip) in float32
    driven by the recorded noise. Used only to check that the recorded noise fully determines the
    sample and that the documented formulas are the ones in use."""
    ac = sched.alphas_cumprod  # float32
    ts = [int(t) for t in sched.timesteps]
    x = init_noise.clone()
    it = iter(variance_noises)
    for i, t in enumerate(ts):
        eps = unet(x, torch.full((1,), t, dtype=torch.long), global_cond=global_cond)
        prev_t = ts[i + 1] if i + 1 < len(ts) else -1
        a_t = ac[t]
        a_prev = ac[prev_t] if prev_t >= 0 else torch.tensor(1.0)
        b_t, b_prev = 1 - a_t, 1 - a_prev
        cur_alpha = a_t / a_prev
        cur_beta = 1 - cur_alpha
        x0 = ((x - b_t ** 0.5 * eps) / a_t ** 0.5).clamp(-1.0, 1.0)
        mean = (a_prev ** 0.5 * cur_beta) / b_t * x0 + cur_alpha ** 0.5 * b_prev / b_t * x
        if t > 0:
            var = torch.clamp(b_prev / b_t * cur_beta, min=1e-20)
            mean = mean + var ** 0.5 * next(it)
        x = mean
    return x


def build_tiny(out_dir: Path):
    cfg = tiny_config()
    torch.manual_seed(0)
    policy = DiffusionPolicy(cfg)
    policy.eval()
    stats = made_up_stats()
    pre, post = make_pre_post_processors(cfg, dataset_stats=stats)

    new_dir = out_dir / "tiny_state"
    old_dir = out_dir / "tiny_state_old"
    for d in (new_dir, old_dir):
        if d.exists():
            shutil.rmtree(d)
    policy.save_pretrained(new_dir)
    pre.save_pretrained(new_dir)
    post.save_pretrained(new_dir)

    # ---- old layout: same weights + lerobot<0.4 Normalize/Unnormalize buffers -------------------
    old_dir.mkdir(parents=True)
    shutil.copyfile(new_dir / "config.json", old_dir / "config.json")
    sd = {k: v.detach().clone().contiguous() for k, v in policy.state_dict().items()}
    old_buffers = {}
    for prefix, feats in (("normalize_inputs", [STATE, ENV]), ("normalize_targets", [ACTION]),
                          ("unnormalize_outputs", [ACTION])):
        for feat in feats:
            for s in ("min", "max"):
                old_buffers[f"{prefix}.buffer_{feat.replace('.', '_')}.{s}"] = \
                    stats[feat][s].to(torch.float32).clone().contiguous()
    save_file({**sd, **old_buffers}, str(old_dir / "model.safetensors"), metadata={"format": "pt"})

    ref = {"generator": GENERATOR, "versions": VERSIONS}
    ref["config"] = json.loads((new_dir / "config.json").read_text())
    ref["notes"] = {
        "float_encoding": "all tensors are float32 written as exact JSON doubles; nested lists in C order",
        "global_cond_layout": "per obs step s=0..n_obs_steps-1 (oldest first): [state(2), env_state(16)]; flattened -> 36",
        "unet_cond": "FiLM cond = concat(diffusion_step_encoder(t) (8), global_cond (36)) = 44",
        "final_conv_groupnorm": "unet.final_conv.0 is DiffusionConv1dBlock built WITHOUT n_groups, so its GroupNorm uses 8 groups (not config n_groups=4)",
        "unet_depth": "with down_dims [8,16] only the first down block downsamples (16 -> 8) and the single up block upsamples (ConvTranspose1d k4 s2 p1)",
        "normaliser": "new layout MIN_MAX: 2*(x-min)/d - 1 with d = max-min (d replaced by eps=1e-8 only where max==min); unnormalise (y+1)/2*d + min. Old layout (lerobot<0.4 Normalize): (x-min)/(max-min+1e-8)*2-1 - identical in float32 for these stats",
        "executed_slice": "select_action executes chunk[n_obs_steps-1 : n_obs_steps-1+n_action_steps] = [1, 9)",
    }

    # ---- (a) state-dict keys ----------------------------------------------------------------
    file_sd = load_file(str(new_dir / "model.safetensors"))
    ref["state_dict"] = [{"key": k, "shape": shape(v), "dtype": str(v.dtype).replace("torch.", "")}
                         for k, v in policy.state_dict().items()]
    assert set(file_sd) == set(sd), "model.safetensors keys != state_dict keys"
    ref["state_dict_num_elements"] = int(sum(v.numel() for v in sd.values()))
    old_sd = load_file(str(old_dir / "model.safetensors"))
    ref["old_layout_extra_keys"] = [{"key": k, "shape": shape(old_sd[k])} for k in sorted(old_buffers)]
    ref["processor_files"] = {}
    for f in sorted(new_dir.glob("policy_*processor*.safetensors")):
        st = load_file(str(f))
        ref["processor_files"][f.name] = {k: {"shape": shape(v), "dtype": str(v.dtype).replace("torch.", ""),
                                              "values": fl(v)} for k, v in sorted(st.items())}

    # ---- scheduler tables ----------------------------------------------------------------------
    sched = policy.diffusion.noise_scheduler
    sched.set_timesteps(policy.diffusion.num_inference_steps)
    ref["scheduler"] = {
        "class": type(sched).__name__,
        "config": {k: (v if not isinstance(v, tuple) else list(v)) for k, v in dict(sched.config).items()
                   if not k.startswith("_") and isinstance(v, (int, float, str, bool, type(None), list, tuple))},
        "betas": fl(sched.betas),
        "alphas_cumprod": fl(sched.alphas_cumprod),
        "inference_timesteps": [int(t) for t in sched.timesteps],
    }

    unet = policy.diffusion.unet
    with torch.no_grad():
        # ---- (c) normalisation + global conditioning ------------------------------------------
        (s0, e0), (s1, e1) = raw_observation(0), raw_observation(1)
        normed = []
        for s, e in ((s0, e0), (s1, e1)):
            o = pre({STATE: s.clone(), ENV: e.clone()})
            normed.append((o[STATE], o[ENV]))  # each (1, dim)
        for (ns, ne), (s, e) in zip(normed, ((s0, e0), (s1, e1))):
            ms = 2 * (s - stats[STATE]["min"]) / (stats[STATE]["max"] - stats[STATE]["min"]) - 1
            me = 2 * (e - stats[ENV]["min"]) / (stats[ENV]["max"] - stats[ENV]["min"]) - 1
            assert torch.equal(ns[0], ms) and torch.equal(ne[0], me)
        hist = {STATE: torch.stack([normed[0][0], normed[1][0]], dim=1),  # (1, 2, 2)
                ENV: torch.stack([normed[0][1], normed[1][1]], dim=1)}  # (1, 2, 16)
        gc = policy.diffusion._prepare_global_conditioning(hist)  # (1, 36)
        assert gc.shape == (1, 36)
        assert torch.equal(gc[0], torch.cat([hist[STATE][0, 0], hist[ENV][0, 0], hist[STATE][0, 1], hist[ENV][0, 1]]))
        ref["global_conditioning"] = {
            "raw": {STATE: [fl(s0), fl(s1)], ENV: [fl(e0), fl(e1)]},
            "raw_formula": "step k: state=[100+30k, 200+10k]; env[i]=f32(256+200*sin(0.3*i+0.5*k)) (f64 math, cast)",
            "normalized": {STATE: fl(hist[STATE][0]), ENV: fl(hist[ENV][0])},
            "global_cond": fl(gc[0]),
        }

        # ---- (b) U-Net parity ---------------------------------------------------------------
        cases = []
        g = torch.Generator().manual_seed(11)
        specs = [("built_global_cond_t0", 0, None, 1.0), ("random_cond_t37", 37, 21, 1.0),
                 ("random_cond_t99_x3", 99, 22, 3.0)]
        for name, t, cond_seed, xscale in specs:
            x = torch.randn((1, 16, 2), generator=g) * xscale
            cond = gc if cond_seed is None else torch.randn((1, 36), generator=torch.Generator().manual_seed(cond_seed))
            tt = torch.tensor([t], dtype=torch.long)
            out = unet(x, tt, global_cond=cond)
            temb = unet.diffusion_step_encoder(tt)
            cases.append({"name": name, "x": fl(x[0]), "timestep": t, "global_cond": fl(cond[0]),
                          "timestep_embedding": fl(temb[0]), "output": fl(out[0])})
        # batched case: two items with different timesteps in one call
        xb = torch.randn((2, 16, 2), generator=g)
        cb = torch.randn((2, 36), generator=g)
        tb = torch.tensor([5, 64], dtype=torch.long)
        ob = unet(xb, tb, global_cond=cb)
        for i in range(2):
            oi = unet(xb[i:i + 1], tb[i:i + 1], global_cond=cb[i:i + 1])
            assert torch.allclose(oi[0], ob[i], atol=1e-6)
        ref["unet_cases"] = cases
        ref["unet_batched_case"] = {"x": fl(xb), "timesteps": tb.tolist(), "global_cond": fl(cb), "output": fl(ob)}

        # ---- (d1) direct sampling with a seeded generator ------------------------------------
        steps = []
        orig_step = sched.step

        def traced_step(model_output, timestep, sample, **kw):
            res = orig_step(model_output, timestep, sample, **kw)
            steps.append({"t": int(timestep), "sample_in": fl(sample[0]), "eps": fl(model_output[0]),
                          "pred_original_sample_clipped": fl(res.pred_original_sample[0]),
                          "prev_sample": fl(res.prev_sample[0])})
            return res

        rec = NoiseRecorder()
        sched.step = traced_step
        try:
            with rec.active():
                chunk = policy.diffusion.conditional_sample(1, global_cond=gc, generator=torch.Generator().manual_seed(1234))
        finally:
            del sched.step
        kinds = [k for k, _ in rec.calls]
        assert kinds == ["randn"] + ["ddpm_variance_noise"] * 9, kinds
        init_noise, var_noises = rec.calls[0][1], [t for _, t in rec.calls[1:]]
        # capture check 1: same seed, no patching -> identical
        again = policy.diffusion.conditional_sample(1, global_cond=gc, generator=torch.Generator().manual_seed(1234))
        assert torch.equal(again, chunk)
        # capture check 2: the generator stream is exactly [prior, noise@t=90, ..., noise@t=10]
        gg = torch.Generator().manual_seed(1234)
        assert torch.equal(torch.randn((1, 16, 2), generator=gg), init_noise)
        for vn in var_noises:
            assert torch.equal(torch.randn((1, 16, 2), generator=gg), vn)
        # capture check 3: manual DDPM loop from recorded noise
        manual = manual_ddpm_loop(unet, sched, gc, init_noise, var_noises)
        assert torch.allclose(manual, chunk, atol=1e-6), (manual - chunk).abs().max()
        unnorm = post(chunk.clone())
        d_act = stats[ACTION]["max"] - stats[ACTION]["min"]
        assert torch.equal(unnorm, (chunk + 1) / 2 * d_act + stats[ACTION]["min"])
        ref["sampling_direct"] = {
            "description": "policy.diffusion.conditional_sample(1, global_cond, generator=torch.Generator().manual_seed(1234)) with global_cond from global_conditioning",
            "generator_seed": 1234,
            "global_cond": fl(gc[0]),
            "timesteps": [s["t"] for s in steps],
            "initial_noise": fl(init_noise[0]),
            "variance_noise": [{"t": s["t"], "noise": fl(vn[0])} for s, vn in zip(steps, var_noises)],
            "steps": steps,
            "chunk_normalized": fl(chunk[0]),
            "chunk_unnormalized": fl(unnorm[0]),
            "executed_slice": [1, 9],
            "executed_normalized": fl(chunk[0, 1:9]),
            "executed_unnormalized": fl(unnorm[0, 1:9]),
        }

        # ---- (d2) select_action rollout (global RNG, as lerobot_eval runs it) ----------------
        def rollout(pol, prep, postp, recorder):
            pol.reset()
            samplings, actions = [], []
            orig_cs = pol.diffusion.conditional_sample

            def traced_cs(batch_size, global_cond=None, generator=None, noise=None):
                n0 = len(recorder.calls)
                out = orig_cs(batch_size, global_cond=global_cond, generator=generator, noise=noise)
                calls = recorder.calls[n0:]
                samplings.append({"global_cond": global_cond.clone(), "chunk": out.clone(), "calls": calls})
                return out

            pol.diffusion.conditional_sample = traced_cs
            try:
                with recorder.active():
                    for k in range(9):
                        s, e = raw_observation(k)
                        o = prep({STATE: s, ENV: e})
                        a = pol.select_action(o)
                        actions.append((s, e, a.clone(), postp(a.clone())))
            finally:
                del pol.diffusion.conditional_sample
            return samplings, actions

        torch.manual_seed(777)
        rec2 = NoiseRecorder()
        samplings, actions = rollout(policy, pre, post, rec2)
        assert len(samplings) == 2
        for sidx, smp in enumerate(samplings):
            assert [k for k, _ in smp["calls"]] == ["randn"] + ["ddpm_variance_noise"] * 9
        # expected executed actions: steps 0..7 from chunk 1 [1..8], step 8 from chunk 2 [1]
        for k, (_, _, a, _) in enumerate(actions):
            src = samplings[0]["chunk"][0, 1 + k] if k < 8 else samplings[1]["chunk"][0, 1]
            assert torch.equal(a[0], src)
        # sampling 1 sees [o0, o0] (queue filled with copies), sampling 2 sees [o7, o8]
        n = {k: pre({STATE: raw_observation(k)[0], ENV: raw_observation(k)[1]}) for k in (0, 7, 8)}
        gc1 = torch.cat([n[0][STATE][0], n[0][ENV][0], n[0][STATE][0], n[0][ENV][0]])
        gc2 = torch.cat([n[7][STATE][0], n[7][ENV][0], n[8][STATE][0], n[8][ENV][0]])
        assert torch.equal(samplings[0]["global_cond"][0], gc1)
        assert torch.equal(samplings[1]["global_cond"][0], gc2)
        ref["rollout"] = {
            "description": "policy.reset(); torch.manual_seed(777); for k in 0..8: a_k = postprocessor(policy.select_action(preprocessor(raw_obs(k)))). All torch.randn outputs captured.",
            "global_seed": 777,
            "observations_raw": [{STATE: fl(s), ENV: fl(e)} for s, e, _, _ in actions],
            "samplings": [{
                "at_step": at,
                "obs_steps_used": used,
                "global_cond": fl(smp["global_cond"][0]),
                "initial_noise": fl(smp["calls"][0][1][0]),
                "variance_noise": [fl(t[0]) for _, t in smp["calls"][1:]],
                "chunk_normalized": fl(smp["chunk"][0]),
                "chunk_unnormalized": fl(post(smp["chunk"].clone())[0]),
            } for smp, at, used in zip(samplings, (0, 8), ([0, 0], [7, 8]))],
            "actions_normalized": [fl(a[0]) for _, _, a, _ in actions],
            "actions_unnormalized": [fl(u[0]) for _, _, _, u in actions],
        }

    # ---- (e) training loss ------------------------------------------------------------------
    B = 2
    bg = torch.Generator().manual_seed(5)
    raw_batch = {
        STATE: (torch.rand((B, 2, 2), generator=bg) * 400 + 50),
        ENV: (torch.rand((B, 2, 16), generator=bg) * 512),
        ACTION: (torch.rand((B, 16, 2), generator=bg) * 400 + 50),
        "action_is_pad": torch.zeros((B, 16), dtype=torch.bool),
    }
    raw_batch["action_is_pad"][1, 13:] = True
    nb = pre({k: v.clone() for k, v in raw_batch.items()})
    for k in (STATE, ENV, ACTION):
        mn, mx = stats[k]["min"], stats[k]["max"]
        assert torch.equal(nb[k], 2 * (raw_batch[k] - mn) / (mx - mn) - 1), k
    policy.train()
    torch.manual_seed(4242)
    rec3 = NoiseRecorder()
    with rec3.active():
        loss, _ = policy.forward(dict(nb))
    policy.eval()
    assert [k for k, _ in rec3.calls] == ["randn", "randint"], [k for k, _ in rec3.calls]
    eps, tsteps = rec3.calls[0][1], rec3.calls[1][1]
    with torch.no_grad():
        gc_b = policy.diffusion._prepare_global_conditioning(nb)
        ac = sched.alphas_cumprod
        noisy = ac[tsteps].sqrt()[:, None, None] * nb[ACTION] + (1 - ac[tsteps]).sqrt()[:, None, None] * eps
        noisy_lib = sched.add_noise(nb[ACTION], eps, tsteps)
        assert torch.allclose(noisy, noisy_lib, atol=1e-6)
        pred = unet(noisy_lib, tsteps, global_cond=gc_b)
        manual_loss = ((pred - eps) ** 2).mean()
        assert torch.allclose(manual_loss, loss.detach(), rtol=1e-6, atol=0), (manual_loss, loss)
        masked = (((pred - eps) ** 2) * (~nb["action_is_pad"]).unsqueeze(-1)).mean()
    ref["training_loss"] = {
        "description": "loss = policy.forward(preprocessor(raw_batch)) in train mode after torch.manual_seed(4242); eps = torch.randn(action.shape), timesteps = torch.randint(0, 100, (B,)) captured; loss = mean((unet(sqrt(abar_t)*a + sqrt(1-abar_t)*eps, t, global_cond) - eps)^2) over all B*16*2 elements",
        "do_mask_loss_for_padding": False,
        "raw_batch": {k: (fl(v) if v.dtype != torch.bool else v.tolist()) for k, v in raw_batch.items()},
        "normalized_batch": {k: fl(nb[k]) for k in (STATE, ENV, ACTION)},
        "global_cond": fl(gc_b),
        "eps": fl(eps),
        "timesteps": tsteps.tolist(),
        "noisy_trajectory": fl(noisy_lib),
        "pred": fl(pred),
        "loss": float(loss.detach()),
        "loss_if_padding_masked_mean_over_all": float(masked),
    }

    # ---- reload checks ------------------------------------------------------------------------
    verify_tiny(out_dir, ref, stats)
    return ref


def verify_tiny(out_dir: Path, ref, stats):
    new_dir, old_dir = out_dir / "tiny_state", out_dir / "tiny_state_old"
    with torch.no_grad():
        for d in (new_dir, old_dir):
            pol = DiffusionPolicy.from_pretrained(d)  # old layout: extra normalisation keys ignored (strict=False)
            pol.eval()
            for c in ref["unet_cases"]:
                out = pol.diffusion.unet(torch.tensor([c["x"]]), torch.tensor([c["timestep"]]),
                                         global_cond=torch.tensor([c["global_cond"]]))
                assert torch.equal(out[0], torch.tensor(c["output"])), d
        # new layout: processors reload from the saved files (no stats passed) and normalise identically
        pol = DiffusionPolicy.from_pretrained(new_dir)
        pre, post = make_pre_post_processors(pol.config, pretrained_path=str(new_dir))
        g = ref["global_conditioning"]
        for k in range(2):
            o = pre({STATE: torch.tensor(g["raw"][STATE][k]), ENV: torch.tensor(g["raw"][ENV][k])})
            assert torch.equal(o[STATE][0], torch.tensor(g["normalized"][STATE][k]))
            assert torch.equal(o[ENV][0], torch.tensor(g["normalized"][ENV][k]))
        sd = ref["sampling_direct"]
        assert torch.equal(post(torch.tensor([sd["chunk_normalized"]]))[0], torch.tensor(sd["chunk_unnormalized"]))
        # sampling replay with a differently seeded generator: recorded noise alone decides the result
        rec = NoiseRecorder(replay=[("randn", torch.tensor([sd["initial_noise"]]))] +
                            [("ddpm_variance_noise", torch.tensor([v["noise"]])) for v in sd["variance_noise"]])
        with rec.active():
            ch = pol.diffusion.conditional_sample(1, global_cond=torch.tensor([sd["global_cond"]]),
                                                  generator=torch.Generator().manual_seed(99))
        assert torch.equal(ch[0], torch.tensor(sd["chunk_normalized"]))
        # rollout replay through select_action with a different global seed
        ro = ref["rollout"]
        replay = []
        for smp in ro["samplings"]:
            replay.append(("randn", torch.tensor([smp["initial_noise"]])))
            replay += [("ddpm_variance_noise", torch.tensor([v])) for v in smp["variance_noise"]]
        rec = NoiseRecorder(replay=replay)
        torch.manual_seed(1)
        pol.reset()
        with rec.active():
            for k in range(9):
                s, e = raw_observation(k)
                a = pol.select_action(pre({STATE: s, ENV: e}))
                assert torch.equal(a[0], torch.tensor(ro["actions_normalized"][k]))
                assert torch.equal(post(a)[0], torch.tensor(ro["actions_unnormalized"][k]))
        assert not rec.replay
        # training loss replay
        tl = ref["training_loss"]
        batch = {k: torch.tensor(tl["normalized_batch"][k]) for k in (STATE, ENV, ACTION)}
        batch["action_is_pad"] = torch.tensor(tl["raw_batch"]["action_is_pad"])
        rec = NoiseRecorder(replay=[("randn", torch.tensor(tl["eps"])), ("randint", torch.tensor(tl["timesteps"]))])
        with rec.active():
            loss, _ = pol.forward(batch)
        assert float(loss) == tl["loss"]

    # old layout: lerobot's own migration helpers find the stats and strip them back to the new keys
    old_sd = load_file(str(old_dir / "model.safetensors"))
    new_sd = load_file(str(new_dir / "model.safetensors"))
    stripped = migrate.remove_normalization_layers(old_sd)
    assert set(stripped) == set(new_sd) and all(torch.equal(stripped[k], new_sd[k]) for k in new_sd)
    extracted = migrate.extract_normalization_stats(old_sd)
    # NB: the migration helper maps buffer names back with replace("_", "."), so
    # buffer_observation_environment_state becomes "observation.environment.state" (lossy).
    assert torch.equal(extracted[STATE]["min"], stats[STATE]["min"])
    assert torch.equal(extracted[ACTION]["max"], stats[ACTION]["max"])
    assert "observation.environment.state" in extracted and ENV not in extracted
    ref["old_layout_migration_note"] = (
        "lerobot 0.4.4 processor/migrate_policy_normalization.extract_normalization_stats turns "
        "buffer_observation_environment_state into feature 'observation.environment.state' (it replaces "
        "every '_' by '.'); a loader should map old buffer names by matching key.replace('.', '_') of the "
        "config's feature names instead.")


# --------------------------------------------------------------------------------------------
# 3. ResNet-18-GN encoder with formula weights
# --------------------------------------------------------------------------------------------

def formula_image(which: int) -> torch.Tensor:
    c = torch.arange(3).view(3, 1, 1)
    y = torch.arange(96).view(1, 96, 1)
    x = torch.arange(96).view(1, 1, 96)
    if which == 0:
        n = (7 * x + 13 * y + 101 * c) % 256
    else:
        n = (x * x + 3 * x * y + 31 * c * (y + 1) + 5) % 256
    return n.to(torch.float32) / 255.0  # float32 division


def build_encoder(out_dir: Path):
    cfg = DiffusionConfig(
        input_features={"observation.image": PolicyFeature(FeatureType.VISUAL, (3, 96, 96)),
                        STATE: PolicyFeature(FeatureType.STATE, (2,))},
        output_features={ACTION: PolicyFeature(FeatureType.ACTION, (2,))},
        vision_backbone="resnet18", pretrained_backbone_weights=None, use_group_norm=True,
        crop_shape=(84, 84), crop_is_random=True, spatial_softmax_num_keypoints=32,
        device="cpu", push_to_hub=False)
    torch.manual_seed(0)
    enc = DiffusionRgbEncoder(cfg)
    enc.eval()
    gn_params = set()
    for mname, m in enc.named_modules():
        if isinstance(m, torch.nn.GroupNorm):
            gn_params.add(f"{mname}.weight")
    params = []
    with torch.no_grad():
        for k, (name, p) in enumerate(enc.named_parameters()):
            j = np.arange(p.numel(), dtype=np.float64)
            v = 0.02 * np.sin(0.37 * j + 1.3 * k)
            rule = "v"
            if name in gn_params:
                v = 1.0 + v
                rule = "1+v"
            p.copy_(torch.from_numpy(v.astype(np.float32)).view(p.shape))
            params.append({"index": k, "name": name, "shape": list(p.shape), "rule": rule,
                           "first": fl(p.flatten()[:3]), "sum": float(p.double().sum())})
    groupnorms = [{"module": n, "num_groups": m.num_groups, "num_channels": m.num_channels, "eps": m.eps}
                  for n, m in enc.named_modules() if isinstance(m, torch.nn.GroupNorm)]
    imgs = torch.stack([formula_image(0), formula_image(1)])  # (2, 3, 96, 96)
    with torch.no_grad():
        cropped = enc.center_crop(imgs)
        assert torch.equal(cropped, imgs[:, :, 6:90, 6:90])
        fmap = enc.backbone(cropped)  # (2, 512, 3, 3)
        kp = enc.pool(fmap)  # (2, 32, 2)
        feat = enc(imgs)
        assert torch.equal(feat, torch.relu(enc.out(kp.flatten(1))))
    per_image = []
    for b in range(2):
        f = fmap[b].double()
        per_image.append({
            "image_checksum": {"sum": float(imgs[b].double().sum()), "pixel_c0_y0_x0": float(imgs[b, 0, 0, 0]),
                               "pixel_c2_y50_x17": float(imgs[b, 2, 50, 17]), "pixel_c1_y95_x95": float(imgs[b, 1, 95, 95])},
            "crop_sum": float(cropped[b].double().sum()),
            "feature_map_mean": float(f.mean()),
            "feature_map_std_population": float(f.std(unbiased=False)),
            "feature_map_channel_means": fl(fmap[b].mean(dim=(1, 2))),
            "feature_map_first8_channels": fl(fmap[b, :8]),
            "keypoints": fl(kp[b]),
            "feature": fl(feat[b]),
        })
    # The same encoder in float64 (weights are exact float32 values, images exact float32
    # values): this network is badly conditioned (float32 rounding grows ~30x per layer in
    # layers 3-4), so the port is checked in float64 against these, tightly.
    enc64 = DiffusionRgbEncoder(cfg)
    enc64.load_state_dict(enc.state_dict())
    enc64 = enc64.double().eval()
    with torch.no_grad():
        im64 = imgs.double()
        c64 = enc64.center_crop(im64)
        fmap64 = enc64.backbone(c64)
        kp64 = enc64.pool(fmap64)
        feat64 = enc64(im64)
    float64_ref = [{
        "feature_map_mean": float(fmap64[b].mean()),
        "feature_map_channel_means": [float(v) for v in fmap64[b].mean(dim=(1, 2))],
        "keypoints": [[float(v) for v in row] for row in kp64[b]],
        "feature": [float(v) for v in feat64[b]],
    } for b in range(2)]
    ref = {
        "float64": float64_ref,
        "generator": GENERATOR, "versions": VERSIONS,
        "module": "lerobot.policies.diffusion.modeling_diffusion.DiffusionRgbEncoder (in a policy: prefix 'diffusion.rgb_encoder.')",
        "config": {"vision_backbone": "resnet18", "pretrained_backbone_weights": None, "use_group_norm": True,
                   "image_shape": [3, 96, 96], "crop_shape": [84, 84], "crop_in_eval": "center",
                   "spatial_softmax_num_keypoints": 32, "feature_dim": 64, "mode": "eval"},
        "weight_rule": ("k = index of the tensor in named_parameters() order (0-based); j = flat C-order element "
                        "index; v = 0.02*sin(0.37*j + 1.3*k) computed in float64 (numpy) then cast to float32; "
                        "GroupNorm weights (rule '1+v') get 1.0 + v (added in float64 before the cast); every other "
                        "parameter (conv/linear weights, all biases incl. GroupNorm biases) gets v"),
        "image_rule": {
            "image0": "n = (7*x + 13*y + 101*c) mod 256",
            "image1": "n = (x*x + 3*x*y + 31*c*(y+1) + 5) mod 256",
            "value": "float32(n) / 255 in float32 arithmetic; layout (c, y, x), 3x96x96; batch = [image0, image1]",
        },
        "crop": {"top": 6, "left": 6, "height": 84, "width": 84},
        "parameters": params,
        "buffers": [{"name": n, "shape": list(b.shape)} for n, b in enc.named_buffers()],
        "groupnorms": groupnorms,
        "pos_grid": fl(enc.pool.pos_grid),
        "feature_map_shape": list(fmap.shape[1:]),
        "images": per_image,
    }
    # reload check: a fresh encoder with the same rule reproduces the feature exactly
    torch.manual_seed(123)
    enc2 = DiffusionRgbEncoder(cfg)
    enc2.load_state_dict(enc.state_dict())
    enc2.eval()
    with torch.no_grad():
        assert torch.equal(enc2(imgs), feat)
    assert len(set(fl(feat[0]))) > 8, "degenerate encoder output"
    return ref


def main():
    out_dir = Path(sys.argv[1])
    out_dir.mkdir(parents=True, exist_ok=True)
    tiny = build_tiny(out_dir)
    (out_dir / "tiny_state_reference.json").write_text(json.dumps(tiny, separators=(",", ":")) + "\n")
    enc = build_encoder(out_dir)
    (out_dir / "resnet_gn_encoder.json").write_text(json.dumps(enc, separators=(",", ":")) + "\n")
    # final re-read: JSON parses back to the same floats
    back = json.loads((out_dir / "tiny_state_reference.json").read_text())
    assert back["unet_cases"][0]["output"] == tiny["unet_cases"][0]["output"]
    assert not any(isinstance(x, float) and (math.isnan(x) or math.isinf(x))
                   for x in back["sampling_direct"]["chunk_normalized"][0])
    print("ok:", sorted(p.name for p in out_dir.iterdir()))


if __name__ == "__main__":
    main()
