"""``from fempdl import mesh`` and ``import fempdl.mesh``, the documented module path; the meshes live in
:mod:`fempdl.core.mesh` (and their geometry in :mod:`fempdl.core.meshgen`)."""
from fempdl.core.mesh import TaggedMesh, as_tagged, available, check_unfolded, load, source_digest

__all__ = ["TaggedMesh", "as_tagged", "available", "check_unfolded", "load", "source_digest"]
