"""``from fempdl import io`` and ``import fempdl.io``, the documented module path; the writers live in
:mod:`fempdl.core.io`."""
from fempdl.core.io import TimeSeries, nodal_field, plot_data, plot_fields, write_fields, write_xdmf

__all__ = ["TimeSeries", "nodal_field", "plot_data", "plot_fields", "write_fields", "write_xdmf"]
