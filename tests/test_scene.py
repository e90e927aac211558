"""Scene files: the bundled scenes, every way a scene can be malformed, and the defaults."""
from __future__ import annotations

import dataclasses
import math
import re
from importlib import resources
from pathlib import Path

import pytest

from fempdl.app import scene, schema, tasks
from fempdl.app.scene import SceneError

EXPECTED_BUNDLED = {"heat-emulator-2d", "heat-emulator-3d", "poisson-inverse", "poisson-inverse-3",
                    "burgers-emulator", "ns-hybrid", "sip-poisson", "sip-heat", "hig-poisson", "sip-flow",
                    "sip-flow-full", "nonlinear-heat-emulator", "sip-nonlinear", "hig-nonlinear"}

EMULATOR = {"scene": 'name = "t"\ntask = "emulator"', "mesh": 'name = "lshape"', "pde": 'type = "heat"'}
INVERSE = {"scene": 'name = "t"\ntask = "inverse"', "mesh": 'name = "lshape"', "pde": 'type = "poisson"',
           "inverse": "theta_ref = [2.0]\ntheta_init = [5.0]"}
HYBRID = {"scene": 'name = "t"\ntask = "hybrid"', "mesh": 'name = "obstacle"', "pde": 'type = "oseen"',
          "hybrid": "fine_h = 0.05", "solver": 'preset = "schur"'}
BURGERS = {**EMULATOR, "pde": 'type = "burgers"', "solver": 'preset = "gmres"'}
SIP = {"scene": 'name = "t"\ntask = "sip"', "mesh": 'name = "lshape"', "pde": 'type = "poisson"',
       "sip": 'inverse = "exact"'}
HIG = {"scene": 'name = "t"\ntask = "hig"', "mesh": 'name = "lshape"', "pde": 'type = "poisson"', "hig": "lr = 0.5"}


def toml(extra: dict | None = None, *, base: dict = EMULATOR, drop: tuple = ()) -> str:
    """Scene text: ``base``'s sections without ``drop``, with ``extra`` lines appended per section."""
    sections = {name: body for name, body in base.items() if name not in drop}
    for name, body in (extra or {}).items():
        sections[name] = (sections.get(name, "") + "\n" + body).strip()
    return "\n".join(f"[{name}]\n{body}\n" for name, body in sections.items())


def assert_scene_error(text: str, *fragments: str, source: str = "<string>") -> SceneError:
    with pytest.raises(SceneError, match=re.escape(fragments[0])) as info:
        scene.parse(text, source=source)
    message = str(info.value)
    for fragment in fragments[1:]:
        assert fragment in message, f"{fragment!r} not in {message!r}"
    assert message.startswith(f"{source}: "), message
    return info.value


# ------------------------------------------------------------------ bundled scenes
def test_available_lists_the_bundled_files():
    names = scene.available()
    assert names == sorted(names)
    assert EXPECTED_BUNDLED <= set(names)
    files = {p.name[:-5] for p in resources.files("fempdl.app.scenes").iterdir() if p.name.endswith(".toml")}
    assert set(names) == files


def _keys_for(sc, section: str) -> set:
    """The schema's keys of a section, less those the scene's task and PDE do not use."""
    unused = [tasks.spec_of(sc.task).unused, schema.PDE_UNUSED.get(sc.pde.type, {})]
    return set(schema.specs(section)).difference(*(by_section.get(section, set()) for by_section in unused))


