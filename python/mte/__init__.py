"""mte: robust temporal ensembling of action-chunked robot policies.

- ``TemporalEnsembler``: the streaming ensembler keyed by absolute control time, with every
  aggregator of mte by its text form (``"median"``, ``"ewm:0.01"``, ``"trimmed-medoid:2"``...).
- ``ACTTemporalEnsembler``: a drop-in for LeRobot's class of that name (same constructor,
  ``reset()`` and ``update()``), plus an ``aggregator`` argument.
- ``mte.stats``: McNemar, Wilcoxon, two-proportion z, Holm, AUROC, Wilson.
- ``mte.policy.load(dir).predict(history, seed)``: mte's Diffusion Policy and ACT checkpoints.
- ``gymnasium.make("mte/PushT-v0", obs_type=...)`` after ``import mte``: native PushT with
  gym-pusht's observation types, and ``mte.envs.VecPushT`` stepping many in Rust.

Units and conventions: control times are integers (steps); a chunk is ``(t_p, dim)`` with
row ``r`` the action for time ``t_query - (t_o - 1) + r``; PushT positions are pixels of
the 512 x 512 workspace, angles radians.
"""

from __future__ import annotations

from typing import Any, Dict, Optional, Tuple

import numpy as np

from . import _native, policy, stats
from ._native import MteError, __version__
from .act import ACTTemporalEnsembler

__all__ = [
    "ACTTemporalEnsembler",
    "MteError",
    "TemporalEnsembler",
    "__version__",
    "policy",
    "stats",
]


class TemporalEnsembler:
    """Streaming temporal ensembler of overlapping action chunks.

    ``TemporalEnsembler(t_p, t_o, h, aggregator="median", dim=None)``: chunks of ``t_p`` rows
    of ``dim`` actions (taken from the first chunk when not given), the policy seeing ``t_o``
    observations and re-queried every ``h`` control steps. ``insert(t, chunk)`` stores the
    chunk of the query fired at control time ``t``; ``action(t)`` aggregates every stored
    chunk covering ``t``. Bad input raises ``MteError`` (a ``ValueError``) naming the value
    and what was expected.
    """

    def __init__(self, t_p: int, t_o: int, h: int, aggregator: str = "median", dim: Optional[int] = None) -> None:
        self._args = (int(t_p), int(t_o), int(h))
        self._aggregator = aggregator
        # Validates the geometry and the aggregator now, whatever the dimension.
        probe = _native.TemporalEnsembler(*self._args, int(dim) if dim is not None else 1, aggregator)
        self._inner = probe if dim is not None else None

    def insert(self, t: int, chunk: Any, corrupted: bool = False) -> None:
        """Insert the ``(t_p, dim)`` chunk queried at control time ``t`` (copied as float32).

        ``corrupted`` marks a query known to be corrupted (it only feeds the step report).
        """
        array = np.ascontiguousarray(_to_numpy(chunk), dtype=np.float32)
        if self._inner is None:
            if array.ndim != 2:
                raise MteError(f"chunk of shape {array.shape}: expected (t_p, dim)")
            self._inner = _native.TemporalEnsembler(*self._args, array.shape[1], self._aggregator)
        self._inner.insert(int(t), array, bool(corrupted))

    def action(self, t: int) -> Tuple[np.ndarray, Dict[str, Any]]:
        """The aggregated action for control time ``t`` (float32, ``dim``) and the step report:
        ``m`` covering chunks, ``q`` flagged corrupted, ``excluded`` non-finite candidates,
        ``regime`` (``"2q<M"``, ``"2q=M"``, ``"2q>M"``), ``oldest_query``, ``newest_query``."""
        if self._inner is None:
            raise MteError(f"action({t}) before any chunk: expected insert(t, chunk) first")
        return self._inner.action(int(t))

    def reset(self) -> None:
        """Forget every chunk and the time cursor (a new episode)."""
        if self._inner is not None:
            self._inner.reset()

    @property
    def aggregator(self) -> str:
        return self._inner.aggregator if self._inner is not None else self._aggregator

    @property
    def dim(self) -> Optional[int]:
        return self._inner.dim if self._inner is not None else None

    def __repr__(self) -> str:
        if self._inner is not None:
            return repr(self._inner)
        t_p, t_o, h = self._args
        return f"TemporalEnsembler(t_p={t_p}, t_o={t_o}, h={h}, aggregator='{self._aggregator}', dim=None)"


def _to_numpy(x: Any) -> np.ndarray:
    """A numpy view of ``x`` (torch tensors are detached and moved to the CPU)."""
    if hasattr(x, "detach") and hasattr(x, "cpu"):
        x = x.detach().cpu().numpy()
    return np.asarray(x)


def _register() -> None:
    try:
        from . import envs
    except ImportError:  # gymnasium is optional
        return
    envs.register_envs()


_register()
