"""Bundled meshes: sizes, tags, measured areas/volumes, loading by path, errors, wheel data."""
import math
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

from mpi4py import MPI
import dolfinx.fem
import dolfinx.mesh
import gmsh
import numpy as np
import pytest
import ufl
from petsc4py import PETSc

from fempdl import mesh
from fempdl.core import meshgen

PROJECT_ROOT = Path(__file__).resolve().parents[1]
COMM = MPI.COMM_WORLD
serial_only = pytest.mark.skipif(COMM.size > 1, reason="packaging does not depend on MPI; build once")

# name -> (tdim, gdim, cell-count range promised for the bundled file)
EXPECTED_SHAPE = {
    "lshape": (2, 2, (1500, 4000)),
    "obstacle": (2, 2, (1500, 4000)),
    "box": (3, 3, (3000, 8000)),
}
CHANNEL_AREA = 2.2 * 0.41 - math.pi * 0.05**2
# name -> exact area/volume (channel: of the true circular hole)
EXACT_MEASURE = {"lshape": 3.0, "obstacle": CHANNEL_AREA, "box": 1.0}
# name -> {facet label: exact length/area of that boundary piece}
EXACT_BOUNDARY = {
    "lshape": {"outer": 6.0, "reentrant": 2.0},
    "obstacle": {"inlet": 0.41, "outlet": 0.41, "walls": 4.4, "obstacle": 2 * math.pi * 0.05},
    "box": {"bottom": 1.0, "top": 1.0, "sides": 4.0},
}


def integrate(msh, measure) -> float:
    one = dolfinx.fem.Constant(msh, PETSc.ScalarType(1.0))
    return COMM.allreduce(dolfinx.fem.assemble_scalar(dolfinx.fem.form(one * measure)), op=MPI.SUM)


def global_cells(msh) -> int:
    return msh.topology.index_map(msh.topology.dim).size_global


def write_unit_square(path: Path, *, named: bool, physical: bool = True) -> Path:
    """A small gmsh unit square; facets tagged 5, cells 7, names only if ``named``."""
    with meshgen.gmsh_session():
        gmsh.model.occ.addRectangle(0.0, 0.0, 0.0, 1.0, 1.0)
        gmsh.model.occ.synchronize()
        if physical:
            gmsh.model.addPhysicalGroup(2, [1], 7)
            gmsh.model.addPhysicalGroup(1, [1, 2, 3, 4], 5)
            if named:
                gmsh.model.setPhysicalName(1, 5, "boundary")
        gmsh.option.setNumber("Mesh.MeshSizeMax", 0.25)
        gmsh.model.mesh.generate(2)
        gmsh.write(str(path))
    return path


@pytest.fixture(scope="module", params=mesh.available())
def bundled(request):
    return mesh.load(request.param, COMM)


def test_available_lists_the_three_bundled_meshes():
    assert mesh.available() == ["lshape", "obstacle", "box"]


def test_bundled_shape_and_size(bundled):
    tdim, gdim, (low, high) = EXPECTED_SHAPE[bundled.name]
    assert (bundled.tdim, bundled.gdim) == (tdim, gdim)
    assert bundled.mesh.geometry.x.shape[1] == 3  # DOLFINx pads coordinates to 3
    assert bundled.comm is not None
    assert low <= global_cells(bundled.mesh) <= high


def test_bundled_unpacks_to_mesh_and_tags(bundled):
    msh, cell_tags, facet_tags = bundled
    assert msh is bundled.mesh
    assert cell_tags.dim == bundled.tdim and facet_tags.dim == bundled.tdim - 1


def test_every_cell_has_the_domain_tag(bundled):
    msh, cell_tags, _ = bundled
    n_local = msh.topology.index_map(msh.topology.dim).size_local
    assert np.array_equal(np.unique(cell_tags.values), [meshgen.CELL_TAG])
    assert np.array_equal(np.sort(cell_tags.indices[cell_tags.indices < n_local]), np.arange(n_local))


