"""One U-Net forward in PyTorch on the networks of mte's `cpu` presets, at batch 1 and 64: the
peer of `unet_forward` and `unet_forward_batch_64` (cpu-image, cpu-keypoints) in
`crates/mte-policy/benches/unet.rs` (issue 17: "the same for the cpu presets at batch 1 and
batch 64").

The network is LeRobot 0.4.4's `DiffusionConditionalUnet1d` with the presets' configuration
(`bench_pgd_lerobot.config()`: down dims 32/64/128, kernel 5, 8 groups, a 32-wide step
embedding, FiLM scale and bias); the global condition is 2 x 66 wide for the image preset
(32 keypoints' coordinates and the 2-D state, two observation steps) and 2 x 18 for the
keypoint preset (16 keypoint coordinates and the state). Same shapes is checked, not assumed:
each preset's bundled checkpoint is loaded into the module, every parameter by name and shape.
A forward is one call on a noisy chunk `(B, 16, 2)`, one timestep per sample and the
condition, under `torch.no_grad()`, with random inputs (its cost does not depend on them).

    pip install -r tools/reference/requirements-lerobot-dp.txt   # in a virtual environment
    python tools/reference/bench_unet_lerobot.py --threads 1

Timings on stdout (not a fixture); BENCHMARKS.md gives them beside mte's.
"""
import argparse
from pathlib import Path

import torch
from safetensors.torch import load_file

from bench_pgd_lerobot import config, timed
from lerobot.policies.diffusion.modeling_diffusion import DiffusionConditionalUnet1d

ASSETS = Path(__file__).resolve().parents[2] / "assets/policies"
# preset -> (global condition width, bundled checkpoint whose U-Net is loaded)
PRESETS = {
    "cpu-image": (2 * 66, ASSETS / "pusht_image_cpu_v2"),
    "cpu-keypoints": (2 * 18, ASSETS / "pusht_keypoints_cpu_v2"),
}


def unet(preset):
    cond_dim, checkpoint = PRESETS[preset]
    net = DiffusionConditionalUnet1d(config(), global_cond_dim=cond_dim)
    tensors = load_file(checkpoint / "model.safetensors")
    prefix = "diffusion.unet."
    mine = {k[len(prefix) :]: v for k, v in tensors.items() if k.startswith(prefix)}
    net.load_state_dict(mine, strict=True)  # every name and shape, nothing left over
    net.eval()
    return net, cond_dim, len(mine)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--reps", type=int, default=7)
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 64])
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    gen = torch.Generator().manual_seed(0)
    for preset in PRESETS:
        net, cond_dim, n = unet(preset)
        params = sum(p.numel() for p in net.parameters())
        print(f"{preset}: loaded {n} U-Net tensors ({params:,} parameters)")
        for b in args.batches:
            x = torch.randn(b, 16, 2, generator=gen)
            t = torch.full((b,), 50, dtype=torch.long)
            cond = torch.randn(b, cond_dim, generator=gen)

            def forward():
                with torch.no_grad():
                    net(x, t, global_cond=cond)

            med, best = timed(forward, args.reps, max(1, 64 // b))
            print(
                f"{preset} batch {b}: {med * 1e3:.3f} ms per forward (min {best * 1e3:.3f}), "
                f"{med * 1e6 / b:.1f} us per sample, {args.threads} thread(s)"
            )


if __name__ == "__main__":
    main()
