"""The drop-in ACTTemporalEnsembler: parity with LeRobot 0.4.4 on recorded streams (the fixture
of crates/mte-ensemble/tests, made by tools/reference/lerobot_ensembler.py), and against the
live class when lerobot is installed."""

import json
import pathlib

import numpy as np
import pytest

import mte

FIXTURE = pathlib.Path(__file__).resolve().parents[2] / "crates/mte-ensemble/tests/fixtures/lerobot_act_ensembler.json"


def cases():
    return json.loads(FIXTURE.read_text())["cases"]


def replay(case, aggregator=None):
    ens = mte.ACTTemporalEnsembler(case["coeff"], case["chunk_size"], aggregator=aggregator)
    out = [ens.update(np.array(chunk, dtype=np.float32)[None])[0] for chunk in case["chunks"]]
    return np.array(out)


def test_default_rule_matches_lerobot_recorded_streams():
    assert len(cases()) == 4
    for case in cases():
        got = replay(case)
        # LeRobot keeps a float32 running average; mte sums the weights in f64 once: a few
        # float32 ulps on values in [-1, 1] (the Rust parity test's bound).
        np.testing.assert_allclose(got, np.array(case["actions"]), atol=1e-5, rtol=0)


def test_median_changes_the_rule_and_nothing_else():
    case = cases()[1]
    got = replay(case, aggregator="median")
    assert got.shape == np.array(case["actions"]).shape
    assert np.abs(got - np.array(case["actions"])).max() > 1e-2
    # Step 0 has one candidate: every rule returns it.
    np.testing.assert_array_equal(got[0], np.array(case["chunks"][0][0], dtype=np.float32))


def test_batches_are_independent_streams():
    rng = np.random.default_rng(0)
    chunks = rng.standard_normal((6, 3, 5, 2)).astype(np.float32)  # steps, batch, chunk, dim
    batched = mte.ACTTemporalEnsembler(0.01, 5)
    singles = [mte.ACTTemporalEnsembler(0.01, 5) for _ in range(3)]
    for step in chunks:
        out = batched.update(step)
        for b in range(3):
            np.testing.assert_array_equal(out[b], singles[b].update(step[b : b + 1])[0])


def test_shape_errors_and_reset():
    ens = mte.ACTTemporalEnsembler(0.01, 5)
    with pytest.raises(mte.MteError, match="expected \\(batch, 5, action_dim\\)"):
        ens.update(np.zeros((1, 4, 2)))
    ens.update(np.zeros((2, 5, 2)))
    with pytest.raises(mte.MteError, match="reset"):
        ens.update(np.zeros((3, 5, 2)))
    ens.reset()
    assert ens.update(np.ones((3, 5, 2))).shape == (3, 2)


def test_torch_in_gives_torch_out():
    torch = pytest.importorskip("torch")
    ens = mte.ACTTemporalEnsembler(0.01, 4)
    out = ens.update(torch.ones((2, 4, 3), dtype=torch.float32))
    assert isinstance(out, torch.Tensor) and out.shape == (2, 3)


def test_live_lerobot_class_agrees():
    modeling = pytest.importorskip("lerobot.policies.act.modeling_act")
    torch = pytest.importorskip("torch")
    rng = np.random.default_rng(1)
    theirs = modeling.ACTTemporalEnsembler(0.01, 8)
    ours = mte.ACTTemporalEnsembler(0.01, 8)
    for _ in range(20):
        chunk = rng.uniform(-1, 1, (2, 8, 3)).astype(np.float32)
        want = theirs.update(torch.from_numpy(chunk)).numpy()
        np.testing.assert_allclose(ours.update(chunk), want, atol=1e-5, rtol=0)
