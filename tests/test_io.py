"""Fields out: Problem.to_function / from_function and XDMF files (fempdl.core.io).

The XDMF tests write with the ASCII encoding, so the values can be read back
from the XML itself and compared with the field's nodal values; one test
writes HDF5 and checks that the XML points into an HDF5 file.
"""
from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np
import pytest
import torch

from fempdl import forms, mesh
from fempdl.core import io
from fempdl.io import TimeSeries

from helpers import smooth


@pytest.fixture(scope="module")
def coarse():
    return mesh.load("lshape", h=0.25)


@pytest.fixture(scope="module")
def poisson_p2(coarse):
    return forms.poisson.problem(coarse, controls=("f", "kappa"), degree=2, kappa_space="DG0", kappa=smooth)


@pytest.fixture(scope="module")
def stokes(coarse):
    return forms.stokes.problem(coarse)


def _linear(x):
    return 1.0 + 2.0 * x[0] - 3.0 * x[1]


def test_round_trip_is_exact_for_every_space(poisson_p2, stokes):
    rng = np.random.default_rng(0)
    for prob, names in ((poisson_p2, (None, "u", "f", "kappa")), (stokes, (None, "u", "p", "f"))):
        for name in names:
            space = prob.function_space(name)
            n = space.dofmap.index_map.size_local * space.dofmap.index_map_bs
            x = torch.from_numpy(rng.standard_normal(n))
            fn = prob.to_function(x, name)
            assert fn.name == ("u" if name is None else name)
            back = prob.from_function(fn, name)
            assert back.dtype == np.float64
            np.testing.assert_array_equal(back, x.numpy())


def test_mixed_field_from_whole_solution(stokes):
    x = np.random.default_rng(1).standard_normal(stokes.output_size)
    whole = stokes.to_function(x)
    assert whole.function_space == stokes.V
    assert stokes.function_space() is stokes.V and stokes.function_space("p") is stokes.field_space("p")
    assert stokes.function_space("f") is stokes.control("f").function_space
    for field, dofs in stokes.fields.items():
        np.testing.assert_array_equal(stokes.from_function(stokes.to_function(x, field), field), x[dofs])
    # the velocity control f lives on an equal but distinct space: interpolated, same values
    f = stokes.to_function(x[stokes.fields["u"]], "f")
    np.testing.assert_allclose(stokes.from_function(f, "u"), x[stokes.fields["u"]], rtol=0, atol=1e-14)


def test_to_function_errors_name_the_argument(poisson_p2):
    with pytest.raises(ValueError, match=r"values for 'kappa' must have shape \(\d+,\) .* got \(2, 3\); "
                                         r"pass one sample"):
        poisson_p2.to_function(np.zeros((2, 3)), "kappa")
    with pytest.raises(ValueError, match=r"unknown name 'p'; use a control \['f', 'kappa'\], or None"):
        poisson_p2.to_function(np.zeros(3), "p")
    with pytest.raises(TypeError, match="fn must be a dolfinx.fem.Function, got ndarray"):
        poisson_p2.from_function(np.zeros(3))


def _ascii_attributes(path):
    """{(name, time): (values array, center)} from an ASCII-encoded XDMF file."""
    root = ET.parse(path).getroot()
    out, geometry = {}, None
    for grid in root.iter("Grid"):
        time = grid.find("Time")
        g = grid.find("Geometry")
        if g is not None and g.find("DataItem") is not None:
            geometry = np.array(g.find("DataItem").text.split(), dtype=float)
        for attr in grid.findall("Attribute"):
            item = attr.find("DataItem")
            dims = [int(d) for d in item.get("Dimensions").split()]
            values = np.array(item.text.split(), dtype=float).reshape(dims)
            out[(attr.get("Name"), float(time.get("Value")))] = (values, attr.get("Center"))
    return out, geometry