def test_every_exterior_facet_tagged_exactly_once(bundled):
    msh, _, facet_tags = bundled
    fdim = msh.topology.dim - 1
    msh.topology.create_connectivity(fdim, msh.topology.dim)
    # Compared on owned facets: in parallel the tags also cover ghost facets.
    n_owned = msh.topology.index_map(fdim).size_local
    exterior = dolfinx.mesh.exterior_facet_indices(msh.topology)
    tagged = facet_tags.indices[facet_tags.indices < n_owned]
    assert len(np.unique(facet_tags.indices)) == len(facet_tags.indices)
    assert np.array_equal(np.sort(tagged), np.sort(exterior[exterior < n_owned]))


def test_facet_tag_values_match_the_documented_ones(bundled):
    documented = meshgen.FACET_TAGS[bundled.name]
    assert dict(bundled.facet_labels) == documented
    present = set().union(*COMM.allgather(set(np.unique(bundled.facet_tags.values).tolist())))
    assert present == set(documented.values())
    for label, tag in documented.items():
        assert bundled.facet_tag(label) == tag


def test_domain_measure_matches_geometry(bundled):
    measure = integrate(bundled.mesh, ufl.dx(domain=bundled.mesh))
    exact = EXACT_MEASURE[bundled.name]
    if bundled.name == "obstacle":
        # The inscribed polygon of the hole is smaller than the disk, by
        # about pi r^2 (2 pi / n)^2 / 6 ~ 1e-4 for n ~ 27 boundary edges.
        assert 0.0 < measure - exact < 2e-4
    else:
        assert measure == pytest.approx(exact, rel=1e-12)


def test_boundary_pieces_have_the_exact_size(bundled):
    ds = ufl.Measure("ds", domain=bundled.mesh, subdomain_data=bundled.facet_tags)
    for label, exact in EXACT_BOUNDARY[bundled.name].items():
        size = integrate(bundled.mesh, ds(bundled.facet_tag(label)))
        if label == "obstacle":
            # Polygon perimeter: 2 pi r (1 - (pi / n)^2 / 6) for n edges.
            assert exact * (1 - 5e-3) < size < exact
        else:
            assert size == pytest.approx(exact, rel=1e-12)


def test_generate_at_default_h_reproduces_the_committed_file():
    generated, _, _ = meshgen.generate("lshape", comm=COMM)
    committed = global_cells(mesh.load("lshape", COMM).mesh)
    if tuple(int(p) for p in gmsh.__version__.split(".")[:2]) == meshgen.COMMITTED_WITH_GMSH:
        assert global_cells(generated) == committed
    else:   # another gmsh release: the same size, a slightly different mesh
        assert abs(global_cells(generated) - committed) <= 0.01 * committed


def test_larger_h_gives_fewer_cells_at_the_h_squared_rate():
    default_cells = global_cells(mesh.load("lshape", COMM).mesh)
    coarse = mesh.load("lshape", COMM, h=2 * meshgen.DEFAULT_H["lshape"])
    assert coarse.name == "lshape" and coarse.facet_tag("reentrant") == 2
    assert 3.0 < default_cells / global_cells(coarse.mesh) < 5.0


def test_smaller_h_gives_more_cells_in_3d():
    fine = mesh.load("box", COMM, h=0.08)
    assert global_cells(fine.mesh) > global_cells(mesh.load("box", COMM).mesh)
    assert integrate(fine.mesh, ufl.dx(domain=fine.mesh)) == pytest.approx(1.0, rel=1e-12)


def test_write_msh_round_trips_through_load(tmp_path):
    path = meshgen.write_msh("obstacle", tmp_path / "coarse.msh", h=0.1)
    loaded = mesh.load(path, COMM)
    assert loaded.name == str(path) and loaded.gdim == 2
    assert loaded.facet_tag("obstacle") == 4  # physical names travel in the file
    assert global_cells(loaded.mesh) == global_cells(meshgen.generate("obstacle", 0.1, COMM)[0])


def test_load_by_path_of_a_bundled_file_matches_load_by_name():
    by_path = mesh.load(str(meshgen.BUNDLED_DIR / "box.msh"), COMM)
    assert (by_path.tdim, by_path.gdim) == (3, 3)
    assert global_cells(by_path.mesh) == global_cells(mesh.load("box", COMM).mesh)


