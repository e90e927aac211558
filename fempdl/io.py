"""``from fempdl import io`` and ``import fempdl.io``, the documented module path; the writers live in
:mod:`fempdl.core.io` and :mod:`fempdl.core.time_series`."""
from fempdl.core.io import nodal_field, plot_data, plot_fields, write_fields, write_xdmf
from fempdl.core.time_series import TimeSeries

__all__ = ["TimeSeries", "nodal_field", "plot_data", "plot_fields", "write_fields", "write_xdmf"]
