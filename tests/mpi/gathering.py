"""What the MPI scripts share: every rank's owned DOF values collected on rank 0 in one order."""
from __future__ import annotations

import numpy as np


def gathered(comm, coords: np.ndarray, values: np.ndarray) -> np.ndarray | None:
    """Values of every rank's owned DOFs on rank 0, sorted by coordinate (rounded, so that a node's
    coordinates computed on two partitions sort alike)."""
    parts = comm.gather((np.round(coords[:, :3], 10), values), root=0)
    if comm.rank != 0:
        return None
    xy = np.concatenate([c for c, _ in parts])
    vals = np.concatenate([v for _, v in parts], axis=-1)
    return vals[..., np.lexsort(xy.T[::-1])]          # by x, then y, then z (0 on a 2D mesh)
