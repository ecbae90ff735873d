"""Scenes as dataclasses: typed overrides, validation that names the field, held nodes, poses, the
Simulation's stages and stats, and the surface embedding used for figures."""

from dataclasses import dataclass, field

import numpy as np
import pytest

import scenes
from tissue.errors import TissueError
from tissue.mesh import beam, box, write_vtu
from tissue.mesh.embedding import EmbeddedSurface
from tissue.options import apply_overrides, flatten, validate
from tissue.output import nice_ceiling
from tissue.body import build_mesh, held_nodes, rotation_matrix
from tissue.scene import Fixed, Render, Scene, Solver, SoftBody
from tissue.simulation import STAGES, Simulation, add_stage


@dataclass
class SmallBeam(Scene):
    """A coarse cantilever for fast tests."""

    dt: float = 0.01
    duration: float = 0.05
    beam: SoftBody = field(default_factory=lambda: SoftBody(
        mesh="beam", size=(1.0, 0.1, 0.1), cells=(6, 1, 1), young=1e6, fixed=Fixed.end("-x")))


# ---- overrides ------------------------------------------------------------------------------------


def test_overrides_reach_the_dataclass_with_the_fields_types():
    scene = scenes.load("liver")().with_overrides([
        "liver.young=5e3", "dt=0.04", "render.camera=side", "liver.fixed.region=0,1,0,1,0.9,1",
        "render.scalars=none", "solver.cg_iterations=10", "render.ghost=true", "liver.mesh=some/liver.vtu",
        "render.size=(640, 480)", "liver.fixed.nodes=3,", "render.outputs=png"])
    assert scene.liver.young == 5000.0 and isinstance(scene.liver.young, float)
    assert scene.dt == 0.04
    assert scene.render.camera == "side"
    assert scene.liver.fixed.region == (0.0, 1.0, 0.0, 1.0, 0.9, 1.0)
    assert scene.render.scalars is None
    assert scene.solver.cg_iterations == 10 and isinstance(scene.solver.cg_iterations, int)
    assert scene.render.ghost is True
    assert scene.liver.mesh == "some/liver.vtu"
    assert scene.render.size == (640, 480)
    assert scene.liver.fixed.nodes == (3,)
    assert scene.render.outputs == ("png",)
    # The defaults are untouched (overrides make a copy).
    assert scenes.load("liver")().liver.young == 3000.0


@pytest.mark.parametrize("assignment, message", [
    ("liver.yung=1", "liver.yung: unknown field; did you mean 'young'?"),
    ("dtt=0.1", "dtt: unknown field; did you mean 'dt'?"),
    ("liver.young=abc", "liver.young: expected a number, got 'abc'"),
    ("solver.cg_iterations=2.5", "solver.cg_iterations: expected an integer, got '2.5'"),
    ("render.camera=sid", "render.camera: unknown value 'sid'; did you mean 'side'?"),
    ("render.size=640", "render.size: expected 2 comma-separated values"),
    ("render.ghost=maybe", "render.ghost: expected true or false, got 'maybe'"),
    ("liver=3", "liver: is a group of fields"),
    ("dt.x=3", "dt: is a single value"),
    ("liver.young", "expected FIELD=VALUE"),
])
def test_bad_overrides_name_the_field(assignment, message):
    with pytest.raises(TissueError) as err:
        scenes.load("liver")().with_overrides([assignment])
    assert message in str(err.value)
    assert "\n" not in str(err.value)


def test_unknown_keyword_is_refused_at_construction():
    with pytest.raises(TissueError, match=r"SoftBody.yung: unknown field; did you mean 'young'\?"):
        SoftBody(yung=3.0)


# ---- validation -----------------------------------------------------------------------------------


@pytest.mark.parametrize("assignment, field_name", [
    ("beam.poisson=0.5", "beam.poisson"),
    ("beam.poisson=0.7", "beam.poisson"),
    ("beam.young=0", "beam.young"),
    ("beam.young=-3", "beam.young"),
    ("beam.density=0", "beam.density"),
    ("dt=0", "dt"),
    ("dt=-0.01", "dt"),
    ("duration=0", "duration"),
    ("beam.young=nan", "beam.young"),
    ("beam.cells=0,1,1", "beam.cells"),
    ("beam.fixed.region=0,1,0,1", "beam.fixed.region"),
    ("render.every=0", "render.every"),
    ("render.outputs=png,jpg", "render.outputs"),
    ("solver.rayleigh_mass=-1", "solver.rayleigh_mass"),
])
def test_validation_refuses_bad_values_naming_the_field(assignment, field_name):
    scene = SmallBeam().with_overrides([assignment])
    with pytest.raises(TissueError) as err:
        validate(scene)
    assert str(err.value).startswith(field_name + ":"), str(err.value)


