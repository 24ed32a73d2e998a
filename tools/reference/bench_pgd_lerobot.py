"""One pixel-PGD iteration in PyTorch on the network of mte's `cpu` image preset, the peer of
`pgd_iteration` and `pgd_iteration_batch_16` (cpu-image) in `crates/mte-policy/benches/unet.rs`.

The iteration is the one `mte_policy::diffusion::attack` runs (protocol section 4): from the
attacked query's two 96 x 96 frames in [0, 1] (a leaf that needs its gradient), mean-std
normalisation, the evaluation centre crop to 84 x 84, the image encoder on each frame, the
global condition (features and state of both steps), the query's condition repeated for 4
diffusion timesteps, forward noising of the clean chunk, LeRobot's conditional U-Net, the
noise-prediction MSE per query, backward to the pixels, a sign step and the projection onto
the eps ball and [0, 1].

The network is LeRobot 0.4.4's: its `DiffusionConditionalUnet1d` and `SpatialSoftmax` with
the preset's configuration, and a ResNet-18 of a quarter of torchvision's width (16, 32, 64,
128 channels) with GroupNorm, which LeRobot's configuration cannot express and which this
script builds with LeRobot's module names. Same shapes is checked, not assumed: with
`--checkpoint` the script loads an mte checkpoint (default: the bundled image policy)
into these modules: every parameter's name and shape must match.

    pip install -r tools/reference/requirements-lerobot-dp.txt   # in a virtual environment
    python tools/reference/bench_pgd_lerobot.py --threads 1

Timings on stdout (not a fixture); BENCHMARKS.md gives them beside mte's.
"""
import argparse
import statistics
from pathlib import Path

import torch
import torch.nn.functional as F
from diffusers.schedulers.scheduling_ddpm import DDPMScheduler
from safetensors.torch import load_file
from torch import nn

from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
from lerobot.policies.diffusion.modeling_diffusion import (
    DiffusionConditionalUnet1d,
    SpatialSoftmax,
)
from timing import per_rep

WIDTH = 16  # mte's `vision_backbone_width` of the cpu image preset
KEYPOINTS = 32
SAMPLES = 4  # diffusion timesteps per PGD iteration (mte's PgdConfig default)
EPS, STEP = 0.1, 0.00625  # the calibrated pixel burst (sweeps/pixel_pgd_eps.toml)


def norm(c):
    return nn.GroupNorm(c // 16, c)


class Block(nn.Module):
    """torchvision's BasicBlock with GroupNorm (LeRobot replaces every BatchNorm)."""

    def __init__(self, cin, cout, stride):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride, 1, bias=False)
        self.bn1 = norm(cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, 1, 1, bias=False)
        self.bn2 = norm(cout)
        self.downsample = None
        if stride != 1 or cin != cout:
            self.downsample = nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), norm(cout))

    def forward(self, x):
        y = F.relu(self.bn1(self.conv1(x)))
        y = self.bn2(self.conv2(y))
        skip = x if self.downsample is None else self.downsample(x)
        return F.relu(y + skip)


def backbone(w):
    stages = []
    cin = w
    for i, c in enumerate([w, 2 * w, 4 * w, 8 * w]):
        stride = 1 if i == 0 else 2
        stages.append(nn.Sequential(Block(cin, c, stride), Block(c, c, 1)))
        cin = c
    return nn.Sequential(
        nn.Conv2d(3, w, 7, 2, 3, bias=False), norm(w), nn.ReLU(), nn.MaxPool2d(3, 2, 1), *stages
    )


class Encoder(nn.Module):
    """LeRobot's DiffusionRgbEncoder layout: backbone, spatial softmax, linear, ReLU."""

    def __init__(self):
        super().__init__()
        self.backbone = backbone(WIDTH)
        with torch.no_grad():
            shape = self.backbone(torch.zeros(1, 3, 84, 84)).shape[1:]
        self.pool = SpatialSoftmax(tuple(shape), num_kp=KEYPOINTS)
        self.out = nn.Linear(2 * KEYPOINTS, 2 * KEYPOINTS)

    def forward(self, x):
        x = torch.flatten(self.pool(self.backbone(x)), start_dim=1)
        return F.relu(self.out(x))


