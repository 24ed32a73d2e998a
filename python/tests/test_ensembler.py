"""mte.TemporalEnsembler from Python: values, reports and typed errors."""

import numpy as np
import pytest

import mte


def ramp(t, t_p, dim, offset=0.0):
    """Chunk queried at t whose row r is the action for time t + r: value t + r + offset."""
    return np.array([[t + r + offset] * dim for r in range(t_p)], dtype=np.float32)


def test_median_of_three_covering_chunks_ignores_one_outlier():
    ens = mte.TemporalEnsembler(t_p=4, t_o=1, h=1, aggregator="median")
    ens.insert(0, ramp(0, 4, 2))
    ens.insert(1, ramp(1, 4, 2, offset=1000.0))  # one corrupted prediction
    ens.insert(2, ramp(2, 4, 2))
    action, report = ens.action(2)
    assert action.dtype == np.float32 and action.shape == (2,)
    np.testing.assert_array_equal(action, [2.0, 2.0])
    assert report["m"] == 3 and report["q"] == 0 and report["regime"] == "2q<M"
    assert report["oldest_query"] == 0 and report["newest_query"] == 2


def test_mean_is_dragged_by_the_same_outlier():
    ens = mte.TemporalEnsembler(4, 1, 1, aggregator="mean", dim=2)
    for t, off in [(0, 0.0), (1, 1000.0), (2, 0.0)]:
        ens.insert(t, ramp(t, 4, 2, off))
    action, _ = ens.action(2)
    np.testing.assert_allclose(action, [2.0 + 1000.0 / 3] * 2, rtol=1e-6)


def test_corrupted_flag_feeds_the_report():
    ens = mte.TemporalEnsembler(4, 1, 1, dim=1)
    ens.insert(0, ramp(0, 4, 1), corrupted=True)
    ens.insert(1, ramp(1, 4, 1))
    _, report = ens.action(1)
    assert (report["m"], report["q"], report["regime"]) == (2, 1, "2q=M")


def test_every_aggregator_text_form_round_trips():
    for text in ["median", "ewm:0.01", "ewm-newest:0.01", "mean", "latest", "medoid", "trimmed-medoid:2",
                 "trimmed-mean:1", "recency-median:0.1", "geomedian:64", "median:lower"]:
        ens = mte.TemporalEnsembler(8, 2, 2, text)
        assert ens.aggregator.split(":")[0] == text.split(":")[0]
        ens.insert(0, np.zeros((8, 3)))
        action, _ = ens.action(0)
        np.testing.assert_array_equal(action, np.zeros(3))


def test_reset_starts_a_new_episode():
    ens = mte.TemporalEnsembler(4, 1, 1, dim=1)
    ens.insert(5, ramp(5, 4, 1))
    ens.action(5)
    ens.reset()
    ens.insert(0, ramp(0, 4, 1))
    action, _ = ens.action(0)
    assert action[0] == 0.0


@pytest.mark.parametrize(
    "call, fragment",
    [
        (lambda: mte.TemporalEnsembler(4, 1, 1, aggregator="mediann"), "mediann"),
        (lambda: mte.TemporalEnsembler(4, 5, 1), "t_o"),
        (lambda: mte.TemporalEnsembler(4, 1, 1, dim=2).insert(0, np.zeros((3, 2))), "(4, 2)"),
        (lambda: mte.TemporalEnsembler(4, 1, 1, dim=2).action(0), "0"),
        (lambda: mte.TemporalEnsembler(4, 1, 1, dim=1).insert(0, np.array([[1.0], [np.nan], [1.0], [1.0]])) or None, None),
    ],
)
def test_bad_input_raises_mte_error_naming_the_value(call, fragment):
    if fragment is None:
        # A NaN candidate is accepted at insert and excluded (and counted) at aggregation.
        call()
        return
    with pytest.raises(mte.MteError) as e:
        call()
    assert fragment in str(e.value)
    assert isinstance(e.value, ValueError)


def test_nan_candidates_are_excluded_and_counted():
    ens = mte.TemporalEnsembler(4, 1, 1, dim=1)
    ens.insert(0, np.array([[0.0], [np.nan], [2.0], [3.0]]))
    ens.insert(1, ramp(1, 4, 1))
    action, report = ens.action(1)
    assert report["m"] == 2 and report["excluded"] == 1
    assert action[0] == 1.0


def test_dimension_comes_from_the_first_chunk_when_not_given():
    ens = mte.TemporalEnsembler(4, 1, 1)
    assert ens.dim is None
    with pytest.raises(mte.MteError, match="before any chunk"):
        ens.action(0)
    ens.insert(0, ramp(0, 4, 3))
    assert ens.dim == 3
    action, _ = ens.action(0)
    assert action.shape == (3,)
