"""Reference outputs of LeRobot's ACT with a camera, for mte-policy's image-ACT parity test.

Builds a tiny ACT (lerobot==0.4.4, torch 2.10.0, torchvision 0.25.0; see
requirements-lerobot.txt) with `observation.image` (3 x 96 x 96), `observation.state` (2-D)
and 2-D actions: torchvision's ResNet-18 with FrozenBatchNorm2d as LeRobot builds it (no
pretrained weights), its layer4 feature map projected to `dim_model` by a 1x1 convolution,
with LeRobot's 2-D sinusoidal position embedding, and the transformer of width 16.

ResNet-18 has 11.2 M parameters, too many for a fixture, so its tensors (every
`model.backbone.*` parameter and FrozenBatchNorm2d buffer) are set by a formula that the
Rust test evaluates too, and only the rest of the network (a few kB) is saved:

    k = index of the tensor in the sorted list of backbone state-dict names (0-based),
    j = flat C-order element index, s = sin(0.37 j + 1.3 k) in float64, then cast to float32:
    conv weights (4-D):      s * sqrt(2) * sqrt(2 / fan_in)   (He scale: s has RMS 1/sqrt(2))
    norm `weight`:           1 + 0.1 s
    norm `bias`:             0.1 s
    norm `running_mean`:     0.1 s
    norm `running_var`:      1 + 0.5 s^2

The transformer's parameters come from torch's initialisation under seed 0, with the 1-D
ones moved off their initial values as in lerobot_act_reference.py.

Records, in the output directory:
- `config.json` as LeRobot's `save_pretrained` writes it;
- `model.safetensors`: every weight but the backbone's;
- `io.safetensors`: the images (B = 2, values in [0, 1], as the network sees them after
  normalisation is skipped: the test feeds them directly), the state, the inference actions
  (eval mode, latent zero) in float32 and in float64 (the same weights in double precision),
  and the layer4 feature map of image 0 in float32.

Usage (from the repository root):
    python3 -m venv /tmp/venv-lerobot
    /tmp/venv-lerobot/bin/pip install -r tools/reference/requirements-lerobot.txt
    /tmp/venv-lerobot/bin/python tools/reference/lerobot_act_image_reference.py \
        crates/mte-policy/tests/fixtures/act_tiny_image
"""
import math
import pathlib
import sys

import numpy as np
import torch
from safetensors.torch import save_file

from lerobot.configs.types import FeatureType, PolicyFeature
from lerobot.policies.act.configuration_act import ACTConfig
from lerobot.policies.act.modeling_act import ACTPolicy

B, CHUNK, LATENT, SIDE = 2, 6, 4, 96


def formula_image(which: int) -> torch.Tensor:
    c = torch.arange(3).view(3, 1, 1)
    y = torch.arange(SIDE).view(1, SIDE, 1)
    x = torch.arange(SIDE).view(1, 1, SIDE)
    if which == 0:
        n = (7 * x + 13 * y + 101 * c) % 256
    else:
        n = (x * x + 3 * x * y + 31 * c * (y + 1) + 5) % 256
    return n.to(torch.float32) / 255.0


def backbone_value(name: str, shape, k: int) -> torch.Tensor:
    j = np.arange(int(np.prod(shape)), dtype=np.float64)
    s = np.sin(0.37 * j + 1.3 * k)
    leaf = name.rsplit(".", 1)[1]
    if len(shape) == 4:
        fan_in = shape[1] * shape[2] * shape[3]
        v = s * math.sqrt(2.0) * math.sqrt(2.0 / fan_in)
    elif leaf == "weight":
        v = 1.0 + 0.1 * s
    elif leaf in ("bias", "running_mean"):
        v = 0.1 * s
    elif leaf == "running_var":
        v = 1.0 + 0.5 * s * s
    else:
        raise ValueError(f"unexpected backbone tensor {name}")
    return torch.from_numpy(v.astype(np.float32)).view(*shape)


def main(out: pathlib.Path) -> None:
    torch.manual_seed(0)
    cfg = ACTConfig(
        input_features={
            "observation.image": PolicyFeature(type=FeatureType.VISUAL, shape=(3, SIDE, SIDE)),
            "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(2,)),
        },
        output_features={"action": PolicyFeature(type=FeatureType.ACTION, shape=(2,))},
        chunk_size=CHUNK, n_action_steps=CHUNK, dim_model=16, n_heads=2, dim_feedforward=32,
        n_encoder_layers=2, n_decoder_layers=1, n_vae_encoder_layers=1, latent_dim=LATENT,
        dropout=0.0, pretrained_backbone_weights=None, device="cpu",
    )
    policy = ACTPolicy(cfg)
    model = policy.model
    with torch.no_grad():
        for name, p in model.named_parameters():
            if p.dim() == 1 and not name.startswith("backbone."):
                p.add_(0.1 * torch.randn_like(p))
        sd = model.backbone.state_dict()
        names = sorted(sd)
        for k, name in enumerate(names):
            sd[name].copy_(backbone_value(name, tuple(sd[name].shape), k))
    assert all(n.endswith(("weight", "bias", "running_mean", "running_var")) for n in names)
    out.mkdir(parents=True, exist_ok=True)
    policy.save_pretrained(out)
    # Keep only the non-backbone weights (the test rebuilds the backbone from the formula).
    from safetensors.torch import load_file

    full = load_file(str(out / "model.safetensors"))
    kept = {k: v for k, v in full.items() if not k.startswith("model.backbone.")}
    assert len(kept) < len(full)
    save_file(kept, str(out / "model.safetensors"), metadata={"format": "pt"})

    images = torch.stack([formula_image(0), formula_image(1)])
    state = torch.randn(B, 2)
    policy.eval()
    with torch.no_grad():
        actions = model({"observation.state": state, "observation.images": [images]})[0]
        fmap = model.backbone(images[:1])["feature_map"]
        # LeRobot makes the zero latent in float32 whatever the model's precision: for the
        # double-precision pass, torch.zeros is briefly made to honour it.
        m64 = model.double()
        zeros = torch.zeros
        torch.zeros = lambda *a, dtype=None, **kw: zeros(
            *a, dtype=torch.float64 if dtype == torch.float32 else dtype, **kw)
        try:
            actions64 = m64({"observation.state": state.double(),
                             "observation.images": [images.double()]})[0]
        finally:
            torch.zeros = zeros
        model.float()
    gap = (actions.double() - actions64).abs().max().item()
    print(f"float32 vs float64 actions: max gap {gap:.3e}; |actions| max {actions.abs().max():.3f}; "
          f"feature map {tuple(fmap.shape)}, RMS {fmap.pow(2).mean().sqrt():.3f}")
    save_file(
        {
            "images": images.contiguous(),
            "state": state.contiguous(),
            "actions": actions.contiguous(),
            "actions_f64": actions64.contiguous(),
            "feature_map0": fmap.contiguous(),
        },
        str(out / "io.safetensors"),
    )


if __name__ == "__main__":
    main(pathlib.Path(sys.argv[1]))
