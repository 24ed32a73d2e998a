"""Reference numpy random streams for mte-sim's bit-exact reproduction (src/rng.rs).

Pins: needs only numpy==2.2.6 (as in tools/reference/requirements-stats.txt); no other
package. Python 3.11.

Writes crates/mte-sim/tests/fixtures/numpy_rng.json, checked by the unit tests in
crates/mte-sim/src/rng.rs (`cargo test -p mte-sim --lib rng`). Everything is seeded, so
regenerating reproduces the file byte for byte.

Usage (from the repository root):
    python3.11 -m venv /tmp/venv-stats
    /tmp/venv-stats/bin/pip install -r tools/reference/requirements-stats.txt
    /tmp/venv-stats/bin/python tools/reference/numpy_rng_reference.py

Streams:
  legacy  numpy.random.RandomState(seed): MT19937 seeded by init_genrand (`mt19937_seed`),
          legacy distributions (random_sample, randint, randn).
  pcg64   numpy.random.Generator(PCG64(SeedSequence(seed))): what gymnasium's
          `np_random(seed)` builds (integers, random, uniform).

Floats are written as JSON *strings* holding Python's shortest round-trip repr: serde_json
without its `float_roundtrip` feature does not promise correctly rounded float parsing,
while Rust's `str::parse::<f64>` does, so strings are read back bit for bit. Integers
(including u64 values >= 2**63) are plain JSON numbers.
"""
import json
import math
import os
import sys

import numpy as np

N = 20
LEGACY_SEEDS = [0, 1, 42, 2**32 - 1, 100000]
PCG64_SEEDS = LEGACY_SEEDS + [2**40 + 7]
# (low, high), high exclusive. (0, 2**32) takes the raw-u32 branch (rng == 0xFFFFFFFF),
# (0, 2**33 + 5) the 64-bit branch; (0, 1) draws nothing.
RANGES = [(50, 450), (100, 400), (0, 1), (-5, 5), (0, 2**32), (0, 2**33 + 5),
          (-(2**62), 2**62 + 12345)]
# Beyond 4 entropy words the extra words are folded into the pool in a third pass.
SEED_SEQUENCE_SEEDS = PCG64_SEEDS + [2**64 - 1, 2**96 + 5, 2**127 + 2**64 + 3,
                                     2**160 + 2**64 + 3]
RESET_SEEDS = list(range(10)) + list(range(100000, 100050))
OUT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "crates",
                   "mte-sim", "tests", "fixtures", "numpy_rng.json")


def f(x):
    """A float as its shortest round-trip repr, in a string."""
    x = float(x)
    assert math.isfinite(x)
    return repr(x)


def legacy(seed):
    return np.random.RandomState(seed)


def pcg64(seed):
    return np.random.Generator(np.random.PCG64(np.random.SeedSequence(seed)))


def legacy_case(seed):
    mt = np.random.MT19937()
    mt._legacy_seeding(seed)
    u32 = [int(v) for v in mt.random_raw(N)]
    rs = legacy(seed)
    # randint(0, 2**32) is the raw next_uint32 branch: the same words.
    assert u32 == [int(rs.randint(0, 2**32)) for _ in range(N)]
    rs = legacy(seed)
    random_f64 = [f(rs.random_sample()) for _ in range(N)]
    rs = legacy(seed)
    randn = [f(rs.randn()) for _ in range(N)]
    randint = []
    for low, high in RANGES:
        rs = legacy(seed)
        randint.append({"low": low, "high": high,
                        "values": [int(rs.randint(low, high)) for _ in range(N)]})
    # Interleaved calls: the gauss cache survives other draws.
    rs = legacy(seed)
    mixed = []
    for op in ["randn", "int 50 450", "randn", "f64", "randn", "u32", "int 0 8589934597",
               "randn", "randn", "int -5 5", "f64", "randn"]:
        if op == "randn":
            mixed.append({"op": op, "value": f(rs.randn())})
        elif op == "f64":
            mixed.append({"op": op, "value": f(rs.random_sample())})
        elif op == "u32":
            mixed.append({"op": op, "value": str(int(rs.randint(0, 2**32)))})
        else:
            _, low, high = op.split()
            mixed.append({"op": op, "value": str(int(rs.randint(int(low), int(high))))})
    return {"seed": seed, "u32": u32, "random_f64": random_f64, "randn": randn,
            "randint": randint, "mixed": mixed}