def test_user_file_without_names_has_tags_but_no_labels(tmp_path):
    loaded = mesh.load(write_unit_square(tmp_path / "square.msh", named=False), COMM)
    assert loaded.gdim == 2  # all z = 0 detected
    assert np.array_equal(np.unique(loaded.facet_tags.values), [5])
    assert np.array_equal(np.unique(loaded.cell_tags.values), [7])
    with pytest.raises(ValueError, match="label 'boundary'.*no named facet tags"):
        loaded.facet_tag("boundary")


def test_user_file_with_names_and_explicit_gdim(tmp_path):
    loaded = mesh.load(write_unit_square(tmp_path / "square.msh", named=True), COMM, gdim=3)
    assert loaded.gdim == 3 and loaded.tdim == 2
    assert loaded.facet_tag("boundary") == 5
    assert integrate(loaded.mesh, ufl.dx(domain=loaded.mesh)) == pytest.approx(1.0, rel=1e-12)


def test_as_tagged_accepts_tagged_and_bare_meshes():
    tagged = mesh.load("lshape", COMM)
    assert mesh.as_tagged(tagged) is tagged
    bare = mesh.as_tagged(tagged.mesh)
    assert bare.mesh is tagged.mesh and bare.cell_tags is None and bare.facet_tags is None
    with pytest.raises(ValueError, match="label"):
        bare.facet_tag("outer")


def test_tagged_mesh_is_immutable():
    tagged = mesh.load("lshape", COMM)
    with pytest.raises(AttributeError):
        tagged.name = "other"
    with pytest.raises(TypeError):
        tagged.facet_labels["outer"] = 3


@pytest.mark.parametrize(
    "kwargs, error, pattern",
    [
        ({"name_or_path": "lshap"}, ValueError, r"name_or_path.*'lshape', 'obstacle', 'box'.*\.msh.*'lshap'"),
        ({"name_or_path": 3}, TypeError, "name_or_path must be a str or os.PathLike, got int"),
        ({"name_or_path": "no/such/mesh.msh"}, FileNotFoundError, "name_or_path.*no/such/mesh.msh"),
        ({"name_or_path": "lshape", "h": 0.0}, ValueError, "h must be a finite mesh size > 0, got 0.0"),
        ({"name_or_path": "lshape", "h": -0.1}, ValueError, "h must be .*-0.1"),
        ({"name_or_path": "lshape", "h": float("nan")}, ValueError, "h must be .*nan"),
        ({"name_or_path": "lshape", "h": float("inf")}, ValueError, "h must be .*inf"),
        ({"name_or_path": "lshape", "h": "0.1"}, TypeError, "h must be a positive float or None, got str"),
        ({"name_or_path": "lshape", "gdim": 3}, ValueError, "gdim applies to .msh files only"),
        ({"name_or_path": "lshape", "rank": 99}, ValueError, r"rank must be one of \[0.*got 99"),
        ({"name_or_path": "lshape", "rank": 0.0}, TypeError, "rank must be an int, got float"),
    ],
)
def test_load_errors_name_the_argument(kwargs, error, pattern):
    with pytest.raises(error, match=pattern):
        mesh.load(comm=COMM, **kwargs)


def test_a_msh_path_that_is_not_a_regular_file_is_named_for_what_it_is(tmp_path):
    """A directory or a FIFO named like a mesh: said so (not "no such file"), and a FIFO is never opened,
    neither by load nor by source_digest (a run's fingerprint), which would wait for a writer forever."""
    import threading

    folder, fifo = tmp_path / "folder.msh", tmp_path / "pipe.msh"
    folder.mkdir()
    os.mkfifo(fifo)
    with pytest.raises(IsADirectoryError, match=rf"^name_or_path: '{folder}' is a directory, not a \.msh file; "
                                                r"give the path of a \.msh file$"):
        mesh.load(folder, COMM)
    with pytest.raises(ValueError, match=rf"^name_or_path: '{fifo}' is not a regular file \(a FIFO\); save the "
                                         r"mesh to a \.msh file and give its path$"):
        mesh.load(fifo, COMM)
    (tmp_path / "plain").write_text("")
    with pytest.raises(FileNotFoundError, match="no such .msh file"):
        mesh.load(tmp_path / "plain" / "inner.msh", COMM)            # a file where a directory should be
    digests = {}
    reader = threading.Thread(target=lambda: digests.update(fifo=mesh.source_digest(fifo),
                                                            folder=mesh.source_digest(folder)), daemon=True)
    reader.start()
    reader.join(10)
    if reader.is_alive():
        os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))      # let the blocked reader go
        reader.join()
        pytest.fail("source_digest blocked opening a FIFO")
    assert digests == {"fifo": None, "folder": None}