def config():
    return DiffusionConfig(
        input_features={
            "observation.image": PolicyFeature(type=FeatureType.VISUAL, shape=(3, 96, 96)),
            "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(2,)),
        },
        output_features={"action": PolicyFeature(type=FeatureType.ACTION, shape=(2,))},
        down_dims=(32, 64, 128),
        kernel_size=5,
        n_groups=8,
        diffusion_step_embed_dim=32,
        use_film_scale_modulation=True,
        num_train_timesteps=100,
        crop_shape=(84, 84),
        spatial_softmax_num_keypoints=KEYPOINTS,
        pretrained_backbone_weights=None,
        use_group_norm=True,
        device="cpu",
    )


class Network(nn.Module):
    def __init__(self, cfg):
        super().__init__()
        self.rgb_encoder = Encoder()
        self.unet = DiffusionConditionalUnet1d(cfg, global_cond_dim=(2 * KEYPOINTS + 2) * 2)


def pgd_iteration(net, sched, x, base, state, x0, gen):
    """One iteration for the batch of queries `x (B, 2, 3, 96, 96)`; returns the new `x`."""
    b = x.shape[0]
    x = x.detach().requires_grad_(True)
    img = (x - 0.5) / 0.25
    img = img[..., 6:90, 6:90].reshape(b * 2, 3, 84, 84)
    feat = net.rgb_encoder(img).reshape(b, 2, -1)
    cond = torch.cat([feat, state], dim=-1).flatten(1).repeat_interleave(SAMPLES, 0)
    target = x0.repeat_interleave(SAMPLES, 0)
    t = torch.randint(0, 100, (b * SAMPLES,), generator=gen)
    noise = torch.randn(target.shape, generator=gen)
    pred = net.unet(sched.add_noise(target, noise, t), t, global_cond=cond)
    loss = F.mse_loss(pred, noise, reduction="none").reshape(b, -1).mean(1)
    (grad,) = torch.autograd.grad(loss.sum(), x)
    with torch.no_grad():
        x = x + STEP * grad.sign()
        return torch.minimum(torch.maximum(x, base - EPS), base + EPS).clamp(0.0, 1.0)


def timed(fn, reps, inner):
    out = per_rep(fn, reps, inner)
    return statistics.median(out), min(out)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument(
        "--checkpoint",
        default=str(Path(__file__).resolve().parents[2] / "assets/policies/pusht_image_cpu_v2"),
        help="an mte image checkpoint loaded into the modules (shape check); '' skips",
    )
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    net = Network(config())
    if args.checkpoint:
        tensors = load_file(Path(args.checkpoint) / "model.safetensors")
        mine = {k[len("diffusion.") :]: v for k, v in tensors.items() if k.startswith("diffusion.")}
        # Every parameter must be there with its shape; only the spatial softmax's fixed
        # coordinate grid (a buffer, not learned) is not stored in mte's checkpoints.
        missing, unexpected = net.load_state_dict(mine, strict=False)
        buffers = {name for name, _ in net.named_buffers()}
        assert not unexpected and set(missing) <= buffers, (missing, unexpected)
        # Named relative to the repository (no machine's path in a committed output).
        root = Path(__file__).resolve().parents[2]
        shown = Path(args.checkpoint).resolve()
        shown = shown.relative_to(root) if shown.is_relative_to(root) else shown.name
        print(f"loaded {len(mine)} tensors of {shown} (every parameter, same names and shapes)")
    print(f"parameters: {sum(p.numel() for p in net.parameters()):,}")
    for p in net.parameters():
        p.requires_grad_(False)
    sched = DDPMScheduler(num_train_timesteps=100, beta_schedule="squaredcos_cap_v2")
    gen = torch.Generator().manual_seed(0)
    for b in [1, 16]:
        base = torch.rand(b, 2, 3, 96, 96, generator=gen)
        state = torch.rand(b, 2, 2, generator=gen)
        x0 = torch.randn(b, 16, 2, generator=gen) * 0.5
        x = [base.clone()]

        def step():
            x[0] = pgd_iteration(net, sched, x[0], base, state, x0, gen)

        med, best = timed(step, args.reps, 3)
        print(
            f"batch {b}: {med * 1e3:.2f} ms per iteration (min {best * 1e3:.2f}), "
            f"{med * 1e3 / b:.2f} ms per attacked query, {args.threads} thread(s)"
        )


if __name__ == "__main__":
    main()
