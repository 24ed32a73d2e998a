"""Reference outputs of LeRobot's ACT network for mte-policy's ACT parity test.

Builds a tiny ACT (lerobot==0.4.4, torch; see requirements-lerobot.txt) with state inputs
(`observation.state` 2-D, `observation.environment_state` 16-D, 2-D actions), randomly
initialised from a fixed torch seed, dropout 0 so that training mode is deterministic, and
records:
- `model.safetensors` and `config.json` as LeRobot's `save_pretrained` writes them;
- `io.safetensors`: normalised inputs, the inference actions (latent zero, eval mode), and
  a training-mode pass with the CVAE (target actions with padding, the reparameterisation
  noise fixed by replacing `torch.randn_like`), giving its actions, mu and 2 log sigma.

Usage (from the repository root):
    python3 -m venv /tmp/venv-lerobot
    /tmp/venv-lerobot/bin/pip install -r tools/reference/requirements-lerobot.txt
    /tmp/venv-lerobot/bin/python tools/reference/lerobot_act_reference.py \
        crates/mte-policy/tests/fixtures/act_tiny
"""
import pathlib
import sys

import torch
from safetensors.torch import save_file

from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.act.configuration_act import ACTConfig
from lerobot.policies.act.modeling_act import ACTPolicy

B, CHUNK, LATENT = 3, 10, 4


def main(out: pathlib.Path) -> None:
    torch.manual_seed(0)
    cfg = ACTConfig(
        input_features={
            "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(2,)),
            "observation.environment_state": PolicyFeature(type=FeatureType.ENV, shape=(16,)),
        },
        output_features={"action": PolicyFeature(type=FeatureType.ACTION, shape=(2,))},
        chunk_size=CHUNK, n_action_steps=CHUNK, dim_model=16, n_heads=2, dim_feedforward=32,
        n_encoder_layers=2, n_decoder_layers=1, n_vae_encoder_layers=1, latent_dim=LATENT,
        dropout=0.0, device="cpu",
    )
    policy = ACTPolicy(cfg)
    # Move the biases and embeddings off their initial values so every term matters.
    with torch.no_grad():
        for name, p in policy.named_parameters():
            if p.dim() == 1:
                p.add_(0.1 * torch.randn_like(p))
    out.mkdir(parents=True, exist_ok=True)
    policy.save_pretrained(out)

    state = torch.randn(B, 2)
    env = torch.randn(B, 16)
    policy.eval()
    with torch.no_grad():
        actions = policy.model({"observation.state": state, "observation.environment_state": env})[0]

    target = torch.randn(B, CHUNK, 2)
    is_pad = torch.zeros(B, CHUNK, dtype=torch.bool)
    is_pad[1, 7:] = True  # one window runs past its episode's end
    eps = torch.randn(B, LATENT)
    original = torch.randn_like
    torch.randn_like = lambda t, **kw: eps.clone()
    try:
        policy.train()
        with torch.no_grad():
            train_actions, (mu, log_sigma_x2) = policy.model({
                "observation.state": state,
                "observation.environment_state": env,
                "action": target,
                "action_is_pad": is_pad,
            })
    finally:
        torch.randn_like = original
    save_file(
        {
            "state": state.contiguous(),
            "env": env.contiguous(),
            "actions": actions.contiguous(),
            "target": target.contiguous(),
            "is_pad": is_pad.float().contiguous(),
            "eps": eps.contiguous(),
            "train_actions": train_actions.contiguous(),
            "mu": mu.contiguous(),
            "log_sigma_x2": log_sigma_x2.contiguous(),
        },
        str(out / "io.safetensors"),
    )


if __name__ == "__main__":
    main(pathlib.Path(sys.argv[1]))
