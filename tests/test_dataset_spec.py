"""Dataset specs (simgen.dataset.spec): presets, validation with one-sentence errors, CLI overrides,
and the plan they produce. No simulation here: fast."""

import re

import numpy as np
import pytest

from simgen.dataset import list_presets, load_spec, parse_spec
from simgen.dataset.spec import preset_path
from simgen.errors import InputError
from simgen.motion.library import library_split


def minimal(**tables):
    doc = {"garment": {"names": ["tshirt_1k"]}}
    for k, v in tables.items():
        doc[k] = v
    return doc


def test_presets_exist_and_validate():
    assert {"tiny", "thesis-tshirt", "thesis-dress"} <= set(list_presets())
    for name in list_presets():
        spec = load_spec(name)
        assert spec.name == name
        assert spec.shapes() and spec.motions()


def test_thesis_tshirt_matches_section_4_3_1():
    spec = load_spec("thesis-tshirt")
    shapes = spec.shapes()
    # 17 shapes: all-zero plus the first 4 components at 4 values each, the others zero.
    assert len(shapes) == 17 and shapes[0].betas == ()
    seen = set()
    for s in shapes[1:]:
        b = np.zeros(10)
        b[:len(s.betas)] = s.betas
        nz = np.flatnonzero(b)
        assert len(nz) == 1 and nz[0] < 4 and b[nz[0]] in (-2.0, -1.0, 1.0, 2.0)
        seen.add((int(nz[0]), float(b[nz[0]])))
    assert len(seen) == 16
    # All library motions, CMU clips included, with the library's own train/test split.
    motions = {m.id: m.split for m in spec.motions()}
    split = library_split()
    assert set(motions) == set(split["train"]) | set(split["test"])
    assert any(m.startswith("cmu_") for m in motions)
    assert {m for m, s in motions.items() if s == "test"} == set(split["test"])
    # ARCSim's time step: 3.33 ms = 10 substeps of a 30 fps frame; one output frame per motion frame.
    assert spec.fps == 30.0 and spec.substeps == 10
    assert spec.solver_config().substeps == 10 and spec.garments == ["tshirt"] and spec.material == "interlock"


def test_tiny_is_small():
    spec = load_spec("tiny")
    assert len(spec.shapes()) == 2 and len(spec.motions()) == 2 and spec.device == "cpu"
    assert {m.split for m in spec.motions()} == {"train", "test"}
    assert 0 < spec.max_frames <= 8 and spec.garments == ["tshirt_1k"]


@pytest.mark.parametrize("doc, field", [
    (minimal(solver={"substeps": "10"}), "solver.substeps"),
    (minimal(solver={"substeps": 0}), "solver.substeps"),
    (minimal(solver={"fps": -30}), "solver.fps"),
    (minimal(solver={"cg_iterations": 2.5}), "solver.cg_iterations"),
    (minimal(solver={"self_contact": "on"}), "solver.self_contact"),
    (minimal(solver={"device": "tpu"}), "solver.device"),
    (minimal(solver={"contact": {"stiffness": 0.0}}), "solver.contact.stiffness"),
    (minimal(solver={"contact_stiffness": 1e5}), "solver.contact_stiffness"),
    (minimal(solver={"contact": {"stifness": 1e5}}), "solver.contact.stifness"),
    (minimal(solver={"contact": 1e5}), "solver.contact"),
    (minimal(solver={"friction": {"max_normal_load": -1.0}}), "solver.friction.max_normal_load"),
    (minimal(solver={"self_contact": {"max_candidates": 0}}), "solver.self_contact.max_candidates"),
    (minimal(solver={"gravity": {"gravity": [0.0, -9.81]}}), "solver.gravity.gravity"),
    (minimal(solver={"armijo": 0.0}), "solver.armijo"),
    (minimal(solver={"constraint_rounds": 0}), "solver.constraint_rounds"),
    (minimal(solver={"limiter_half_space": True}), "solver.limiter_half_space"),
    (minimal(solver={"guard_energy": "off"}), "solver.guard_energy"),
    (minimal(solver={"substep": 4}), "solver.substep"),
    (minimal(protocol={"ramp_frames": 0}), "protocol.ramp_frames"),
    (minimal(protocol={"store_rest_frames": "yes"}), "protocol.store_rest_frames"),
    (minimal(shapes={"values": [1, "2"]}), "shapes.values"),
    (minimal(shapes={"generator": "random"}), "shapes.generator"),
    (minimal(shapes={"generator": "list", "list": [{"id": "a b", "betas": []}]}), "shapes.list[0].id"),
    (minimal(shapes={"generator": "list", "list": [{"betas": [1.0]}]}), "shapes.list[0].id"),
    (minimal(motions={"library": "walk", "max_frames": -1}), "motions.max_frames"),
    (minimal(smoothing={"mu": -0.1}), "smoothing.mu"),
    (minimal(execution={"batch_size": True}), "execution.batch_size"),
    (minimal(execution={"overlap_writes": "no"}), "execution.overlap_writes"),
    (minimal(execution={"retry_strain_outliers": 0}), "execution.retry_strain_outliers"),
    (minimal(garment={"names": ["tshirt_1k"], "material": "kevlar"}), "garment.material"),
    (minimal(garment={"names": ["tshirt_1k"], "material_overrides": {"stiffness": 1.0}}),
     "garment.material_overrides.stiffness"),
    ({"garment": {"material": "cotton"}}, "garment.names"),
    (minimal(extra=1), "extra"),
])
def test_type_errors_name_the_field(doc, field):
    with pytest.raises(InputError) as exc:
        parse_spec(doc, source="bad.toml")
    msg = str(exc.value)
    assert "bad.toml" in msg and f"'{field}'" in msg
    assert "\n" not in msg and msg.count(". ") == 0  # one sentence


