"""Under mpirun -n 1 and -n 2: point observations and mass inner products of a distributed field, and
their gradients, written from rank 0 to OUT (.npz) for comparison with the serial run."""
import sys

from mpi4py import MPI
import numpy as np
import torch

from fempdl import MassInner, PointObservation, forms, mesh

comm = MPI.COMM_WORLD
problem = forms.poisson.problem(mesh.load("lshape", comm, h=0.1), controls=("f",), degree=2)
points = np.array([[0.1, 0.2], [-0.5, 0.3], [-0.7, -0.8], [0.0, 0.0], [0.95, 0.05], [-0.25, -0.25]])
u = torch.as_tensor(problem.interpolate(lambda x: np.sin(2 * x[0]) * np.cos(x[1]) + x[0] * x[1]),
                    dtype=torch.float64).requires_grad_()
observe, inner = PointObservation(problem, points), MassInner(problem, kind="H1")
values = observe(u)
total = values.square().sum() + inner(u)
total.backward()
coordinates = problem.dof_coordinates()
value = float(inner(u))                      # collective: every rank
gathered = comm.gather((coordinates, u.grad.numpy()))
if comm.rank == 0:
    xs = np.concatenate([c for c, _ in gathered])
    grads = np.concatenate([g for _, g in gathered])
    rounded = np.round(xs, 10)                   # coordinates agree to round-off across partitions
    order = np.lexsort((rounded[:, 1], rounded[:, 0]))
    np.savez(sys.argv[1], values=values.detach().numpy(), inner=value, grad=grads[order])