def test_xdmf_p2_solution_written_at_nodes_with_time_steps(tmp_path, poisson_p2, coarse):
    u = poisson_p2.interpolate(_linear)
    steps = np.stack([u, 2.0 * u, -u])
    path = io.write_fields(tmp_path / "series", poisson_p2, {"prediction": steps, "kappa": poisson_p2.interpolate(
        smooth, "kappa")}, times=[0.0, 0.5, 1.0], encoding="ascii")
    assert path == tmp_path / "series.xdmf" and not (tmp_path / "series.h5").exists()
    attrs, geometry = _ascii_attributes(path)
    assert sorted(attrs) == sorted((n, t) for n in ("prediction", "kappa") for t in (0.0, 0.5, 1.0))
    xy = geometry.reshape(-1, 2)
    exact = _linear(xy.T)
    for t, scale in ((0.0, 1.0), (0.5, 2.0), (1.0, -1.0)):
        values, center = attrs[("prediction", t)]
        assert center == "Node" and values.shape == (len(xy), 1)
        # a linear field: its P1 interpolant at the nodes is exact
        np.testing.assert_allclose(values[:, 0], scale * exact, rtol=0, atol=1e-12)
    kappa, center = attrs[("kappa", 1.0)]
    assert center == "Cell"
    # (the XML holds 16 significant digits)
    np.testing.assert_allclose(kappa[:, 0], poisson_p2.interpolate(smooth, "kappa"), rtol=1e-15, atol=0)


def test_xdmf_vector_field_and_hdf5(tmp_path, stokes):
    velocity = np.zeros(stokes.output_size)
    dofs = stokes.fields["u"]
    coords = stokes.dof_coordinates("f")          # velocity nodes (f lives on the velocity space)
    velocity[dofs[0::2]] = _linear(coords.T)
    velocity[dofs[1::2]] = coords[:, 0]
    path = io.write_fields(tmp_path / "flow", stokes, {"pred": velocity}, encoding="ascii")
    attrs, geometry = _ascii_attributes(path)
    assert sorted(attrs) == [("pred_p", 0.0), ("pred_u", 0.0)]
    values, _ = attrs[("pred_u", 0.0)]
    xy = geometry.reshape(-1, 2)
    np.testing.assert_allclose(values[:, 0], _linear(xy.T), atol=1e-12)
    np.testing.assert_allclose(values[:, 1], xy[:, 0], atol=1e-12)
    np.testing.assert_array_equal(attrs[("pred_p", 0.0)][0], 0.0)

    h5 = io.write_fields(tmp_path / "flow_h5", stokes, {"pred": velocity})
    assert (tmp_path / "flow_h5.h5").read_bytes()[:8] == b"\x89HDF\r\n\x1a\n"
    items = [item.text.strip() for item in ET.parse(h5).getroot().iter("DataItem")]
    assert "flow_h5.h5:/Function/pred_u/0" in items and "flow_h5.h5:/Function/pred_p/0" in items


def test_write_xdmf_errors(tmp_path, poisson_p2, stokes):
    fn = poisson_p2.to_function(np.zeros(poisson_p2.output_size))
    with pytest.raises(ValueError, match=r"every field needs one Function per time step \(or one for all steps\); "
                                         r"got \{'a': 2, 'b': 3\} Functions"):
        io.write_xdmf(tmp_path / "x", {"a": [fn, fn], "b": [fn, fn, fn]})
    with pytest.raises(ValueError, match=r"times must hold 2 finite values .* got \[0.0\]"):
        io.write_xdmf(tmp_path / "x", {"a": [fn, fn]}, times=[0.0])
    with pytest.raises(ValueError, match="field 'w' is on a mixed space; write its parts instead"):
        io.write_xdmf(tmp_path / "x", {"w": stokes.to_function(np.zeros(stokes.output_size))})
    with pytest.raises(ValueError, match=r"encoding must be one of \['hdf5', 'ascii'\], got 'vtk'"):
        io.write_xdmf(tmp_path / "x", fn, encoding="vtk")