@pytest.mark.parametrize("name", scene.available())
def test_bundled_scene_loads_with_its_tasks_sections(name):
    sc = scene.load(name)
    assert sc.name == name
    assert sc.source == f"bundled:{name}"
    assert sc.description.strip()
    assert sc.task in ("emulator", "inverse", "hybrid", "sip", "hig")
    assert sc.mesh.name
    sections = ("mesh", "pde", "data", "optimizer") + (("network", "baseline")
                                                       if tasks.spec_of(sc.task).trains == "method"
                                                       else ("solver", "prdp"))
    for section in sections:
        assert set(sc.as_dict()[section]) == _keys_for(sc, section), section
    if tasks.spec_of(sc.task).trains == "method":
        assert sc.solver is None and sc.prdp is None and sc.inverse is None
        assert (sc.sip is not None, sc.hig is not None) == (sc.task == "sip", sc.task == "hig")
        assert sc.optimizer.batch <= sc.data.train
        assert sc.baseline.lr > 0
    elif sc.task in ("emulator", "hybrid"):
        assert sc.inverse is None
        assert set(sc.as_dict()["network"]) == set(schema.specs("network"))
        assert sc.network.type in ("mlp", "graph")
        assert sc.pde.type in {"emulator": ("heat", "burgers", "nonlinear-heat"), "hybrid": ("oseen",)}[sc.task]
        assert (sc.hybrid is not None) == (sc.task == "hybrid")
        # Every training sample passes the layer once per epoch in batches that fit.
        assert sc.optimizer.batch <= sc.data.train
    else:
        assert sc.network is None
        theta_ref, theta_init = sc.inverse.theta_ref, sc.inverse.theta_init
        assert len(theta_ref) == len(theta_init) >= 1
        assert all(type(v) is float and math.isfinite(v) for v in theta_ref + theta_init)
        assert theta_ref != theta_init
        assert sc.pde.type == "poisson"
        assert sc.optimizer.stop_at is not None and sc.optimizer.stop_at > 0
    if sc.prdp is not None:
        if sc.prdp.k_cap is not None:
            assert sc.prdp.k_cap >= sc.prdp.k0
        assert 0 < sc.prdp.tau_stop <= 1 and 0 < sc.prdp.tau_step <= 1


@pytest.mark.parametrize("name", scene.available())
def test_bundled_scene_by_path_equals_by_name(name):
    path = Path(str(resources.files("fempdl.app.scenes").joinpath(f"{name}.toml")))
    by_path, by_name = scene.load(path), scene.load(name)
    assert by_path.source == str(path)
    assert {**by_path.as_dict(), "source": ""} == {**by_name.as_dict(), "source": ""}


def test_bundled_values():
    two_d = scene.load("heat-emulator-2d")
    assert (two_d.mesh.name, two_d.mesh.h, two_d.network.type) == ("lshape", None, "mlp")
    assert scene.load("heat-emulator-3d").network.type == "graph"
    assert scene.load("poisson-inverse").as_dict()["inverse"] == {"theta_ref": [2.0], "theta_init": [5.0]}
    three = scene.load("poisson-inverse-3").inverse
    assert len(three.theta_ref) == len(three.theta_init) == 3


def test_a_loaded_scene_is_frozen_and_changed_by_replace():
    first = scene.load("heat-emulator-2d")
    epochs = first.optimizer.epochs
    with pytest.raises(dataclasses.FrozenInstanceError):
        first.optimizer.epochs = epochs + 1000
    with pytest.raises(dataclasses.FrozenInstanceError):
        first.optimizer = None
    # What `fempdl run --epochs` does: a new scene; the loaded one and the next load are unchanged.
    longer = dataclasses.replace(first, optimizer=dataclasses.replace(first.optimizer, epochs=epochs + 1000))
    assert longer.optimizer.epochs == epochs + 1000 and longer.optimizer.lr == first.optimizer.lr
    assert longer.as_dict()["optimizer"]["epochs"] == epochs + 1000
    assert first.optimizer.epochs == scene.load("heat-emulator-2d").optimizer.epochs == epochs
    assert longer.pde is first.pde


def test_schema_text_names_every_section_and_key():
    blocks = {block.split("]")[0]: block for block in scene.schema_text().split("\n[")[1:]}
    assert set(blocks) == set(schema.SECTIONS)
    for name, cls in schema.SECTIONS.items():
        lines = {line.split()[0]: line for line in blocks[name].splitlines()[1:] if line.strip()}
        assert set(lines) == {field.name for field in dataclasses.fields(cls)}, name
        for field in dataclasses.fields(cls):
            spec, line = schema.specs(name)[field.name], lines[field.name]
            assert spec.doc in line and ("required" in line) == spec.required, line
            assert all(f'"{choice}"' in line for choice in spec.choices or ()), line