def pcg64_case(seed):
    u64 = [int(v) for v in np.random.PCG64(np.random.SeedSequence(seed)).random_raw(N)]
    g = pcg64(seed)
    # integers(0, 2**32) is the raw next_uint32 branch: low half, then high half of a draw.
    u32 = [int(g.integers(0, 2**32)) for _ in range(N)]
    halves = [w for v in u64[: N // 2] for w in (v & 0xFFFFFFFF, v >> 32)]
    assert u32 == halves
    g = pcg64(seed)
    random_f64 = [f(g.random()) for _ in range(N)]
    g = pcg64(seed)
    uniform = [f(g.uniform(-np.pi, np.pi)) for _ in range(N)]
    integers = []
    for low, high in RANGES:
        g = pcg64(seed)
        integers.append({"low": low, "high": high,
                         "values": [int(g.integers(low, high)) for _ in range(N)]})
    # Interleaved calls: a 64-bit draw neither uses nor clears the buffered 32-bit half.
    g = pcg64(seed)
    mixed = []
    for op in ["u32", "u64", "u32", "f64", "int 50 450", "int 0 8589934597", "int 50 450",
               "uniform -3.141592653589793 3.141592653589793", "int 0 1", "u32", "u32",
               "uniform 2.5 2.5", "int -5 5"]:
        if op == "u64":
            mixed.append({"op": op, "value": str(int(g.integers(0, 2**64, dtype=np.uint64)))})
        elif op == "f64":
            mixed.append({"op": op, "value": f(g.random())})
        elif op == "u32":
            mixed.append({"op": op, "value": str(int(g.integers(0, 2**32)))})
        elif op.startswith("uniform"):
            _, low, high = op.split()
            mixed.append({"op": op, "value": f(g.uniform(float(low), float(high)))})
        else:
            _, low, high = op.split()
            mixed.append({"op": op, "value": str(int(g.integers(int(low), int(high))))})
    return {"seed": seed, "u64": u64, "u32": u32, "random_f64": random_f64,
            "uniform": uniform, "integers": integers, "mixed": mixed}


def reset_legacy(seed):
    # Diffusion Policy / gym-pusht <= 0.1.5, verbatim operation order.
    rs = np.random.RandomState(seed=seed)
    return np.array([
        rs.randint(50, 450), rs.randint(50, 450),
        rs.randint(100, 400), rs.randint(100, 400),
        rs.randn() * 2 * np.pi - np.pi,
    ])


def reset_pcg64(seed):
    # gym-pusht >= 0.1.6: gymnasium's np_random(seed) = Generator(PCG64(SeedSequence(seed))).
    g = pcg64(seed)
    return np.array([
        g.integers(50, 450), g.integers(50, 450),
        g.integers(100, 400), g.integers(100, 400),
        g.uniform(low=-np.pi, high=np.pi),
    ])


def main():
    if np.__version__ != "2.2.6":
        sys.exit(f"numpy 2.2.6 required, found {np.__version__}")
    seed_sequence = []
    for seed in SEED_SEQUENCE_SEEDS:
        ss = np.random.SeedSequence(seed)
        entropy = [int(w) for w in np.random.bit_generator._coerce_to_uint32_array(seed)]
        seed_sequence.append({
            "seed": str(seed),  # a string: some exceed u64 / u128
            "entropy": entropy,
            "pool": [int(w) for w in ss.pool],
            "words": [int(w) for w in ss.generate_state(8, np.uint32)],
        })
    pcg0 = reset_pcg64(0)
    # Anchor: gym-pusht 0.1.8 reset(seed=0) puts the agent at (390, 304).
    assert (pcg0[0], pcg0[1]) == (390.0, 304.0), pcg0
    doc = {
        "generator": "tools/reference/numpy_rng_reference.py",
        "versions": {"numpy": np.__version__},
        "draws_per_case": N,
        "legacy": [legacy_case(s) for s in LEGACY_SEEDS],
        "pcg64": [pcg64_case(s) for s in PCG64_SEEDS],
        "seed_sequence": seed_sequence,
        "reset": {
            "legacy": [{"seed": s, "sample": [f(v) for v in reset_legacy(s)]}
                       for s in RESET_SEEDS],
            "pcg64": [{"seed": s, "sample": [f(v) for v in reset_pcg64(s)]}
                      for s in RESET_SEEDS],
        },
    }
    text = json.dumps(doc, separators=(",", ":"))
    # One case per line: small, diffable, and still plain JSON.
    text = (text.replace('{"seed"', '\n{"seed"').replace('],"', '],\n"')
            + "\n")
    with open(OUT, "w", encoding="utf-8") as fh:
        fh.write(text)
    json.loads(text)
    print(f"wrote {os.path.normpath(OUT)} ({len(text)} bytes)", file=sys.stderr)


if __name__ == "__main__":
    main()