def test_plot_fields_png_and_its_refusal(tmp_path, poisson_p2, stokes):
    import matplotlib

    before = matplotlib.get_backend()
    matplotlib.use("svg")                                # a caller's own (non-PNG) backend
    try:
        u = poisson_p2.interpolate(_linear)
        png = io.plot_fields(tmp_path / "p.png", poisson_p2, {"u": u, "kappa": poisson_p2.interpolate(smooth, "kappa"),
                                                              "flow": ("f", np.ones(poisson_p2.control_size("f")))})
        assert matplotlib.get_backend() == "svg"         # left alone: the figure is drawn without pyplot
    finally:
        matplotlib.use(before)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert io.plot_fields(tmp_path / "s.png", stokes, {"w": np.ones(stokes.output_size)}).stat().st_size > 1000
    with pytest.raises(ValueError, match=r"same_scale names \['v'\], which are not labels of values \['u'\]"):
        io.plot_fields(tmp_path / "x.png", poisson_p2, {"u": u}, same_scale=("u", "v"))
    box = forms.poisson.problem(mesh.load("box", h=0.5), controls=("f",))
    with pytest.raises(ValueError, match="plot_fields draws 2D meshes on one process; write XDMF"):
        io.plot_fields(tmp_path / "b.png", box, {"u": np.zeros(box.output_size)})
    assert not (tmp_path / "b.png").exists()


def test_plot_data_is_signed_nodal_or_per_cell(poisson_p2, stokes, coarse):
    xy, triangles, data, per_cell, vector = io.plot_data(poisson_p2, "u", -poisson_p2.interpolate(_linear))
    assert not per_cell and not vector and triangles.shape[1] == 3 and data.min() < 0
    np.testing.assert_allclose(data, -_linear(xy.T), atol=1e-12)          # signed values at the P1 nodes
    _, triangles, kappa, per_cell, _ = io.plot_data(poisson_p2, "kappa", poisson_p2.interpolate(smooth, "kappa"))
    assert per_cell and kappa.shape == (len(triangles),)
    np.testing.assert_allclose(kappa, poisson_p2.interpolate(smooth, "kappa"), rtol=1e-15)
    w = np.zeros(stokes.output_size)
    w[stokes.fields["u"][0::2]], w[stokes.fields["u"][1::2]] = 3.0, -4.0
    _, _, speed, _, vector = io.plot_data(stokes, "flow", w)
    assert vector
    np.testing.assert_allclose(speed, 5.0, rtol=1e-14)


@pytest.mark.parametrize("schedule", [None, ("revolve", 2)])
def test_a_rollout_writes_its_time_series_step_by_step(tmp_path, coarse, schedule):
    """Every second state of a 5-step heat rollout with a varying dt and the last one, at t_k = dt_0 + ... +
    dt_k-1, with the values the rollout returns; a schedule's recomputed steps write nothing more."""
    from fempdl import Rollout, SolveLayer

    step = SolveLayer(forms.heat.problem(coarse, controls=("u0", "f")), "lu")
    rollout = Rollout(step, "u0", schedule=schedule)
    n = step.problem.output_size
    u0 = torch.linspace(0, 1, n, dtype=torch.float64).requires_grad_()
    f = torch.ones(2, step.problem.control_size("f"), dtype=torch.float64)
    dts = [0.1, 0.2, 0.05, 0.3, 0.1]
    with TimeSeries(tmp_path / "heat", step.problem, every=2, sample=1, encoding="ascii") as series:
        states = rollout(u0, 5, constants={"dt": dts}, f=f, series=series)
        states[:, -1].sum().backward()
    assert series.times == pytest.approx([0.0, 0.3, 0.65, 0.75])
    attrs, _ = _ascii_attributes(tmp_path / "heat.xdmf")
    assert sorted(t for _, t in attrs) == pytest.approx([0.0, 0.3, 0.65, 0.75])
    for k, t in zip((0, 2, 4, 5), series.times):
        written = next(v for (name, s), v in attrs.items() if name == "u" and abs(s - t) < 1e-12)
        # P1 values in node order: the same numbers as the state's DOF values
        np.testing.assert_allclose(np.sort(written[0][:, 0]), np.sort(states[1, k].detach().numpy()), atol=1e-14)


