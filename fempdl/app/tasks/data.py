"""Synthetic data of the scenes: smooth random fields, source modes and box indicators on DOF coordinates.

All take ``coords`` (n, 3), node or DOF coordinates, and work on the unit box
they span (:func:`unit_box`), so a field looks alike on any mesh of a geometry.
"""
from __future__ import annotations

from mpi4py import MPI
import numpy as np

__all__ = ["unit_box", "smooth_fields", "source_modes", "rectangle_fields"]


def unit_box(coords: np.ndarray, comm: MPI.Comm | None = None) -> np.ndarray:
    """(n, d) coordinates scaled to [0, 1] along each of the d axes the points span.

    With ``comm`` the box is that of all its ranks' points (a distributed mesh)."""
    lo, hi = coords.min(axis=0), coords.max(axis=0)
    if comm is not None:
        comm.Allreduce(MPI.IN_PLACE, lo, op=MPI.MIN)
        comm.Allreduce(MPI.IN_PLACE, hi, op=MPI.MAX)
    dims = [d for d in range(coords.shape[1]) if hi[d] > lo[d]]
    return (coords[:, dims] - lo[dims]) / (hi[dims] - lo[dims])


def smooth_fields(coords: np.ndarray, count: int, modes: int, rng: np.random.Generator,
                  components: int = 1) -> np.ndarray:
    """(count, n * components) random sums of sine modes over the bounding box, amplitudes ~ 1/|mode|^2.

    ``coords`` (n, 3) are node coordinates; with ``components`` > 1 every
    component is an independent field and the values are blocked per node
    (x0, y0, x1, y1, ...), the DOF order of a vector space."""
    unit = unit_box(coords)
    out = np.zeros((count, len(coords), components))
    for index in np.ndindex(*([modes] * unit.shape[1])):
        wave = np.array(index) + 1
        shape = np.prod(np.sin(np.pi * wave[None, :] * unit), axis=1)
        out += (rng.standard_normal((count, 1, components)) / float(wave @ wave)) * shape[None, :, None]
    return out.reshape(count, -1)


def source_modes(coords: np.ndarray, count: int, comm: MPI.Comm = MPI.COMM_SELF) -> np.ndarray:
    """(n, P) smooth modes phi_p(x) = prod_d sin(p pi x_d) over the bounding box.

    ``coords`` are this rank's rows; the box is that of all ranks of ``comm``."""
    unit = unit_box(coords, comm)
    return np.stack([np.prod(np.sin(np.pi * p * unit), axis=1) for p in range(1, count + 1)], axis=1)


def rectangle_fields(coords: np.ndarray, count: int, boxes: int, rng: np.random.Generator) -> np.ndarray:
    """(count, n) sums of ``boxes`` indicator functions of random axis-aligned boxes, amplitudes ~ N(0, 1).

    Each box spans 10% to 50% of the bounding box along every axis; ``coords``
    (n, 3) are the DOF coordinates."""
    unit = unit_box(coords)
    out = np.zeros((count, len(coords)))
    for sample in out:
        for _ in range(boxes):
            inside = np.zeros(len(coords), dtype=bool)
            while not inside.any():             # a box between the nodes would leave the truth zero
                width = rng.uniform(0.1, 0.5, unit.shape[1])
                start = rng.uniform(0.0, 1.0 - width)
                inside = np.all((unit >= start) & (unit <= start + width), axis=1)
            sample[inside] += rng.standard_normal()
    return out
