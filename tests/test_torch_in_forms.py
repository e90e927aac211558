"""A torch network or tensor put where a form needs UFL (a conductivity law q(u)) or numpy values (a
coefficient's callable x -> values) is refused in one line that names the cause and what works,
instead of torch's "linear(): argument 'input' must be Tensor, not Function"."""
from __future__ import annotations

import pytest
import torch

from fempdl import Network, NonlinearSolveLayer, forms

NET = torch.nn.Sequential(torch.nn.Linear(1, 8), torch.nn.Softplus(), torch.nn.Linear(8, 1)).double()
WHAT_WORKS = "q=lambda u: fempdl.Network(module, operands=(u,))"


@pytest.mark.parametrize("q, message", [
    (NET, r"q is a torch Sequential; a form is UFL"),
    (lambda u: NET(u), r"q\(u\) called torch on the UFL unknown \(TypeError: "),
    (lambda u: torch.tensor(1.0), r"q\(u\) must return a UFL expression of u, got a Tensor; "),
], ids=["module", "module-in-lambda", "tensor"])
def test_a_torch_law_is_refused_naming_the_cause(coarse_lshape, q, message):
    with pytest.raises(TypeError, match=message) as caught:
        forms.nonlinear_diffusion.problem(coarse_lshape, q=q)
    if "tensor" not in message:
        assert WHAT_WORKS in str(caught.value)


def test_a_law_that_is_not_ufl_is_refused(coarse_lshape):
    with pytest.raises(TypeError, match=r"q\(u\) must return a UFL expression of u, got a str$"):
        forms.nonlinear_diffusion.problem(coarse_lshape, q=lambda u: "1 + u**2")


def test_an_error_of_the_users_own_law_is_left_as_it_is(coarse_lshape):
    def law(u):
        raise ZeroDivisionError("the user's own bug")
    with pytest.raises(ZeroDivisionError, match="the user's own bug"):
        forms.nonlinear_diffusion.problem(coarse_lshape, q=law)


@pytest.mark.parametrize("f, message", [
    (NET, r"f is a torch Sequential; give a float or a callable x \(3, N\) -> \(N,\) numpy values, or make f a "
          r"control"),
    (lambda x: NET(x), r"f: the callable called torch on numpy coordinates \(TypeError: .*\); return numpy "
                       r"values, or make f a control"),
], ids=["module", "module-in-lambda"])
def test_a_torch_coefficient_is_refused_naming_the_control_route(coarse_lshape, f, message):
    with pytest.raises(TypeError, match=message):
        forms.poisson.problem(coarse_lshape, controls=("kappa",), f=f)


def test_a_ufl_law_and_numpy_callables_still_work(coarse_lshape):
    """The same law as the default (1 + u^2) given as q, with a numpy source: the same solution."""
    import numpy as np
    source = lambda x: 1.0 + np.sin(x[0])                      # noqa: E731
    given = forms.nonlinear_diffusion.problem(coarse_lshape, q=lambda u: 1 + u ** 2, f=source, controls=("kappa",))
    default = forms.nonlinear_diffusion.problem(coarse_lshape, f=source, controls=("kappa",))
    kappa = torch.ones(given.control_size("kappa"), dtype=torch.float64)
    u_given, u_default = NonlinearSolveLayer(given)(kappa=kappa), NonlinearSolveLayer(default)(kappa=kappa)
    assert u_given.abs().max() > 0.01
    torch.testing.assert_close(u_given, u_default, rtol=0, atol=1e-12)


def test_the_route_the_refusal_names_trains_the_module_through_the_bundled_form(coarse_lshape):
    """q=lambda u: Network(module, (u,)): the law torch computes, its weights' gradient from backward."""
    net = torch.nn.Sequential(torch.nn.Linear(1, 8), torch.nn.Tanh(), torch.nn.Linear(8, 1),
                              torch.nn.Softplus()).double()
    prob = forms.nonlinear_diffusion.problem(coarse_lshape, q=lambda u: Network(net, (u,), name="q", positive=True),
                                             controls=("f",))
    layer = NonlinearSolveLayer(prob)
    u = layer(f=torch.full((prob.control_size("f"),), 5.0, dtype=torch.float64))
    u.square().sum().backward()
    assert u.abs().max() > 0.01 and all(p.grad is not None and p.grad.abs().max() > 0 for p in net.parameters())