def test_time_series_arguments_are_checked(tmp_path, coarse):
    prob = forms.heat.problem(coarse, controls=("u0",))
    with pytest.raises(ValueError, match="every"):
        TimeSeries(tmp_path / "x", prob, every=0)
    with pytest.raises(ValueError, match="encoding"):
        TimeSeries(tmp_path / "x", prob, encoding="csv")
    with TimeSeries(tmp_path / "x", prob, sample=3) as series, pytest.raises(ValueError, match="3"):
        series.write(0, 0.0, np.zeros((2, prob.output_size)))


@pytest.mark.parametrize("schedule", [None, ("revolve", 2)])
def test_every_k_also_writes_the_last_state(tmp_path, coarse, schedule):
    """10 steps every 4th: states 0, 4, 8 and the last one, 10, at its own time and with its own values."""
    from fempdl import Rollout, SolveLayer

    step = SolveLayer(forms.heat.problem(coarse, controls=("u0", "f")), "lu")
    u0 = torch.linspace(0, 1, step.problem.output_size, dtype=torch.float64)
    f = torch.ones(step.problem.control_size("f"), dtype=torch.float64)
    with TimeSeries(tmp_path / "heat", step.problem, every=4, encoding="ascii") as series:
        states = Rollout(step, "u0", schedule=schedule)(u0, 10, constants={"dt": [0.01] * 10}, f=f, series=series)
        assert series.times == pytest.approx([0.0, 0.04, 0.08, 0.1], abs=1e-15)    # written as the rollout ends
    assert series.times == pytest.approx([0.0, 0.04, 0.08, 0.1], abs=1e-15)
    attrs, _ = _ascii_attributes(tmp_path / "heat.xdmf")
    assert sorted(t for _, t in attrs) == pytest.approx([0.0, 0.04, 0.08, 0.1], abs=1e-15)
    last = next(v for (_, t), v in attrs.items() if t == pytest.approx(0.1, abs=1e-15))
    np.testing.assert_allclose(np.sort(last[0][:, 0]), np.sort(states[10].numpy()), rtol=0, atol=1e-14)


def test_time_series_refuses_to_replace_existing_files(tmp_path, coarse):
    """An existing u.xdmf, or the user's data.h5 that TimeSeries("data.h5") would write its values into, stays
    as it was unless overwrite=True."""
    prob = forms.heat.problem(coarse, controls=("u0",))
    u = np.ones(prob.output_size)
    (tmp_path / "u.xdmf").write_text("mine")
    (tmp_path / "data.h5").write_bytes(b"my data")
    with pytest.raises(ValueError, match=rf"^TimeSeries path '{tmp_path}/u' would replace the existing "
                                         rf"'{tmp_path}/u.xdmf' \(it writes '{tmp_path}/u.xdmf' and "
                                         rf"'{tmp_path}/u.h5'\); pass overwrite=True to replace, or give another "
                                         r"path$"):
        TimeSeries(tmp_path / "u", prob).write(0, 0.0, u)
    with pytest.raises(ValueError, match=rf"^TimeSeries path '{tmp_path}/data.h5' would replace the existing "
                                         rf"'{tmp_path}/data.h5' \(it writes '{tmp_path}/data.xdmf' and "
                                         rf"'{tmp_path}/data.h5'\); pass overwrite=True"):
        TimeSeries(tmp_path / "data.h5", prob).write(0, 0.0, u)
    assert (tmp_path / "u.xdmf").read_text() == "mine" and (tmp_path / "data.h5").read_bytes() == b"my data"
    assert not (tmp_path / "data.xdmf").exists()
    series = TimeSeries(tmp_path / "u", prob, encoding="ascii")      # ASCII writes no .h5: only u.xdmf counts
    with pytest.raises(ValueError, match=r"the existing '[^']*u\.xdmf' \(it writes '[^']*u\.xdmf'\); pass"):
        series.write(0, 0.0, u)
    (tmp_path / "u.xdmf").unlink()
    with series:
        series.write(0, 0.0, u)                                          # the refused write, given again
    assert series.times == [0.0]
    with TimeSeries(tmp_path / "data.h5", prob, overwrite=True) as series:    # the refusal left no lock behind
        series.write(0, 0.0, u)
    assert (tmp_path / "data.h5").read_bytes()[:8] == b"\x89HDF\r\n\x1a\n"
    with pytest.raises(TypeError, match="overwrite must be True or False, got 'yes'"):
        TimeSeries(tmp_path / "u", prob, overwrite="yes")