def test_unknown_motion_and_missing_files(tmp_path):
    with pytest.raises(InputError, match=r"unknown motion 'walkk'.*close: walk"):
        parse_spec(minimal(motions={"library": ["walkk"]}), source="s.toml").motions()
    with pytest.raises(InputError, match="matches no library motion"):
        parse_spec(minimal(motions={"library": ["zzz*"]}), source="s.toml").motions()
    with pytest.raises(InputError, match=r"'motions.files' file 'nope.npz' matches no file"):
        parse_spec(minimal(motions={"library": [], "files": ["nope.npz"]}), source="s.toml",
                   base_dir=tmp_path).motions()
    with pytest.raises(InputError, match=r"'motions.test' names 'dance'"):
        parse_spec(minimal(motions={"library": ["walk"], "test": ["dance"]}), source="s.toml").motions()
    with pytest.raises(InputError, match="does not exist"):
        load_spec(str(tmp_path / "missing.toml"))
    with pytest.raises(InputError, match="unknown dataset preset 'thesis-shirt'"):
        load_spec("thesis-shirt")


def test_invalid_toml_and_unknown_garment(tmp_path):
    p = tmp_path / "broken.toml"
    p.write_text("[garment\nnames = 1\n")
    with pytest.raises(InputError, match="is not valid TOML"):
        load_spec(p)
    from simgen.dataset import generate_dataset

    spec = parse_spec(minimal(garment={"names": ["ballgown"]}), source="g.toml")
    with pytest.raises(InputError, match="ballgown"):
        generate_dataset(spec, out=str(tmp_path / "store"))
    assert not (tmp_path / "store").exists()  # checked before anything is written


def test_motion_files_relative_to_spec(tmp_path):
    from simgen.motion import load_motion, save_motion
    from simgen.motion.ops import trim

    save_motion(trim(load_motion("walk"), 0.0, 0.2), tmp_path / "clips" / "short walk.npz")
    spec_file = tmp_path / "my.toml"
    spec_file.write_text('[garment]\nnames = ["tshirt_1k"]\n'
                         '[motions]\nfiles = ["clips/*.npz"]\ntest = ["short_walk"]\n')
    spec = load_spec(spec_file)
    (m,) = spec.motions()
    assert m.id == "short_walk" and m.split == "test" and m.source.endswith("short walk.npz")