def test_load_errors_for_paths(tmp_path):
    square = write_unit_square(tmp_path / "square.msh", named=False)
    with pytest.raises(ValueError, match="h applies to bundled meshes only, got h=0.1"):
        mesh.load(square, COMM, h=0.1)
    with pytest.raises(ValueError, match=r"gdim must be one of \[1, 2, 3\], got 4"):
        mesh.load(square, COMM, gdim=4)
    with pytest.raises(TypeError, match="gdim must be an int, got str"):
        mesh.load(square, COMM, gdim="2")
    with pytest.raises(ValueError, match="gdim must be >= the mesh's topological dimension 2, got 1"):
        mesh.load(square, COMM, gdim=1)
    other_format = tmp_path / "square.vtk"
    other_format.write_text("")
    with pytest.raises(ValueError, match="name_or_path must be a gmsh .msh file"):
        mesh.load(other_format, COMM)
    garbage = tmp_path / "garbage.msh"
    garbage.write_text("not a mesh\n")
    with pytest.raises(ValueError, match="name_or_path: gmsh cannot read"):
        mesh.load(garbage, COMM)
    untagged = write_unit_square(tmp_path / "untagged.msh", named=False, physical=False)
    with pytest.raises(ValueError, match="name_or_path: .* has no physical groups"):
        mesh.load(untagged, COMM)


def test_other_errors_name_the_argument():
    with pytest.raises(TypeError, match="mesh must be a fempdl.core.mesh.TaggedMesh .* got str"):
        mesh.as_tagged("lshape")
    obstacle = mesh.load("obstacle", COMM)
    with pytest.raises(ValueError, match=r"label must be one of \['inlet', 'obstacle', 'outlet', 'walls'\]"):
        obstacle.facet_tag("inflow")
    with pytest.raises(TypeError, match="label must be a str"):
        obstacle.facet_tag(1)
    with pytest.raises(ValueError, match="name must be one of the bundled meshes"):
        meshgen.generate("square", comm=COMM)
    with pytest.raises(ValueError, match="h must be"):
        meshgen.write_msh("box", "unused.msh", h=-1.0)


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    """A wheel built from a copy of the project (keeps build/ out of the tree)."""
    src = tmp_path_factory.mktemp("src")
    for item in PROJECT_ROOT.iterdir():
        if item.is_file():
            shutil.copy2(item, src)
    for folder in ("fempdl", "meshes"):
        shutil.copytree(PROJECT_ROOT / folder, src / folder, ignore=shutil.ignore_patterns("__pycache__"))
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
                    "-w", str(out), str(src)], check=True)
    (path,) = out.glob("fempdl-*.whl")
    return path


@serial_only
def test_wheel_contains_the_bundled_meshes(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    for name in mesh.available():
        assert f"fempdl/meshes/{name}.msh" in names
    assert "fempdl/core/meshgen.py" in names


@serial_only
def test_bundled_mesh_loads_from_the_unpacked_wheel(wheel, tmp_path):
    site = tmp_path / "site"
    zipfile.ZipFile(wheel).extractall(site)
    code = ("import fempdl.core.mesh as m; t = m.load('obstacle'); "
            "print(m.__file__); print(t.mesh.topology.index_map(2).size_global)")
    result = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(site)},
                            capture_output=True, text=True, check=True)
    module_file, cells = result.stdout.split()
    assert Path(module_file).is_relative_to(site)
    assert int(cells) == global_cells(mesh.load("obstacle", COMM).mesh)


def test_loading_a_mesh_keeps_the_openmp_thread_count():
    """gmsh resets OpenMP's thread count when it starts; torch shares that runtime."""
    torch = pytest.importorskip("torch")
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        mesh.load("lshape", COMM, h=0.3)
        mesh.load("lshape", COMM)
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