def test_missing_mesh_file_and_unknown_mesh_name_are_named(tmp_path):
    with pytest.raises(TissueError, match=r"^beam.mesh: no such file '.*nowhere.vtu'"):
        validate(SmallBeam().with_overrides([f"beam.mesh={tmp_path / 'nowhere.vtu'}"]))
    with pytest.raises(TissueError, match=r"^beam.mesh: 'livr' is neither a built-in mesh .*did you mean 'liver'\?"):
        validate(SmallBeam().with_overrides(["beam.mesh=livr"]))


def test_validation_checks_types_of_fields_set_in_python():
    scene = SmallBeam()
    scene.beam.young = "soft"
    with pytest.raises(TissueError, match=r"^beam.young: expected a number, got 'soft'"):
        validate(scene)


def test_a_scene_without_bodies_is_refused():
    with pytest.raises(TissueError, match="declares no soft body"):
        validate(Scene())


def test_flatten_lists_every_leaf_by_dotted_name():
    flat = flatten(SmallBeam())
    assert flat["beam.young"] == 1e6 and flat["render.camera"] == "iso" and flat["dt"] == 0.01
    # Every flattened name can be set back, and setting each to its value changes nothing: the
    # round trip, on a scene whose every value is first changed to a different one (so that a
    # value parsed wrongly, dropped or set on another field shows) and on the shipped scenes.
    def assignments(flat):
        return [f"{k}={v if not isinstance(v, list) else ','.join(map(str, v))}"
                for k, v in flat.items() if v is not None and v != []]

    changed = SmallBeam().with_overrides(["beam.young=2.5e5", "dt=0.02", "render.camera=top",
                                          "beam.cells=3,2,1", "solver.cg_iterations=7"])
    for scene in [SmallBeam(), changed, *(cls() for cls in scenes.catalogue().values())]:
        flat = flatten(scene)
        back = flatten(apply_overrides(type(scene)(), assignments(flat)))
        assert back == flat, type(scene).__name__
    assert flatten(changed)["beam.young"] == 2.5e5 and flatten(changed)["beam.cells"] == [3, 2, 1]


# ---- held nodes and poses ------------------------------------------------------------------------


def test_fixed_end_holds_the_clamped_face():
    mesh = beam(1.0, 0.1, 0.1, 6, 2)
    held = held_nodes(mesh.points, Fixed.end("-x"))
    assert len(held) == 9 and np.all(mesh.points[held, 0] == 0.0)
    top = held_nodes(mesh.points, Fixed.end("+z", fraction=0.0))
    assert np.all(np.isclose(mesh.points[top, 2], 0.05))


def test_fixed_count_spreads_and_radius_grows_patches():
    mesh = box(size=(1, 1, 1), cells=(6, 6, 6))
    region = (0.0, 1.0, 0.0, 1.0, 1.0, 1.0)
    three = held_nodes(mesh.points, Fixed(region=region, count=3))
    assert len(three) == 3 and np.all(mesh.points[three, 2] == 1.0)
    spread = np.linalg.norm(mesh.points[three][:, None] - mesh.points[three][None], axis=-1)
    assert spread[np.triu_indices(3, 1)].min() > 0.4
    patches = held_nodes(mesh.points, Fixed(region=region, count=3, radius=0.2))
    assert set(three) < set(patches) and len(patches) > 3
    explicit = held_nodes(mesh.points, Fixed(nodes=(0, 5)))
    assert explicit.tolist() == [0, 5]


def test_radius_patches_are_the_k_d_trees_ball_query():
    """The nodes a patch holds: those scipy's k-d tree finds within the radius of each chosen node."""
    from scipy.spatial import cKDTree

    points = np.random.default_rng(3).uniform(-0.1, 0.1, (5000, 3))
    fixed = Fixed(region=(0.0, 1.0, 0.0, 1.0, 0.8, 1.0), count=4, radius=0.03)
    chosen = held_nodes(points, Fixed(region=fixed.region, count=4))
    expected = np.unique(np.concatenate([chosen, *map(np.asarray, cKDTree(points).query_ball_point(points[chosen], 0.03))]))
    assert 4 < len(expected) < 1000
    assert np.array_equal(held_nodes(points, fixed), expected)