# ------------------------------------------------------------------ defaults
def test_parse_fills_the_schema_defaults():
    sc = scene.parse(toml())
    assert (sc.name, sc.task, sc.description, sc.source) == ("t", "emulator", "", "<string>")
    assert sc.as_dict()["mesh"] == {"name": "lshape", "h": None}
    # nu, inflow: not heat
    assert sc.as_dict()["pde"] == {"type": "heat", "dt": 0.01, "theta": 1.0, "kappa": 1.0, "degree": 1}
    assert sc.as_dict()["data"] == {"train": 64, "validation": 16, "modes": 4, "seed": 0, "k_eps_rtol": 1e-5,
                                    "rollout": 1, "train_rollout": 1}
    assert sc.as_dict()["network"] == {"type": "mlp", "hidden": 128, "layers": 2}
    assert sc.as_dict()["optimizer"] == {"type": "adam", "lr": 1e-3, "decay": 1.0, "epochs": 30, "batch": 16,
                                         "stop_at": None}
    assert sc.as_dict()["solver"] == {"preset": "jacobi", "diff": "implicit", "warm_start": False,
                                      "lag_preconditioner": False}
    assert sc.as_dict()["prdp"] == {"k0": 1, "dk": 1, "tau_step": 0.95, "tau_stop": 0.9, "delta": 3, "ema_window": 6,
                       "k_cap": None, "guard": None, "growth": 1.5, "judge": "reference", "gap": 0.05,
                                     "remeasure": True, "k_eps_rtol": 1e-8, "health": 1.0, "adjoint_health": 0.01}
    assert sc.inverse is None
    # ... and they are the schema's.
    for section in schema.SECTIONS:
        keys = schema.specs(section)
        values = {"name": sc.name, "task": sc.task, "description": sc.description} if section == "scene" \
            else sc.as_dict()[section]
        if values is None:
            continue
        assert set(values) == _keys_for(sc, section), section
        for key, spec in keys.items():
            if key in values and spec.default is not schema.REQUIRED and (section, key) != ("pde", "degree"):
                assert values[key] == spec.default, (section, key)


def test_method_scene_defaults():
    sip = scene.parse(toml({"optimizer": "lr = 0.02\ndecay = 0.99"}, base=SIP))
    assert sip.solver is None and sip.prdp is None and sip.hig is None
    assert sip.as_dict()["sip"] == {"inverse": "exact", "eta": 1.0, "damping": 0.0, "cg_iterations": 20}
    assert sip.as_dict()["baseline"] == {"lr": 0.02, "decay": 0.99}          # the method's schedule unless given
    own = scene.parse(toml({"optimizer": "lr = 0.02\ndecay = 0.99", "baseline": "lr = 0.1\ndecay = 1.0"}, base=SIP))
    assert own.as_dict()["baseline"] == {"lr": 0.1, "decay": 1.0}
    assert sip.as_dict()["data"] == {"train": 64, "validation": 16, "modes": 4, "seed": 0, "truths": "smooth",
                                     "noise": 0.0, "resample": False}
    assert sip.as_dict()["network"] == {"type": "mlp", "hidden": 128, "layers": 2} and sip.pde.degree == 1
    hig = scene.parse(toml({"network": "layers = 0"}, base=HIG))
    assert hig.as_dict()["baseline"] == {"lr": 1e-3, "decay": 1.0} and hig.network.layers == 0
    assert hig.as_dict()["hig"] == {"lr": 0.5, "kappa": -0.5, "beta": 0.0, "tau": 1e-5, "method": "auto",
                       "max_jacobian_mib": 1024.0}
    assert hig.as_dict()["optimizer"] == {"epochs": 30, "batch": 16, "stop_at": None}


def test_given_values_override_only_their_keys():
    sc = scene.parse(toml({"optimizer": "epochs = 5\nlr = 2", "mesh": "h = 0.2"}), source="mine.toml")
    assert sc.source == "mine.toml"
    assert sc.as_dict()["optimizer"] == {"type": "adam", "lr": 2.0, "decay": 1.0, "epochs": 5, "batch": 16,
                                         "stop_at": None}
    assert type(sc.optimizer.lr) is float  # an int is accepted where a float is expected
    assert sc.as_dict()["mesh"] == {"name": "lshape", "h": 0.2}


def test_flow_defaults():
    hybrid = scene.parse(toml(base=HYBRID))
    assert hybrid.pde.degree == 2  # Taylor-Hood P2-P1
    assert hybrid.as_dict()["hybrid"] == {"fine_h": 0.05, "steps": 2, "spinup": 10, "perturbation": 0.2}
    assert hybrid.as_dict()["network"] == {"type": "mlp", "hidden": 128, "layers": 2}
    burgers = scene.parse(toml(base=BURGERS))
    assert burgers.pde.degree == 1 and burgers.pde.nu == 0.01 and burgers.hybrid is None