def test_a_reused_time_series_never_repeats_times(tmp_path, coarse):
    """A second run of steps into one series, or a write after close: refused, the file keeping one value per
    time (the first run's last state included); with overwrite=True the file starts afresh instead."""
    prob = forms.heat.problem(coarse, controls=("u0",))
    u = np.ones(prob.output_size)
    path = tmp_path / "u.xdmf"
    series = TimeSeries(path, prob, every=2, encoding="ascii")
    for k in range(4):
        series.write(k, 0.1 * k, k * u)
    with pytest.raises(ValueError, match=rf"^TimeSeries '{path}' already holds times up to t=0\.3, so a write at "
                                         r"t=0 would repeat times \(a second rollout into one series\?\); give each "
                                         r"rollout its own TimeSeries \(or path\), or pass overwrite=True to start "
                                         r"the file afresh$"):
        series.write(0, 0.0, u)
    series.close()
    with pytest.raises(ValueError, match=rf"^TimeSeries '{path}' is closed and holds times up to t=0\.3; writing "
                                         r"again would replace them: open a new TimeSeries on another path, or "
                                         r"pass overwrite=True to start the file afresh$"):
        series.write(4, 0.4, u)
    attrs, _ = _ascii_attributes(path)
    assert series.times == pytest.approx([0.0, 0.2, 0.3]) and sorted(t for _, t in attrs) == series.times
    np.testing.assert_allclose(next(v for (_, t), v in attrs.items() if t == pytest.approx(0.3))[0], 3.0, atol=1e-14)

    with TimeSeries(path, prob, encoding="ascii", overwrite=True) as again:
        for run in range(2):
            for k in range(3):
                again.write(k, 0.1 * k, (10 * run + k) * u)
    with again:
        again.write(0, 0.0, -u)                          # after close: afresh too
    attrs, _ = _ascii_attributes(path)
    assert again.times == [0.0] and list(attrs) == [("u", 0.0)]
    np.testing.assert_allclose(attrs[("u", 0.0)][0], -1.0, rtol=0, atol=1e-15)


def test_a_busy_path_names_who_holds_it(tmp_path, coarse):
    """An unclosed TimeSeries of this process blocks its path with a message saying so; one held by another
    process names that process."""
    import socket
    import subprocess
    import sys

    prob = forms.heat.problem(coarse, controls=("u0",))
    u = np.ones(prob.output_size)
    first = TimeSeries(tmp_path / "u", prob, encoding="ascii")
    first.write(0, 0.0, u)
    with pytest.raises(ValueError, match=rf"^'{tmp_path}/u\.xdmf' is held by a TimeSeries in this process that is "
                                         r"still open; close it \(series\.close\(\)\) or write it inside `with "
                                         r"TimeSeries\(\.\.\.\) as series:`, or use another path$"):
        TimeSeries(tmp_path / "u", prob).write(0, 0.0, u)
    first.close()
    with TimeSeries(tmp_path / "u", prob, overwrite=True) as second:
        second.write(0, 0.0, u)

    holder = ("import fcntl, os, socket, sys\n"
              "fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT)\n"
              "fcntl.flock(fd, fcntl.LOCK_EX)\n"
              "os.write(fd, f'{socket.gethostname()} {os.getpid()} TimeSeries'.encode())\n"
              "print('holding', flush=True)\n"
              "sys.stdin.read()\n")
    other = subprocess.Popen([sys.executable, "-c", holder, str(tmp_path / ".v.xdmf.writing")],
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert other.stdout.readline() == "holding\n"
        with pytest.raises(ValueError, match=rf"^another process is writing '{tmp_path}/v\.xdmf' at this moment "
                                             rf"\(process {other.pid} on {socket.gethostname()}, TimeSeries\): a "
                                             r"TimeSeries there still open on that path, or every rank of a "
                                             r"data-parallel run writing one file\?; close that TimeSeries"):
            TimeSeries(tmp_path / "v", prob).write(0, 0.0, u)
    finally:
        other.communicate("", timeout=30)
