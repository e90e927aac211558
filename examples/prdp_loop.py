"""PRDP in your own training loop, with PRDP's defaults: a capped heat step, K raised up to K_eps.

A network maps mode amplitudes a (B, m) to an initial temperature u0; a heat step capped at K
Richardson-Jacobi iterations advances it; the loss is the nMSE against converged steps. After every
epoch PRDP runs the validation at converged physics and at the cap: K rises at once while the two
differ by more than 5%, and when the metric stops improving, never above K_eps. ``finish`` closes the
gap at the end and returns the metric the model is judged by.
"""
import os

import numpy as np
import torch

from fempdl import forms, mesh
from fempdl.bridge_torch import SolveLayer
from fempdl.ksp_adjoint import KSPOptions
from fempdl.prdp import PRDP, k_eps

small = os.environ.get("FEMPDL_EXAMPLE_SMALL") == "1"
problem = forms.heat.problem(mesh.load("lshape", h=0.2) if small else mesh.load("lshape"), controls=("u0",),
                             dt=0.01)
x = problem.dof_coordinates()
modes = torch.from_numpy(np.stack([np.sin(i * x[:, 0] + 1.0) * np.cos(j * x[:, 1])
                                   for i in range(1, 4) for j in range(1, 4)], axis=1))   # (n, 9)
torch.manual_seed(0)
a_train, a_val = torch.randn(32, 9, dtype=torch.float64), torch.randn(8, 9, dtype=torch.float64)
reference = SolveLayer(problem, KSPOptions.preset("lu"))
with torch.no_grad():
    u_train, u_val = reference(u0=a_train @ modes.T), reference(u0=a_val @ modes.T)

layer = SolveLayer(problem, KSPOptions(ksp_type="richardson", pc_type="jacobi", max_it=1))
k_cap = k_eps(layer, u0=a_val @ modes.T)
ctrl = PRDP(layer, k0=1, k_cap=k_cap)            # every other setting PRDP's default
net = torch.nn.Sequential(torch.nn.Linear(9, 32), torch.nn.Tanh(), torch.nn.Linear(32, problem.output_size)).double()
optimizer = torch.optim.Adam(net.parameters(), lr=3e-2)


def nmse(u, ref):
    return (((u - ref) ** 2).sum(1) / (ref ** 2).sum(1)).mean()


def validate():
    return nmse(layer(u0=net(a_val)), u_val)


schedule = []
for _epoch in range(30 if small else 100):
    for batch in torch.randperm(32).split(8):
        optimizer.zero_grad()
        nmse(layer(u0=net(a_train[batch])), u_train[batch]).backward()
        optimizer.step()
    schedule.append(layer.max_it)
    ctrl.step(validate)              # at converged physics and at the cap
k_last = ctrl.k
done = ctrl.finish(validate)     # validates at both physics once more at k_last; closes the gap if open
capped = [k for rec in ctrl.history for k in [rec.k] * (rec.capped_metric is not None) + [k for k, _ in rec.probes]]
print(f"K_eps {k_cap}; K per epoch {schedule}; capped validations at K {capped}; finished at K {done.k} from "
      f"{k_last} (gap {done.gap:.3g}, probes {[k for k, _ in done.probes]})")
print(f"validation nMSE {done.metric:.3e}; solver iterations {layer.stats.total_iterations}; "
      f"converged validations {layer.reference_stats.forward_solves}")