def test_inverse_defaults_and_theta_as_floats():
    sc = scene.parse(toml({"inverse": ""}, base={**INVERSE, "inverse": "theta_ref = [2, 0.5]\ntheta_init = [1, 1]"}))
    assert sc.task == "inverse" and sc.network is None
    assert sc.as_dict()["inverse"] == {"theta_ref": [2.0, 0.5], "theta_init": [1.0, 1.0]}
    assert all(type(v) is float for v in sc.inverse.theta_ref + sc.inverse.theta_init)
    assert sc.optimizer.stop_at is None and sc.pde.type == "poisson"


def test_boundary_values_are_accepted():
    sc = scene.parse(toml({"prdp": "delta = 2\nk_cap = 1", "pde": "theta = 0.0", "data": "seed = 0"}))
    assert (sc.prdp.delta, sc.prdp.k_cap, sc.pde.theta) == (2, 1, 0.0)


# ------------------------------------------------------------------ malformed scenes
BAD = {
    # invalid TOML
    "toml-syntax": ("[scene\nname = 't'", ["not valid TOML"]),
    "toml-expression": (toml({"optimizer": "lr = 1e-3 * 2"}), ["not valid TOML"]),
    "toml-duplicate-key": (toml({"scene": 'name = "u"'}), ["not valid TOML"]),
    # unknown section / key
    "unknown-section": (toml({"training": "epochs = 3"}),
                        ["unknown section(s) ['training']", f"allowed sections are {sorted(schema.SECTIONS)}"]),
    "unknown-top-level-key": ('epochs = 3\n' + toml(), ["unknown section(s) ['epochs']"]),
    "unknown-key": (toml({"optimizer": "learning_rate = 0.1"}),
                    ["unknown key(s) ['learning_rate'] in [optimizer]",
                     "allowed keys are ['batch', 'decay', 'epochs', 'lr', 'stop_at', 'type']"]),
    "unknown-key-scene": (toml({"scene": 'author = "me"'}),
                          ["unknown key(s) ['author'] in [scene]", "allowed keys are ['description', 'name', 'task']"]),
    "section-not-table": ('scene = "t"\n' + toml(drop=("scene",)), ["[scene] must be a table, got str"]),
    "array-of-tables": (toml() + '[[optimizer]]\nlr = 0.1\n', ["[optimizer] must be a table, got list"]),
    # wrong types
    "str-for-float": (toml({"optimizer": 'lr = "0.1"'}), ["[optimizer] lr must be of type float, got '0.1' (str)"]),
    "float-for-int": (toml({"optimizer": "epochs = 6.0"}), ["[optimizer] epochs must be of type int, got 6.0 (float)"]),
    "bool-for-int": (toml({"optimizer": "batch = true"}), ["[optimizer] batch must be of type int, got True (bool)"]),
    "bool-for-float": (toml({"pde": "dt = false"}), ["[pde] dt must be of type float, got False (bool)"]),
    "str-for-int": (toml({"network": 'hidden = "64"'}), ["[network] hidden must be of type int, got '64' (str)"]),
    "int-for-str": (toml({"scene": "description = 3"}), ["[scene] description must be of type str, got 3 (int)"]),
    "list-for-str": (toml(drop=("mesh",)) + '[mesh]\nname = ["lshape"]\n',
                     ["[mesh] name must be of type str, got ['lshape'] (list)"]),
    "table-for-float": (toml({"prdp": "tau_step = {value = 0.9}"}),
                        ["[prdp] tau_step must be of type float, got {'value': 0.9} (dict)"]),
    # choices
    "pde-choice": (toml(drop=("pde",)) + '[pde]\ntype = "wave"\n',
                   ["[pde] type must be one of ['heat', 'poisson', 'burgers', 'oseen', 'marker', 'nonlinear-heat', "
                    "'nonlinear-poisson'], got 'wave'"]),
    # PDE and task, solver and network combinations
    "poisson-emulator": (toml(drop=("pde",)) + '[pde]\ntype = "poisson"\n',
                         ["[pde] type 'poisson' does not apply to task 'emulator'; "
                          "it takes ['heat', 'burgers', 'nonlinear-heat']"]),
    "heat-inverse": (toml(base={**INVERSE, "pde": 'type = "heat"'}),
                     ["[pde] type 'heat' does not apply to task 'inverse'; it takes ['poisson']"]),
    "burgers-hybrid": (toml(base={**HYBRID, "pde": 'type = "burgers"', "solver": 'preset = "gmres"'}),
                       ["[pde] type 'burgers' does not apply to task 'hybrid'; it takes ['oseen']"]),
    "oseen-without-schur": (toml(base={**HYBRID, "solver": 'preset = "gmres"'}),
                            ["[solver] preset 'schur' is the saddle-point solver", "(pde 'oseen', preset 'gmres')"]),
    "oseen-default-preset": (toml(base=HYBRID, drop=("solver",)),
                             ["[solver] preset 'schur' is the saddle-point solver", "preset 'jacobi'"]),
    "schur-for-heat": (toml({"solver": 'preset = "schur"'}),
                       ["[solver] preset 'schur' is the saddle-point solver", "(pde 'heat', preset 'schur')"]),
    "oseen-p1": (toml({"pde": "degree = 1"}, base=HYBRID), ["[pde] degree must be >= 2 for oseen", "got 1"]),
    "graph-burgers": (toml({"network": 'type = "graph"'}, base=BURGERS),
                      ["[network] type 'graph' works on scalar fields; burgers states are vector fields"]),
    "hybrid-without-hybrid": (toml(base=HYBRID, drop=("hybrid",)), ["task 'hybrid' needs section(s) ['hybrid']"]),
    "hybrid-missing-fine-h": (toml(base={**HYBRID, "hybrid": "steps = 3"}), ["[hybrid] fine_h is required"]),
    "hybrid-zero-steps": (toml({"hybrid": "steps = 0"}, base=HYBRID), ["[hybrid] steps must be >= 1, got 0"]),
    "hybrid-on-emulator": (toml({"hybrid": "fine_h = 0.1"}), ["section(s) ['hybrid'] do not apply to task 'emulator'"]),
    "nu-for-heat": (toml({"pde": "nu = 0.1"}), ["[pde] nu do(es) not apply to pde 'heat'"]),
    "kappa-for-burgers": (toml({"pde": "kappa = 2.0"}, base=BURGERS),
                          ["[pde] kappa do(es) not apply to pde 'burgers'"]),
    "inflow-for-burgers": (toml({"pde": "inflow = 2.0"}, base=BURGERS),
                           ["[pde] inflow do(es) not apply to pde 'burgers'"]),
    "theta-for-oseen": (toml({"pde": "theta = 0.5"}, base=HYBRID), ["[pde] theta do(es) not apply to pde 'oseen'"]),
    "rollout-for-inverse": (toml({"data": "rollout = 2"}, base=INVERSE),
                            ["[data] rollout do(es) not apply to task 'inverse'"]),
    "zero-rollout": (toml({"data": "rollout = 0"}), ["[data] rollout must be >= 1, got 0"]),
    "optimizer-choice": (toml({"optimizer": 'type = "rmsprop"'}),
                         ["[optimizer] type must be one of ['adam', 'sgd'], got 'rmsprop'"]),
    "graph-without-convolutions": (toml({"network": 'type = "graph"\nlayers = 0'}),
                                   ["[network] layers must be >= 1 for a graph network", "got 0"]),
    "network-choice": (toml({"network": 'type = "cnn"'}),
                       ["[network] type must be one of ['mlp', 'graph'], got 'cnn'"]),
    "solver-choice": (toml({"solver": 'diff = "adjoint"'}),
                      ["[solver] diff must be one of ['implicit', 'unrolled'], got 'adjoint'"]),
    "unrolled-gmres": (toml({"solver": 'preset = "gmres"\ndiff = "unrolled"'}),
                       ["[solver] diff = 'unrolled' needs preset 'jacobi' or 'cg', got 'gmres'"]),
    "task-choice": ('[scene]\nname = "t"\ntask = "forward"\n',
                    ["[scene] task must be one of ['emulator', 'inverse', 'hybrid', 'sip', 'hig'], got 'forward'"]),
    "choice-is-case-sensitive": (toml({"optimizer": 'type = "Adam"'}),
                                 ["[optimizer] type must be one of ['adam', 'sgd'], got 'Adam'"]),
    # minimum
    "negative-lr": (toml({"optimizer": "lr = -0.1"}), ["[optimizer] lr must be > 0, got -0.1"]),
    "zero-lr": (toml({"optimizer": "lr = 0"}), ["[optimizer] lr must be > 0, got 0.0"]),
    "zero-epochs": (toml({"optimizer": "epochs = 0"}), ["[optimizer] epochs must be >= 1, got 0"]),
    "delta-1": (toml({"prdp": "delta = 1"}), ["[prdp] delta must be >= 2, got 1"]),
    "negative-theta": (toml({"pde": "theta = -0.5"}), ["[pde] theta must be >= 0, got -0.5"]),
    "zero-h": (toml({"mesh": "h = 0.0"}), ["[mesh] h must be > 0, got 0.0"]),
    "zero-k-cap": (toml({"prdp": "k_cap = 0"}), ["[prdp] k_cap must be >= 1, got 0"]),
    # maximum and cross-key ranges (values later code would reject)
    "tau-step-above-1": (toml({"prdp": "tau_step = 1.5"}), ["[prdp] tau_step must be <= 1, got 1.5"]),
    "tau-stop-above-1": (toml({"prdp": "tau_stop = 1.01"}), ["[prdp] tau_stop must be <= 1, got 1.01"]),
    "theta-above-1": (toml({"pde": "theta = 3.0"}), ["[pde] theta must be <= 1, got 3.0"]),
    "negative-seed": (toml({"data": "seed = -1"}), ["[data] seed must be >= 0, got -1"]),
    "k-cap-below-k0": (toml({"prdp": "k0 = 5\nk_cap = 2"}), ["[prdp] k_cap must be >= k0 (5), got 2"]),
    # keys a task or PDE does not use
    "train-for-inverse": (toml({"data": "train = 8"}, base=INVERSE),
                          ["[data] train do(es) not apply to task 'inverse'"]),
    "batch-for-inverse": (toml({"optimizer": "batch = 8"}, base=INVERSE),
                          ["[optimizer] batch do(es) not apply to task 'inverse'"]),
    "dt-for-poisson": (toml({"pde": "dt = 0.1"}, base=INVERSE), ["[pde] dt do(es) not apply to pde 'poisson'"]),
    # non-finite
    "nan-lr": (toml({"optimizer": "lr = nan"}), ["[optimizer] lr must be finite, got nan"]),
    "inf-h": (toml({"mesh": "h = inf"}), ["[mesh] h must be finite, got inf"]),
    "minus-inf-stop-at": (toml({"optimizer": "stop_at = -inf"}), ["[optimizer] stop_at must be finite, got -inf"]),
    "inf-tau": (toml({"prdp": "tau_step = +inf"}), ["[prdp] tau_step must be finite, got inf"]),
    # missing pieces
    "empty": ("", ["missing section [scene]"]),
    "missing-scene": (toml(drop=("scene",)), ["missing section [scene]"]),
    "missing-name": (toml(drop=("scene",)) + '[scene]\ntask = "emulator"\n', ["[scene] name is required"]),
    "missing-task": (toml(drop=("scene",)) + '[scene]\nname = "t"\n', ["[scene] task is required"]),
    "missing-mesh-name": (toml(drop=("mesh",)) + "[mesh]\nh = 0.2\n", ["[mesh] name is required"]),
    "missing-pde-type": (toml(drop=("pde",)) + "[pde]\ndt = 0.1\n", ["[pde] type is required"]),
    "missing-pde": (toml(drop=("pde",)), ["task 'emulator' needs section(s) ['pde']"]),
    "missing-mesh-and-pde": (toml(drop=("mesh", "pde")), ["task 'emulator' needs section(s) ['mesh', 'pde']"]),
    "inverse-without-inverse": (toml(base=INVERSE, drop=("inverse",)), ["task 'inverse' needs section(s) ['inverse']"]),
    "inverse-missing-theta-init": (toml(base=INVERSE, drop=("inverse",)) + "[inverse]\ntheta_ref = [1.0]\n",
                                   ["[inverse] theta_init is required"]),
    # sections that do not apply
    "network-on-inverse": (toml({"network": "hidden = 8"}, base=INVERSE),
                           ["section(s) ['network'] do not apply to task 'inverse'",
                            "allowed: ['data', 'inverse', 'mesh', 'optimizer', 'pde', 'prdp', 'scene', 'solver']"]),
    "inverse-on-emulator": (toml({"inverse": "theta_ref = [1.0]\ntheta_init = [2.0]"}),
                            ["section(s) ['inverse'] do not apply to task 'emulator'", "'network'"]),
    # sip and hig scenes
    "sip-without-sip": (toml(base=SIP, drop=("sip",)), ["task 'sip' needs section(s) ['sip']"]),
    "sip-inverse-choice": (toml(base={**SIP, "sip": 'inverse = "newton"'}),
                           ["[sip] inverse must be one of ['exact', 'tikhonov', 'gauss-newton'], got 'newton'"]),
    "sip-exact-with-damping": (toml({"sip": "damping = 0.1\ncg_iterations = 5"}, base=SIP),
                               ["[sip] cg_iterations, damping do(es) not apply to inverse 'exact'"]),
    "sip-tikhonov-with-cg": (toml(base={**SIP, "sip": 'inverse = "tikhonov"\ndamping = 0.1\ncg_iterations = 5'}),
                             ["[sip] cg_iterations do(es) not apply to inverse 'tikhonov'"]),
    "sip-negative-damping": (toml(base={**SIP, "sip": 'inverse = "gauss-newton"\ndamping = -1.0'}),
                             ["[sip] damping must be >= 0, got -1.0"]),
    "sip-oseen": (toml(base={**SIP, "pde": 'type = "oseen"'}),
                  ["[pde] type 'oseen' does not apply to task 'sip'",
                   "['poisson', 'heat', 'nonlinear-poisson', 'marker']"]),
    "sip-graph": (toml({"network": 'type = "graph"'}, base=SIP), ["[network] type must be 'mlp' for the sip task"]),
    "sip-solver": (toml({"solver": 'preset = "cg"'}, base=SIP), ["section(s) ['solver'] do not apply to task 'sip'"]),
    "sip-prdp": (toml({"prdp": "k0 = 2"}, base=SIP), ["section(s) ['prdp'] do not apply to task 'sip'"]),
    "sip-rollout": (toml({"data": "rollout = 2"}, base=SIP), ["[data] rollout do(es) not apply to task 'sip'"]),
    "sip-truths-choice": (toml({"data": 'truths = "noise"'}, base=SIP),
                          ["[data] truths must be one of ['smooth', 'rectangles'], got 'noise'"]),
    "sip-negative-noise": (toml({"data": "noise = -0.1"}, base=SIP), ["[data] noise must be >= 0, got -0.1"]),
    "sip-resample-string": (toml({"data": 'resample = "yes"'}, base=SIP),
                            ["[data] resample must be of type bool, got 'yes' (str)"]),
    "noise-on-emulator": (toml({"data": "noise = 0.1"}), ["[data] noise do(es) not apply to task 'emulator'"]),
    "hig-heat": (toml(base={**HIG, "pde": 'type = "heat"'}), ["[pde] type 'heat' does not apply to task 'hig'"]),
    "hig-optimizer-lr": (toml({"optimizer": "lr = 0.1"}, base=HIG),
                         ["[optimizer] lr do(es) not apply to task 'hig'"]),
    "hig-tau-above-1": (toml(base={**HIG, "hig": "tau = 2.0"}), ["[hig] tau must be <= 1, got 2.0"]),
    "hig-method-choice": (toml(base={**HIG, "hig": 'method = "qr"'}),
                          ["[hig] method must be one of ['auto', 'svd', 'gram'], got 'qr'"]),
    "baseline-on-emulator": (toml({"baseline": "lr = 0.1"}),
                             ["section(s) ['baseline'] do not apply to task 'emulator'"]),
    # theta lists
    "theta-lengths": (toml(base={**INVERSE, "inverse": "theta_ref = [1.0, 2.0]\ntheta_init = [1.0]"}),
                      ["[inverse] theta_ref and theta_init must have the same length", "got [1.0, 2.0] and [1.0]"]),
    "theta-string": (toml(base={**INVERSE, "inverse": 'theta_ref = ["a"]\ntheta_init = [1.0]'}),
                     ["[inverse] theta_ref must be a non-empty list of finite numbers, got ['a']"]),
    "theta-bool": (toml(base={**INVERSE, "inverse": "theta_ref = [1.0]\ntheta_init = [true]"}),
                   ["[inverse] theta_init must be a non-empty list of finite numbers, got [True]"]),
    "theta-empty": (toml(base={**INVERSE, "inverse": "theta_ref = []\ntheta_init = []"}),
                    ["[inverse] theta_ref must be a non-empty list of finite numbers, got []"]),
    "theta-nan": (toml(base={**INVERSE, "inverse": "theta_ref = [1.0]\ntheta_init = [nan]"}),
                  ["[inverse] theta_init must be a non-empty list of finite numbers, got [nan]"]),
    "theta-nested": (toml(base={**INVERSE, "inverse": "theta_ref = [[1.0]]\ntheta_init = [1.0]"}),
                     ["[inverse] theta_ref must be a non-empty list of finite numbers, got [[1.0]]"]),
    "theta-scalar": (toml(base={**INVERSE, "inverse": "theta_ref = 2.0\ntheta_init = [1.0]"}),
                     ["[inverse] theta_ref must be of type list, got 2.0 (float)"]),
}