def test_fixed_errors_name_the_field():
    mesh = box(size=(1, 1, 1), cells=(2, 2, 2))
    with pytest.raises(TissueError, match=r"^beam.fixed.nodes: ids \[999\] out of range"):
        held_nodes(mesh.points, Fixed(nodes=(999,)), "beam")
    with pytest.raises(TissueError, match=r"^beam.fixed.region: .* holds no node"):
        held_nodes(mesh.points, Fixed(region=(0.1, 0.2, 0.1, 0.2, 0.1, 0.2)), "beam")
    with pytest.raises(TissueError, match="^count: counts nodes of a region"):
        validate(Fixed(count=2))


def test_rotation_matrix_is_x_then_y_then_z():
    r = rotation_matrix((90, 0, 0))
    assert np.allclose(r @ [0, 1, 0], [0, 0, 1])
    r = rotation_matrix((90, 90, 0))  # y -> z by the x turn, then z -> x by the y turn
    assert np.allclose(r @ [0, 1, 0], [1, 0, 0])


# ---- simulation ----------------------------------------------------------------------------------


def test_run_freezes_the_objects_built_before_it_for_its_length(backend):
    """Simulation.run freezes what is alive when it starts (gc.freeze): the collector's full
    passes no longer walk the simulation's objects during its steps (a floor step paused for tens
    of ms about once in 1,000 steps); after the run, even one that raised, they are collectable
    again (nothing frozen is ever freed)."""
    import gc

    sim = Simulation(SmallBeam())
    frozen = []
    sim.run(2, callback=lambda s: frozen.append(gc.get_freeze_count()))
    assert len(frozen) == 2 and min(frozen) > 0
    assert gc.get_freeze_count() == 0

    def fail(s):
        raise RuntimeError("a callback that fails")

    with pytest.raises(RuntimeError):
        sim.run(1, callback=fail)
    assert gc.get_freeze_count() == 0


def test_simulation_builds_only_free_motion_and_steps(backend):
    sim = Simulation(SmallBeam().with_overrides(["beam.position=0,0,1", "beam.orientation=0,0,90"]))
    assert [s.name for s in sim.stages] == ["free_motion"]
    body = sim.bodies["beam"]
    # Posed: rotated 90 degrees about z, then lifted; the held face (x = 0 in the body's frame) stays put.
    assert np.allclose(body.rest[body.fixed, 1], 0.0, atol=1e-12)
    assert np.allclose(body.rest[:, 2].mean(), 1.0)
    sim.run(3)
    assert sim.step_count == 3 and sim.time == pytest.approx(0.03)
    state = sim.state()["beam"]
    assert state["positions"].shape == (body.mesh.n_points, 3)
    assert np.allclose(state["displacement"][body.fixed], 0.0)
    assert state["positions"][:, 2].min() < 1.0 - 0.05  # sagging under gravity
    ms = sim.ms_per_step()
    assert {"free_motion", "free_motion: step"} <= set(ms)
    assert sim.stats.counters["cg_iterations"] >= 1 and "beam.cg_iterations" in sim.stats.counters
    assert "total" in sim.timing_table()
    stress = body.von_mises()
    assert stress.shape == (body.mesh.n_tets,) and np.all(stress >= 0) and stress.max() > 0
    assert body.nodal(stress).shape == (body.mesh.n_points,)


def test_mesh_generation_and_kernel_compilation_are_reported_on_their_own(backend, monkeypatch):
    import time

    import taichi as ti

    from tissue import body as body_module

    make_mesh = body_module._make_mesh

    def slow_mesh(body, name):
        time.sleep(0.05)
        return make_mesh(body, name)

    monkeypatch.setattr(body_module, "_make_mesh", slow_mesh)
    sim = Simulation(SmallBeam())
    assert sim.mesh_seconds >= 0.05

    @ti.kernel
    def fresh(a: ti.f64) -> ti.f64:    # new to this process: compiled on the first step
        return 2 * a

    class Probe:
        name = "probe"

        def step(self, sim):
            fresh(sim.time)

    sim.stages.append(Probe())
    sim.run(3)
    first, *rest = sim.compile_seconds_by_step
    assert first > 0 and rest == [0.0, 0.0]
    summary = sim.summary()
    assert summary["mesh_generation_seconds"] >= 0.05
    assert summary["kernels_compiled"] == sim.compiled().count >= 1
    assert summary["kernel_compilation_seconds_in_steps"] == pytest.approx(first, abs=1e-4)
    assert summary["kernel_compilation_seconds"] >= summary["kernel_compilation_seconds_in_steps"]
    table = sim.timing_table()
    assert "(median, step 1 left out)" in table and "mesh generation" in table
    assert f"({sim.compiled().count} kernels; {first:.3f} s of it in the steps, {first:.3f} s in step 1)" in table


