"""Golden outputs of LeRobot's ACTTemporalEnsembler for mte-ensemble's parity test.

Drives the real `ACTTemporalEnsembler.update()` (lerobot==0.4.4, torch, see
requirements-lerobot.txt) through fixed chunk streams and records every executed action.
ACT with temporal ensembling queries every control step: in mte terms t_o = 1, h = 1,
t_p = chunk_size, and the aggregator is `ewm:<coeff>` (index 0 = oldest candidate).

Usage (from the repository root):
    python3 -m venv /tmp/venv-lerobot
    /tmp/venv-lerobot/bin/pip install -r tools/reference/requirements-lerobot.txt
    /tmp/venv-lerobot/bin/python tools/reference/lerobot_ensembler.py \
        > crates/mte-ensemble/tests/fixtures/lerobot_act_ensembler.json
"""
import json
import sys
from importlib.metadata import version

import numpy as np
import torch
from lerobot.policies.act.modeling_act import ACTTemporalEnsembler

CASES = [
    # (coeff, chunk_size, action_dim, steps, seed)
    (0.01, 10, 3, 30, 0),   # ACT's default coefficient
    (0.5, 6, 2, 20, 1),     # strong decay: old predictions dominate
    (-0.3, 8, 4, 24, 2),    # negative: newer predictions dominate
    (0.0, 5, 1, 12, 3),     # uniform mean
]


def main():
    out = {"generator": "tools/reference/lerobot_ensembler.py",
           "versions": {p: version(p) for p in ["lerobot", "torch", "numpy"]},
           "cases": []}
    for coeff, chunk, dim, steps, seed in CASES:
        rng = np.random.RandomState(seed)
        chunks = rng.uniform(-1.0, 1.0, size=(steps, chunk, dim)).astype(np.float32)
        ens = ACTTemporalEnsembler(coeff, chunk)
        ens.reset()
        actions = []
        with torch.no_grad():
            for t in range(steps):
                a = ens.update(torch.from_numpy(chunks[t][None]))  # (1, chunk, dim)
                actions.append(a[0].numpy().astype(float).tolist())
        out["cases"].append({"coeff": coeff, "chunk_size": chunk, "action_dim": dim,
                             "chunks": chunks.astype(float).tolist(), "actions": actions})
    json.dump(out, sys.stdout, separators=(",", ":"))
    sys.stdout.write("\n")


if __name__ == "__main__":
    main()
