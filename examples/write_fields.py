"""Write a prediction and its reference to XDMF, for ParaView.

A Poisson layer capped at K Richardson-Jacobi iterations predicts the
solution for a source f; the reference is the converged (LU) solve. The file
holds the prediction, the reference and their difference as a time series
over K = 1, 2, 4, ... (ParaView's time slider steps through the caps), and
the source f. A Taylor-Hood (P2-P1) Stokes solution is written as well: its
velocity and pressure become separate fields, interpolated to P1 nodes.

Usage: python write_fields.py [OUTPUT_DIR]   (default runs/examples)
"""
import os
import sys
from pathlib import Path

import numpy as np
import torch

from fempdl import forms, mesh
from fempdl.bridge_torch import SolveLayer
from fempdl.core import io
from fempdl.ksp_adjoint import KSPOptions

small = os.environ.get("FEMPDL_EXAMPLE_SMALL") == "1"
out = Path(sys.argv[1] if len(sys.argv) > 1 else "runs/examples")
msh = mesh.load("lshape", h=0.2) if small else mesh.load("lshape")
problem = forms.poisson.problem(msh, controls=("f",))
f = torch.from_numpy(problem.interpolate(lambda x: 10 * (x[0] + 1) * (x[1] + 1), "f"))
reference = SolveLayer(problem, KSPOptions.preset("lu"))(f=f)
layer = SolveLayer(problem, KSPOptions(ksp_type="richardson", pc_type="jacobi", max_it=1))
caps = [2 ** i for i in range(6 if small else 10)]
predictions = []
for k in caps:
    layer.max_it = k
    predictions.append(layer(f=f))
prediction = torch.stack(predictions)                                  # (len(caps), n)
path = io.write_fields(out / "poisson.xdmf", problem, {
    "prediction": prediction, "reference": reference.expand_as(prediction),
    "error": prediction - reference, "f": f}, times=caps)
error = (prediction - reference).norm(dim=1) / reference.norm()
print(f"wrote {path}; relative error at K = {caps[0]} ... {caps[-1]}: {error[0]:.3e} ... {error[-1]:.3e}")

# A mixed solution: velocity and pressure are written as separate P1 fields.
stokes = forms.stokes.problem(msh, controls=(), f=lambda x: np.stack([-x[1], x[0]]))   # a swirling force
w = SolveLayer(stokes, KSPOptions.preset("lu"))()
velocity = stokes.from_function(stokes.to_function(w, "u"), "u")      # the same values, through a Function
print(f"wrote {io.write_fields(out / 'stokes.xdmf', stokes, {'flow': w})}; |u|_max {abs(velocity).max():.3e}")
