"""Floor 3, the torch layer's machinery: the adjoint autograd Function (implicit gradients) and the
``diff="unrolled"`` path. :class:`fempdl.layer.solve_layer.SolveLayer`, on this floor, is the layer itself."""
