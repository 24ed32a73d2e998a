"""Reference outputs of the Diffusion Transformer's noise network, built from PyTorch's own
modules as Diffusion Policy's `TransformerForDiffusion` assembles them, for mte-policy's
parity test (`tests/dit_parity.rs`).

Diffusion Policy is not a pip package, so this script assembles the same structure from
torch (torch==2.10.0, see requirements-lerobot.txt): `nn.Linear` action and observation
embeddings, learned position embeddings, the sinusoidal time embedding, the MLP condition
encoder (Linear 4x, Mish, Linear), `nn.TransformerDecoder` of `nn.TransformerDecoderLayer`
(`norm_first=True`, GELU, feed-forward 4x, `batch_first=True`) with the causal target mask
and the memory mask `t >= s - 1`, a final LayerNorm and a linear head; state-dict names
follow Diffusion Policy's. Tiny sizes (width 16, 2 heads, 2 layers, horizon 6, 2
observation steps of 5 features, 2-D actions), eval mode, random init from a fixed seed with
every 1-D parameter and the position embeddings moved off their initial values.

    /tmp/venv-lerobot/bin/python tools/reference/dit_reference.py \
        crates/mte-policy/tests/fixtures/dit_tiny.safetensors
"""
import math
import sys

import torch
from safetensors.torch import save_file
from torch import nn

E, HEADS, LAYERS, T, TO, F, A, B = 16, 2, 2, 6, 2, 5, 2, 3


class Tiny(nn.Module):
    def __init__(self):
        super().__init__()
        self.input_emb = nn.Linear(A, E)
        self.pos_emb = nn.Parameter(torch.zeros(1, T, E))
        self.cond_obs_emb = nn.Linear(F, E)
        self.cond_pos_emb = nn.Parameter(torch.zeros(1, 1 + TO, E))
        self.encoder = nn.Sequential(nn.Linear(E, 4 * E), nn.Mish(), nn.Linear(4 * E, E))
        layer = nn.TransformerDecoderLayer(d_model=E, nhead=HEADS, dim_feedforward=4 * E, dropout=0.0,
                                           activation="gelu", batch_first=True, norm_first=True)
        self.decoder = nn.TransformerDecoder(decoder_layer=layer, num_layers=LAYERS)
        self.ln_f = nn.LayerNorm(E)
        self.head = nn.Linear(E, A)
        mask = (torch.triu(torch.ones(T, T)) == 1).transpose(0, 1)
        self.register_buffer("mask", mask.float().masked_fill(mask == 0, float("-inf")).masked_fill(mask == 1, 0.0))
        t, s = torch.meshgrid(torch.arange(T), torch.arange(1 + TO), indexing="ij")
        mm = t >= (s - 1)
        self.register_buffer("memory_mask", mm.float().masked_fill(mm == 0, float("-inf")).masked_fill(mm == 1, 0.0))

    def time_emb(self, t):
        half = E // 2
        f = torch.exp(torch.arange(half) * -(math.log(10000) / (half - 1)))
        x = t[:, None].float() * f[None, :]
        return torch.cat([x.sin(), x.cos()], dim=-1)

    def forward(self, sample, timesteps, cond):
        cond_emb = torch.cat([self.time_emb(timesteps).unsqueeze(1), self.cond_obs_emb(cond)], dim=1)
        memory = self.encoder(cond_emb + self.cond_pos_emb)
        x = self.input_emb(sample) + self.pos_emb
        x = self.decoder(tgt=x, memory=memory, tgt_mask=self.mask, memory_mask=self.memory_mask)
        return self.head(self.ln_f(x))


def main(path):
    torch.manual_seed(0)
    net = Tiny().eval()
    with torch.no_grad():
        for name, p in net.named_parameters():
            if p.dim() == 1 or "pos_emb" in name:
                p.add_(0.1 * torch.randn_like(p))
    sample = torch.randn(B, T, A)
    cond = torch.randn(B, TO, F)
    timesteps = torch.tensor([0, 17, 99])
    with torch.no_grad():
        out = net(sample, timesteps, cond)
    tensors = {f"net.{k}": v.contiguous() for k, v in net.state_dict().items() if "mask" not in k}
    tensors.update({
        "io.sample": sample, "io.cond": cond.reshape(B, TO * F).contiguous(),
        "io.timesteps": timesteps.float(), "io.out": out.contiguous(),
    })
    save_file(tensors, path)


if __name__ == "__main__":
    main(sys.argv[1])