@pytest.mark.parametrize("case", BAD)
def test_malformed_scene_names_the_problem(case):
    text, fragments = BAD[case]
    err = assert_scene_error(text, *fragments, source="bad.toml")
    assert isinstance(err, ValueError)


def test_error_from_a_file_names_the_file(tmp_path):
    path = tmp_path / "broken.toml"
    path.write_text(toml({"optimizer": "epochs = 0"}))
    with pytest.raises(SceneError, match=re.escape(f"{path}: [optimizer] epochs must be >= 1, got 0")):
        scene.load(path)
    with pytest.raises(SceneError, match=re.escape(f"{path}: [optimizer] epochs must be >= 1, got 0")):
        scene.load(str(path))


def test_load_by_path(tmp_path):
    path = tmp_path / "mine.toml"
    path.write_text(toml({"optimizer": "epochs = 7"}))
    sc = scene.load(path)
    assert (sc.name, sc.source, sc.optimizer.epochs) == ("t", str(path), 7)


def test_unknown_bundled_name_lists_the_bundled_scenes():
    with pytest.raises(SceneError, match=re.escape("unknown scene 'no-such-scene'; bundled scenes are")) as info:
        scene.load("no-such-scene")
    message = str(info.value)
    for name in scene.available():
        assert repr(name) in message
    assert ".toml" in message  # tells the user how to pass a file instead


