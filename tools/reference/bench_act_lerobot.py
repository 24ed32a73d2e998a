"""LeRobot 0.4.4's ACT on the CPU, for the side-by-side figures of `benches/act.rs`: one
chunk at batch 1 (eval mode) and one training step at batch 8 (CVAE path, AdamW), for the
`paper` (LeRobot's defaults) and `cpu` (width 128, 4 heads, feed-forward 512, 2 + 2 encoder
layers, latent 16) configurations on PushT keypoints, random init. Median of `--reps`.

    /tmp/venv-lerobot/bin/python tools/reference/bench_act_lerobot.py --threads 1
"""
import argparse
import statistics

import torch

from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.act.configuration_act import ACTConfig
from lerobot.policies.act.modeling_act import ACTPolicy
from timing import per_rep

PRESETS = {
    "paper": {},
    "cpu": dict(dim_model=128, n_heads=4, dim_feedforward=512, n_encoder_layers=2,
                n_vae_encoder_layers=2, latent_dim=16),
}


def make(preset):
    cfg = ACTConfig(
        input_features={
            "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(2,)),
            "observation.environment_state": PolicyFeature(type=FeatureType.ENV, shape=(16,)),
        },
        output_features={"action": PolicyFeature(type=FeatureType.ACTION, shape=(2,))},
        device="cpu", **PRESETS[preset],
    )
    return ACTPolicy(cfg), cfg


def timed(fn, reps, inner):
    return statistics.median(per_rep(fn, reps, inner))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--reps", type=int, default=5)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    for preset in ["paper", "cpu"]:
        policy, cfg = make(preset)
        policy.eval()
        obs = {"observation.state": torch.zeros(1, 2), "observation.environment_state": torch.zeros(1, 16)}
        with torch.no_grad():
            chunk = timed(lambda: policy.model(obs), args.reps, 10)
        policy.train()
        b = 8
        batch = {
            "observation.state": torch.zeros(b, 2),
            "observation.environment_state": torch.zeros(b, 16),
            "action": torch.zeros(b, cfg.chunk_size, 2),
            "action_is_pad": torch.zeros(b, cfg.chunk_size, dtype=torch.bool),
        }
        opt = torch.optim.AdamW(policy.parameters(), lr=cfg.optimizer_lr)

        def step():
            opt.zero_grad()
            loss, _ = policy.forward(batch)
            loss.backward()
            opt.step()

        train = timed(step, args.reps, 3)
        print(f"{preset}: chunk {chunk * 1e3:.2f} ms, train step (batch 8) {train * 1e3:.1f} ms")


if __name__ == "__main__":
    main()