def test_overrides():
    spec = load_spec("thesis-tshirt")
    o = spec.with_overrides(device="cpu", batch_size=4, substeps=5, max_frames=3, motions=["walk", "dance"],
                            shapes=["zero", "b2p1"])
    assert o.device == "cpu" and o.batch_size == 4 and o.substeps == 5 and o.max_frames == 3
    assert [s.id for s in o.shapes()] == ["zero", "b2p1"] and o.shapes()[1].betas == (0.0, 0.0, 1.0)
    assert {m.id: m.split for m in o.motions()} == {"walk": "train", "dance": "test"}
    assert spec.substeps == 10 and len(spec.shapes()) == 17  # the original is untouched
    with pytest.raises(InputError, match="--shapes: unknown shape id 'b9p1'"):
        spec.with_overrides(shapes=["b9p1"])
    with pytest.raises(InputError, match="solver.device"):
        spec.with_overrides(device="gpu")
    # Content keys: execution settings are free, physics settings are not.
    assert spec.with_overrides(batch_size=2).content_hash("tshirt") == spec.content_hash("tshirt")
    assert spec.overlap_writes and not spec.with_overrides(overlap_writes=False).overlap_writes
    assert spec.with_overrides(overlap_writes=False).content_hash("tshirt") == spec.content_hash("tshirt")
    assert parse_spec(minimal(execution={"overlap_writes": False}), source="s.toml").overlap_writes is False
    with pytest.raises(InputError, match="execution.overlap_writes"):
        spec.with_overrides(overlap_writes=1)
    assert spec.with_overrides(substeps=5).content_hash("tshirt") != spec.content_hash("tshirt")


def test_preset_files_document_their_fields():
    # Every preset parses with no unknown field and names its thesis source in a comment.
    for name in ("thesis-tshirt", "thesis-dress"):
        text = preset_path(name).read_text()
        assert re.search(r"4\.3\.1", text)


def test_cli_bad_input_is_one_sentence_exit_2(tmp_path, capsys):
    from simgen import cli

    for argv, needle in (
        (["dataset", "generate", "thesis-shirt", "--out", str(tmp_path / "a")], "unknown dataset preset"),
        (["dataset", "generate", "tiny", "--out", str(tmp_path / "b"), "--motions", "moonwalk"], "'moonwalk'"),
        (["dataset", "generate", "tiny", "--out", str(tmp_path / "c"), "--batch-size", "-1"], "batch_size"),
        (["dataset", "info", str(tmp_path / "none")], "not a dataset store"),
        (["dataset", "export", str(tmp_path / "none.npz"), "x"], "does not exist"),
    ):
        with pytest.raises(SystemExit) as exc:
            cli.main(argv)
        assert exc.value.code == 2, argv
        err = capsys.readouterr().err.strip()
        assert needle in err and len(err.splitlines()) == 1, err
    assert not any(tmp_path.iterdir())  # nothing written


def test_self_contact_option_reaches_the_solver_and_only_then_the_store_key():
    off, on = parse_spec(minimal()), parse_spec(minimal(solver={"self_contact": True}))
    assert off.solver_config().solver.self_contact is None
    assert on.solver_config().solver.self_contact is not None
    # Stores made before the option existed keep their key; turning it on makes a different store.
    assert "self_contact" not in off.content_key("tshirt_1k")
    assert on.content_hash("tshirt_1k") != off.content_hash("tshirt_1k")


def test_contact_table_and_constraint_rounds_reach_the_solver():
    default = parse_spec(minimal())
    spec = parse_spec(minimal(solver={"contact": {"stiffness": 1e5}, "constraint_rounds": 2}))
    assert default.solver_config().solver.contact.stiffness == 1e4
    solver = spec.solver_config().solver
    assert solver.contact.stiffness == 1e5 and solver.constraint_rounds == 2
    assert solver.contact.margin == default.solver_config().solver.contact.margin  # the rest unchanged
    assert spec.content_hash("tshirt_1k") != default.content_hash("tshirt_1k")
    # The sub-table enters the store key under its one-level name, so stores made when the spec
    # field was solver.contact_stiffness keep their key.
    assert spec.content_key("tshirt_1k")["solver"] == {"contact_stiffness": 1e5, "constraint_rounds": 2}
    assert spec.to_dict()["solver"] == {"contact": {"stiffness": 1e5}, "constraint_rounds": 2}


def test_old_flat_contact_field_says_where_it_went():
    with pytest.raises(InputError, match=r"unknown field 'solver.contact_stiffness' \(it is now "
                                         r"'solver.contact.stiffness': stiffness in a \[solver.contact\] table\)"):
        parse_spec(minimal(solver={"contact_stiffness": 1e5}), source="old.toml")
    with pytest.raises(InputError, match=r"unknown field 'solver.contact.stifness' \(did you mean "
                                         r"'solver.contact.stiffness'\?\)"):
        parse_spec(minimal(solver={"contact": {"stifness": 1e5}}), source="typo.toml")


