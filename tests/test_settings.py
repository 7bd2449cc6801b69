"""Settings declared once (simgen.settings): every field of the solver's and the simulation's
settings and of the energy parameters carries its type, bounds, default and doc; validation,
the dataset spec's [solver] / [protocol] tables and the simulate flags come from there."""

import dataclasses
import math
import subprocess
import sys

import pytest

from simgen.errors import InputError
from simgen.params import ContactParams, FrictionParams, GravityParams, SelfContactParams
from simgen.settings import setting, settings_of, validate

CLASSES = (ContactParams, GravityParams, FrictionParams, SelfContactParams)


def all_classes():
    from simgen.sim import SimulationConfig, SolverConfig

    return (*CLASSES, SolverConfig, SimulationConfig)


def test_every_field_is_declared_with_a_doc():
    for cls in all_classes():
        declared = settings_of(cls)
        assert list(declared) == [f.name for f in dataclasses.fields(cls)], cls
        for s in declared.values():
            assert s.doc and "\n" not in s.doc, (cls.__name__, s.name)
            # A unit, where there is one, leads the doc: "[m] ...".
            assert s.doc.count("[") == s.doc.count("]"), (cls.__name__, s.name)
        # The docstring lists the declarations (generated, so it cannot drift from them).
        assert all(f"- {name} (" in cls.__doc__ for name in declared), cls


def test_defaults_are_the_dataclass_defaults_and_valid():
    for cls in all_classes():
        instance = cls()
        for name, s in settings_of(cls).items():
            assert getattr(instance, name) == s.default, (cls.__name__, name)
            assert s.check(s.default, name) == s.default


def test_defaults_are_set_once():
    from simgen.sim import SimulationConfig, SolverConfig

    assert SimulationConfig().solver == SolverConfig()
    assert SolverConfig().projection_offset == 2.0e-4   # projected vertices count as outside


def bad_values(s):
    """Values that break a declaration's type or bounds."""
    if s.kind is bool:
        return [1, "yes"]
    if s.kind is int:
        return [1.5, True, *([s.low - 1] if s.low is not None else [])]
    if s.kind is float:
        out = [math.nan, "1.0", True]
        if s.finite:
            out.append(math.inf)
        if s.low is not None:
            out.append(s.low if not s.inclusive else s.low - 1.0)
        return out
    if s.kind is tuple:
        return [(0.0,) * (s.length - 1), (0.0, math.nan, 0.0)[:s.length], "abc"]
    if s.nested or s.types:
        return [object()]
    return []


def test_a_bad_value_of_any_field_raises_input_error_naming_it():
    checked = 0
    for cls in all_classes():
        for name, s in settings_of(cls).items():
            for bad in bad_values(s):
                with pytest.raises(InputError) as exc:
                    cls(**{name: bad})
                msg = str(exc.value)
                assert f"{name} must be" in msg and repr(bad) in msg and "\n" not in msg, msg
                checked += 1
    assert checked > 80


def test_messages_name_the_class_field_and_value():
    from simgen.sim import SimulationConfig, SolverConfig

    cases = [
        (lambda: SolverConfig(newton_iterations=0), "solver newton_iterations must be an integer >= 1, got 0"),
        (lambda: SolverConfig(strain_limit=0.0), "solver strain_limit must be a finite number > 0 or None, got 0.0"),
        (lambda: SolverConfig(max_retries=-1), "solver max_retries must be an integer >= 0, got -1"),
        (lambda: SolverConfig(line_search=1), "solver line_search must be True or False, got 1"),
        (lambda: SolverConfig(contact=1e5), "solver contact must be a ContactParams, got 100000.0"),
        (lambda: SimulationConfig(fps=0), "simulation fps must be a finite number > 0 or None, got 0"),
        (lambda: SimulationConfig(solver=None), "simulation solver must be a SolverConfig, got None"),
        (lambda: ContactParams(power=1.5), "contact power must be a finite number >= 2, got 1.5"),
        (lambda: FrictionParams(max_normal_load=0), "friction max_normal_load must be a number > 0, got 0"),
        (lambda: GravityParams((0.0, 1.0)), "gravity must be 3 finite numbers, got (0.0, 1.0)"),
        (lambda: SelfContactParams(max_candidates=0), "self-contact max_candidates must be an integer >= 1, got 0"),
    ]
    for make, message in cases:
        with pytest.raises(InputError) as exc:
            make()
        assert str(exc.value) == message


