"""Which recorded states an animation shows: the GIF/MP4 of :mod:`swarmpc.plots` and the
interactive page of :mod:`swarmpc.viewer` pick their frames with the same rule."""

from __future__ import annotations

import numpy as np


def even_indices(count: int, n: int) -> np.ndarray:
    """``min(n, count)`` distinct, increasing, evenly spread indices in [0, count) with both ends."""
    if count <= 0 or n <= 0:
        return np.zeros(0, int)
    n = min(n, count)
    if n == 1:
        return np.zeros(1, int)
    # floor(x + 0.5) is monotone with unit steps, so spacing >= 1 keeps the indices distinct.
    return np.floor(np.linspace(0, count - 1, n) + 0.5).astype(int)


def frame_indices(num_states: int, max_frames: int, keep: int | None = None) -> np.ndarray:
    """The state indices an animation shows: ``min(num_states, max_frames)`` evenly spread ones.

    Parameters
    ----------
    num_states : int
        Number of recorded states (T+1).
    max_frames : int
        Frame cap.
    keep : int, optional
        A state that must be shown (e.g. the closest approach): it replaces the nearest interior
        index when the even spread misses it.

    Returns
    -------
    np.ndarray
        Increasing distinct indices including the first and the last state (and ``keep``).
    """
    idx = even_indices(num_states, max_frames)
    if keep is None or not 0 < keep < num_states - 1 or keep in idx or len(idx) < 3:
        return idx
    interior = np.arange(1, len(idx) - 1)
    idx[interior[np.argmin(np.abs(idx[interior] - keep))]] = keep
    return np.unique(idx)
