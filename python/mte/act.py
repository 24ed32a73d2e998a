"""A drop-in for LeRobot's ``ACTTemporalEnsembler`` with any mte aggregator.

LeRobot (0.4.4) queries ACT at every control step and combines, for the current step, the
rows of every chunk that covers it with weights ``exp(-coeff * i)``, ``i = 0`` the oldest.
Here that is ``TemporalEnsembler(chunk_size, t_o=1, h=1, aggregator="ewm:<coeff>")`` per
batch element; ``aggregator="median"`` (or any other text form) swaps the combination rule
and nothing else.
"""

from __future__ import annotations

from typing import Any, List, Optional

import numpy as np

from . import _native


class ACTTemporalEnsembler:
    """``ACTTemporalEnsembler(temporal_ensemble_coeff, chunk_size, aggregator=None)``.

    ``update(actions)`` takes the ``(batch, chunk_size, action_dim)`` chunk predicted at this
    step and returns the ``(batch, action_dim)`` action to execute. A torch tensor in gives a
    torch tensor out (same dtype and device), numpy otherwise. ``reset()`` starts a new
    episode. ``aggregator=None`` means LeRobot's rule, ``"ewm:<coeff>"``.
    """

    def __init__(self, temporal_ensemble_coeff: float, chunk_size: int, aggregator: Optional[str] = None) -> None:
        self.temporal_ensemble_coeff = float(temporal_ensemble_coeff)
        self.chunk_size = int(chunk_size)
        self.aggregator = aggregator if aggregator is not None else f"ewm:{self.temporal_ensemble_coeff!r}"
        # Validate the arguments now, as LeRobot's constructor would fail now.
        _native.TemporalEnsembler(self.chunk_size, 1, 1, 1, self.aggregator)
        self.reset()

    def reset(self) -> None:
        """Start a new episode: the next ``update`` is step 0."""
        self._streams: List[Any] = []
        self._t = 0

    def update(self, actions: Any) -> Any:
        """Ensemble the new ``(batch, chunk_size, action_dim)`` chunk into the plan and return the
        ``(batch, action_dim)`` action for this step."""
        array, like = _as_numpy(actions)
        if array.ndim != 3 or array.shape[1] != self.chunk_size:
            raise _native.MteError(
                f"actions of shape {tuple(array.shape)}: expected (batch, {self.chunk_size}, action_dim)"
            )
        batch, _, dim = array.shape
        if not self._streams:
            self._streams = [_native.TemporalEnsembler(self.chunk_size, 1, 1, dim, self.aggregator) for _ in range(batch)]
        elif len(self._streams) != batch or self._streams[0].dim != dim:
            raise _native.MteError(
                f"actions of shape {tuple(array.shape)}: this episode started with batch "
                f"{len(self._streams)} and action_dim {self._streams[0].dim}; call reset() first"
            )
        chunk = np.ascontiguousarray(array, dtype=np.float32)
        out = np.empty((batch, dim), dtype=np.float32)
        for b, stream in enumerate(self._streams):
            stream.insert(self._t, chunk[b])
            out[b], _ = stream.action(self._t)
        self._t += 1
        return _like(out, like)


def _as_numpy(x: Any):
    """``(numpy array, original)``; torch tensors are detached and copied to the CPU."""
    if hasattr(x, "detach") and hasattr(x, "cpu"):
        return x.detach().cpu().numpy(), x
    return np.asarray(x), None


def _like(out: np.ndarray, like: Any) -> Any:
    if like is None:
        return out
    import torch  # present: `like` is a tensor

    return torch.from_numpy(out).to(dtype=like.dtype, device=like.device)
