"""LeRobot DiffusionPolicy (PushT image defaults, the `paper` preset's peer) on a CUDA GPU.

The GPU counterpart of the peer's CPU benchmark (bench_diffusion.py beside the peer
facts): the same configuration (LeRobot 0.4.4 DiffusionConfig defaults for PushT, image
variant, ResNet-18 with GroupNorm and no pretrained weights, 100 DDPM steps, crop 84),
randomly initialised, fp32, eval mode. Compared with `MTE_BENCH_DEVICE=cuda cargo bench -p
mte-policy --features cuda --bench unet` (`unet_forward` and `chunk`, preset `paper`) on the
same GPU in the same session.

Measures, each after warm-up, with torch.cuda.synchronize() around every timed call:
  * unet: one U-Net forward at batch 1 (one denoising step).
  * chunk: policy.reset(); policy.select_action(batch) -> one full denoising loop (100
    U-Net evaluations at batch 1) + observation encoding.
  * unet_b64: one U-Net forward at batch 64 (a lockstep batch).

Pinned: requirements-lerobot-dp.txt (lerobot 0.4.4) with the machine's own CUDA torch.
Usage: python bench_diffusion_gpu.py [--reps 20] [--chunk-reps 5] [--json out.json]
"""
import argparse
import json
import statistics
import sys
import time
from importlib.metadata import version

import torch
from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy


def timeit(fn, reps, warmup=3):
    for _ in range(warmup):
        fn()
    torch.cuda.synchronize()
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        torch.cuda.synchronize()
        ts.append(time.perf_counter() - t0)
    return {"min_s": min(ts), "median_s": statistics.median(ts), "reps": reps}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--reps", type=int, default=20)
    ap.add_argument("--chunk-reps", type=int, default=5)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    dev = torch.device("cuda")
    torch.manual_seed(0)
    inp = {
        "observation.state": PolicyFeature(FeatureType.STATE, (2,)),
        "observation.image": PolicyFeature(FeatureType.VISUAL, (3, 96, 96)),
    }
    cfg = DiffusionConfig(
        input_features=inp,
        output_features={"action": PolicyFeature(FeatureType.ACTION, (2,))},
        device="cuda",
        crop_shape=(84, 84),
    )
    policy = DiffusionPolicy(cfg).to(dev).eval()
    d = policy.diffusion
    out = {
        "gpu": torch.cuda.get_device_name(0),
        "versions": {p: version(p) for p in ["lerobot", "torch", "diffusers"]},
        "tf32_matmul": torch.backends.cuda.matmul.allow_tf32,
        "tf32_cudnn": torch.backends.cudnn.allow_tf32,
        "cudnn_benchmark": torch.backends.cudnn.benchmark,
        "num_inference_steps": d.num_inference_steps,
    }
    batch1 = {
        "observation.state": torch.rand(1, 2, device=dev) * 2 - 1,
        "observation.image": torch.rand(1, 3, 96, 96, device=dev),
    }
    with torch.no_grad():
        bb = {
            "observation.state": batch1["observation.state"].unsqueeze(1).repeat(1, 2, 1),
            "observation.images": batch1["observation.image"][:, None, None].repeat(1, 2, 1, 1, 1, 1),
        }
        gc = d._prepare_global_conditioning(bb)
        for b, key in [(1, "unet"), (64, "unet_b64")]:
            sample = torch.randn(b, cfg.horizon, 2, device=dev)
            t = torch.full((b,), 50, dtype=torch.long, device=dev)
            g = gc.repeat(b, 1)
            out[key] = timeit(lambda: d.unet(sample, t, global_cond=g), args.reps)

        def chunk():
            policy.reset()
            a = policy.select_action(dict(batch1))
            assert a.shape == (1, 2)

        out["chunk"] = timeit(chunk, args.chunk_reps, warmup=1)
    print(json.dumps(out), flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