def test_checks_across_fields_stay():
    with pytest.raises(InputError, match=r"contact query_distance \(0.001\) must exceed the margin"):
        ContactParams(query_distance=1e-3)
    with pytest.raises(InputError, match="pinch_distance"):
        ContactParams(margin=6e-3)
    with pytest.raises(InputError, match="search_radius"):
        SelfContactParams(thickness=0.02)


def test_values_are_normalised():
    c = ContactParams(stiffness=100000, margin=2e-3)
    assert type(c.stiffness) is float and c == ContactParams(stiffness=1e5)
    assert GravityParams([0, -1, 0]).gravity == (0.0, -1.0, 0.0)
    assert FrictionParams(max_normal_load=math.inf).max_normal_load == math.inf


def test_the_helper_on_a_class_of_its_own():
    @dataclasses.dataclass(frozen=True)
    class Box:
        size: float = setting(1.0, low=0.0, high=2.0, inclusive=False, doc="[m] edge")
        kind: str = setting("cube", choices=("cube", "ball"), doc="shape")
        tag: str | None = setting(None, doc="label")

        def __post_init__(self):
            validate(self, "box")

    assert Box(size=1.5).size == 1.5
    for bad, needle in ((2.0, "box size must be a finite number > 0 and < 2, got 2.0"),
                        (0.0, "box size must be a finite number > 0 and < 2, got 0.0")):
        with pytest.raises(InputError, match=needle):
            Box(size=bad)
    with pytest.raises(InputError, match="box kind must be one of 'cube', 'ball', got 'cone'"):
        Box(kind="cone")
    with pytest.raises(InputError, match="box tag must be a string or None, got 3"):
        Box(tag=3)


def test_spec_schema_is_derived_from_the_declarations():
    """Every SolverConfig field can be set in a spec's [solver], each parameter class as a sub-table of its fields, with the same
    bounds; the [protocol] frame counts are SimulationConfig's."""
    from simgen.dataset.spec import simulation_settings, solver_settings
    from simgen.sim import SimulationConfig, SolverConfig

    solver = solver_settings()
    assert set(solver) == set(settings_of(SolverConfig))
    for name, s in solver.items():
        assert s == settings_of(SolverConfig)[name]
    assert {k for k, s in solver.items() if s.nested} == {"gravity", "contact", "friction", "self_contact"}
    for name, s in simulation_settings().items():
        assert s == settings_of(SimulationConfig)[name]


def test_optional_parameter_classes_have_their_spec_switch():
    """friction / self_contact = true / false lands in the DatasetSpec field of that name, which the
    store's content key holds: a new optional parameter class of SolverConfig needs one too."""
    from simgen.dataset.spec import DatasetSpec, solver_settings

    switches = {k for k, s in solver_settings().items() if s.nested and s.optional}
    assert switches == {"friction", "self_contact"}
    assert switches <= {f.name for f in dataclasses.fields(DatasetSpec)}


def test_spec_reads_every_bounded_solver_field_with_its_bounds():
    from simgen.dataset import parse_spec
    from simgen.dataset.spec import solver_settings

    tables = {k: settings_of(s.nested) for k, s in solver_settings().items() if s.nested}
    cases = [((), k, s) for k, s in solver_settings().items() if not s.nested] + \
        [((t,), k, s) for t, fields_ in tables.items() for k, s in fields_.items()]
    bounded = 0
    for path, key, s in cases:
        if s.low is None:
            continue
        bad = s.low - 1 if s.kind is int else (s.low if not s.inclusive else s.low - 1.0)
        table = {key: bad}
        for t in reversed(path):
            table = {t: table}
        field = ".".join(("solver", *path, key))
        with pytest.raises(InputError, match=rf"spec b.toml: field '{field}' must be"):
            parse_spec({"garment": {"names": ["tshirt_1k"]}, "solver": table}, source="b.toml")
        bounded += 1
    assert bounded >= 20


def test_the_simulate_flags_take_the_solver_bounds():
    from simgen.settings import check_value
    from simgen.sim import SolverConfig

    with pytest.raises(InputError, match=r"--strain-limit must be a finite number > 0, got -1.0$"):
        check_value(SolverConfig, "strain_limit", -1.0, "--strain-limit")
    assert check_value(SolverConfig, "newton_iterations", 2, "--newton-iterations") == 2


def test_the_parameter_classes_import_without_warp():
    code = "import sys, simgen.params, simgen.settings; print('warp' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