def test_missing_path_is_file_not_found(tmp_path):
    missing = tmp_path / "nope.toml"
    with pytest.raises(FileNotFoundError, match=re.escape(str(missing))):
        scene.load(missing)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        scene.load(str(missing))


def test_load_rejects_non_paths():
    with pytest.raises(TypeError, match="bundled name or a path, got int"):
        scene.load(3)


PAYLOAD = "__import__('os').system('touch {marker}')"


def test_strings_are_never_evaluated(tmp_path):
    marker = tmp_path / "pwned"
    payload = PAYLOAD.format(marker=marker)
    quoted = payload.replace("\\", "\\\\").replace('"', '\\"')
    text = toml(drop=("scene", "mesh")) + (f'[scene]\nname = "evil"\ntask = "emulator"\n'
                                           f'description = "{quoted}"\n[mesh]\nname = "{quoted}"\n')
    path = tmp_path / "evil.toml"
    path.write_text(text)
    # The mesh name is a name or a path, looked up, never run: refused as neither.
    for parse in (lambda: scene.parse(text), lambda: scene.load(path)):
        with pytest.raises(scene.SceneError, match=r"\[mesh\] name .* is neither a bundled mesh"):
            parse()
    text = text.replace(f'[mesh]\nname = "{quoted}"', '[mesh]\nname = "lshape"')
    path.write_text(text)
    for sc in (scene.parse(text), scene.load(path)):
        assert sc.description == payload
    # The name becomes a directory: only a slug is accepted.
    with pytest.raises(scene.SceneError, match=r"\[scene\] name must be 1-128 letters"):
        scene.parse(text.replace('name = "evil"', f'name = "{quoted}"'))
    # A string where a number belongs is a type error, not an expression.
    assert_scene_error(toml({"optimizer": f'lr = "{quoted}"'}), "[optimizer] lr must be of type float")
    assert not marker.exists()


def test_warm_start_applies_to_the_inverse_task_and_is_off_unless_set():
    text = toml({"solver": "warm_start = true"}, base={**INVERSE, "scene": 'name = "inv"\ntask = "inverse"',
                                                       "inverse": "theta_ref = [1.0]\ntheta_init = [2.0]"})
    assert scene.parse(text).solver.warm_start is True
    parsed = scene.parse(text.replace("warm_start = true", ""))
    assert parsed.solver.warm_start is False and parsed.as_dict()["solver"]["warm_start"] is False
    with pytest.raises(SceneError, match=r"\[solver\] warm_start must be of type bool"):
        scene.parse(text.replace("warm_start = true", 'warm_start = "yes"'))