def test_a_registered_stage_plugs_in_and_is_timed(backend):
    calls = []

    class Probe:
        name = "probe"

        def step(self, sim):
            calls.append(sim.step_count)

        def report(self):
            return {"inner": 0.001}, {"probe_count": len(calls)}

    def probe(sim):
        return Probe() if sim.scene.dt == 0.01 else None

    add_stage(probe, after="free_motion")
    try:
        sim = Simulation(SmallBeam())
        assert [s.name for s in sim.stages] == ["free_motion", "probe"]
        sim.run(2)
        assert calls == [0, 1]
        assert "probe: inner" in sim.ms_per_step(skip=0) and sim.stats.counters["probe_count"] == 2
        sim.scene = SmallBeam(dt=0.02)  # a scene that does not declare the layer gets no stage
        assert probe(sim) is None
    finally:
        STAGES.remove(probe)


def test_mesh_from_a_volume_file_is_scaled(tmp_path):
    mesh = beam(0.5, 0.1, 0.1, 3, 1)
    write_vtu(tmp_path / "bar.vtu", mesh.points, mesh.tets)
    spec = SmallBeam().with_overrides([f"beam.mesh={tmp_path / 'bar.vtu'}", "beam.scale=2"]).beam
    built = build_mesh(spec, "beam")
    assert built.n_tets == mesh.n_tets and np.isclose(np.ptp(built.points[:, 0]), 1.0)
    (tmp_path / "bad.vtu").write_text("not a mesh")
    with pytest.raises(TissueError, match="^beam.mesh: .*bad.vtu: cannot read"):
        build_mesh(SmallBeam().with_overrides([f"beam.mesh={tmp_path / 'bad.vtu'}"]).beam, "beam")


def test_simulation_refuses_an_invalid_scene_before_building(backend):
    with pytest.raises(TissueError, match="^beam.poisson"):
        Simulation(SmallBeam().with_overrides(["beam.poisson=0.5"]))


# ---- output helpers -------------------------------------------------------------------------------


def test_embedded_surface_follows_affine_motion_exactly():
    mesh = box(size=(1, 1, 1), cells=(2, 2, 2))
    rng = np.random.default_rng(1)
    surface = rng.uniform(-0.02, 1.02, size=(50, 3))  # inside and slightly outside
    emb = EmbeddedSurface(surface, np.array([[0, 1, 2]]), mesh.points, mesh.tets)
    assert np.allclose(emb.points(mesh.points), surface)
    a = np.array([[1.1, 0.2, 0.0], [0.0, 0.9, 0.1], [0.05, 0.0, 1.2]])
    moved = mesh.points @ a.T + [0.3, -0.1, 2.0]
    assert np.allclose(emb.points(moved), surface @ a.T + [0.3, -0.1, 2.0])
    assert np.allclose(emb.values(mesh.points[:, 0]), surface[:, 0])


def test_nice_ceiling():
    assert nice_ceiling(0.0) == 1.0
    assert nice_ceiling(1.0) == 1.0
    assert nice_ceiling(137.0) == 150.0
    assert nice_ceiling(0.0042) == pytest.approx(0.005)


# ---- the shipped scenes ---------------------------------------------------------------------------


def test_shipped_scenes_are_valid_and_described():
    catalogue = scenes.catalogue()
    assert {"beam", "liver", "organs"} <= set(catalogue)
    for name, cls in catalogue.items():
        scene = validate(cls())
        assert scene.bodies(), name
        assert cls.description() != cls.__name__, f"{name}: give the scene a docstring"
    assert set(scenes.load("organs")().bodies()) == {"liver", "stomach", "colon"}


def test_unknown_scene_suggests_a_name():
    with pytest.raises(TissueError, match=r"livr: unknown scene; did you mean 'liver'\?"):
        scenes.load("livr")


def test_scene_groups_can_be_built_directly():
    assert Solver(cg_iterations=5).cg_iterations == 5
    assert Render(scalars=None).scalars is None
    assert SmallBeam().steps == 5