def test_parameter_sub_tables_and_switches():
    """friction and self_contact: true/false or a table of their fields (then on); contact and
    gravity: tables; checks across a class's fields run when the spec is read."""
    from simgen.params import FrictionParams, SelfContactParams

    off = parse_spec(minimal(solver={"friction": False}))
    assert off.friction is False and off.solver_config().solver.friction is None
    capped = parse_spec(minimal(solver={"friction": {"max_normal_load": float("inf")}}))
    assert capped.friction is True
    assert capped.solver_config().solver.friction == FrictionParams(max_normal_load=float("inf"))
    thick = parse_spec(minimal(solver={"self_contact": {"thickness": 3e-3, "search_radius": 2e-2}}))
    assert thick.self_contact is True
    assert thick.solver_config().solver.self_contact == SelfContactParams(thickness=3e-3, search_radius=2e-2)
    assert thick.content_key("tshirt_1k")["self_contact"] is True
    assert parse_spec(minimal(solver={"self_contact": True})).solver_config().solver.self_contact == \
        SelfContactParams()
    moon = parse_spec(minimal(solver={"gravity": {"gravity": [0, -1.62, 0]}}))
    assert moon.solver_config().solver.gravity.gravity == (0.0, -1.62, 0.0)
    # An empty table is the defaults: the same store as none.
    assert parse_spec(minimal(solver={"contact": {}})).content_hash("x") == parse_spec(minimal()).content_hash("x")
    with pytest.raises(InputError, match=r"spec bad.toml: table 'solver.contact': contact pinch_distance"):
        parse_spec(minimal(solver={"contact": {"margin": 1e-2}}), source="bad.toml")


def test_solver_table_covers_solver_config():
    """Every SolverConfig field can be set in [solver] with the declaration's bounds and default
    (its own substeps aside: a spec's substeps is the frame's, SimulationConfig.substeps)."""
    from simgen.dataset.spec import simulation_settings, solver_settings
    from simgen.settings import settings_of
    from simgen.sim import SimulationConfig, SolverConfig

    assert set(solver_settings()) == set(settings_of(SolverConfig))
    assert simulation_settings()["substeps"] is settings_of(SimulationConfig)["substeps"]
    spec = parse_spec(minimal())
    # Defaults: a spec that sets nothing gets the dataclasses' defaults.
    assert spec.solver_options() == SolverConfig()
    cfg = spec.solver_config()
    sim = SimulationConfig()
    assert (cfg.substeps, cfg.relax_frames, cfg.ramp_frames, cfg.rest_frames) == \
        (sim.substeps, sim.relax_frames, sim.ramp_frames, sim.rest_frames)
    assert cfg.solver == sim.solver
    # Each scalar field reaches the SolverConfig.
    every = {"newton_iterations": 3, "newton_tolerance": 1e-6, "cg_iterations": 7, "cg_tolerance": 1e-4,
             "line_search": True, "line_search_steps": 3, "armijo": 1e-3, "floor": -1.0,
             "strain_limit": 0.3, "strain_limit_iterations": 4, "project": False, "projection_offset": 1e-4,
             "constraint_rounds": 3, "guard": False, "max_retries": 2, "max_speed": 20.0, "divergence_ratio": 5.0,
             "guard_energy": False, "cg_warm_start": False}
    assert set(every) == {k for k, s in solver_settings().items() if not s.nested}
    solver = parse_spec(minimal(solver=every)).solver_options()
    assert all(getattr(solver, k) == v for k, v in every.items())


@pytest.mark.parametrize("table, key", [("solver", k) for k in ("newton_iterations", "cg_iterations",
                                                                 "projection_offset", "strain_limit", "max_speed")]
                         + [("protocol", "ramp_frames"), ("protocol", "relax_frames")])
def test_bad_bounded_value_names_the_field(table, key):
    from simgen.dataset.spec import simulation_settings, solver_settings

    s = {**solver_settings(), **simulation_settings()}[key]
    bad = s.low - 1 if s.kind is int else -1.0
    with pytest.raises(InputError, match=rf"spec b.toml: field '{table}.{key}' must be .*, got {bad!r}"):
        parse_spec(minimal(**{table: {key: bad}}), source="b.toml")
