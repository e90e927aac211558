"""Floor 3, the torch layer's machinery: the adjoint autograd Function (implicit gradients) and the
``diff="unrolled"`` path. :class:`fempdl.bridge_torch.SolveLayer`, on this floor, is the layer itself."""
