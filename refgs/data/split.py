"""The sparse-view train/test split of DropGaussian / FSGS / CoR-GS (clause DAT-10).

Views are ranked by image name in Python ``sorted()`` order; every ``holdout``-th view
(rank % holdout == 0) is a test view; of the remaining R views, ``n_views`` are kept at ranks
``[round(x) for x in np.linspace(0, R - 1, n_views)]`` (Python ``round``: halves to even).
Source: DCVL-3D/DropGaussian_release@c13da4a scene/dataset_readers.py L171-212 (peers.md 3.1).
"""
from __future__ import annotations

import numpy as np

from ..errors import ConfigError

#: Every 8th view (sorted by name, starting with the first) is held out for testing
#: (``llffhold = 8`` in 3DGS/DropGaussian/FSGS dataset_readers.py).  [DAT-10]
LLFF_HOLD = 8


def split_views(names, n_views: int | None, holdout: int = LLFF_HOLD):
    """Return ``(train_idx, test_idx)``: integer lists indexing ``names`` (clause DAT-10).

    names    sequence of V image names (any order; ranked here with ``sorted()``)
    n_views  number of training views, or None for all non-test views
    holdout  test views are the ranks r with r % holdout == 0

    train_idx is in rank order, test_idx too.  ConfigError (naming ``--views``) when n_views is
    not an integer in 1..R, R = V - ceil(V / holdout) the number of non-test views.
    """
    names = list(names)
    if len(set(names)) != len(names):
        raise ConfigError("split_views: image names must be unique")
    if not (isinstance(holdout, (int, np.integer)) and holdout >= 2):
        raise ConfigError(f"--holdout: expected an integer >= 2, got {holdout!r}")
    order = sorted(range(len(names)), key=lambda i: names[i])
    test = [i for r, i in enumerate(order) if r % holdout == 0]
    rest = [i for r, i in enumerate(order) if r % holdout != 0]
    if n_views is None:
        return rest, test
    if isinstance(n_views, bool) or not isinstance(n_views, (int, np.integer)) or n_views < 1:
        raise ConfigError(f"--views: expected a positive integer, got {n_views!r}")
    if n_views > len(rest):
        raise ConfigError(f"--views: asked for {n_views} training views, but the scene has only "
                          f"{len(rest)} non-test views ({len(names)} images, every {holdout}th "
                          "held out for testing)")
    picks = [round(float(x)) for x in np.linspace(0, len(rest) - 1, int(n_views))]
    return [rest[k] for k in picks], test


__all__ = ["split_views", "LLFF_HOLD"]
