"""The on-disk mesh cache: a cached mesh is the generated one exactly, keyed by what made it, under
$TISSUE_CACHE, and a damaged file is regenerated."""

import numpy as np
import pytest

from tissue.mesh import box, cache
from tissue.mesh.organs import organ_mesh


@pytest.fixture
def cache_dir(tmp_path, monkeypatch):
    monkeypatch.setenv("TISSUE_CACHE", str(tmp_path))
    return tmp_path / "meshes"


def counted(make):
    """make, and a list that grows by one at each call."""
    calls = []

    def wrapped():
        calls.append(1)
        return make()

    return wrapped, calls


def same(a, b):
    return (a.source == b.source and a.points.dtype == b.points.dtype and a.tets.dtype == b.tets.dtype
            and np.array_equal(a.points, b.points) and np.array_equal(a.tets, b.tets))


def test_an_organ_comes_back_from_the_cache_exactly_as_generated(cache_dir, monkeypatch):
    made = organ_mesh("stomach", target_tets=300)
    assert len(list(cache_dir.glob("organ-*.npz"))) == 1

    def no_generation(*args, **kwargs):
        raise AssertionError("generated again instead of loaded")

    monkeypatch.setattr("tissue.mesh.tetrahedralize.tetrahedralize", no_generation)
    assert same(organ_mesh("stomach", target_tets=300), made)


def test_the_key_follows_the_parameters_and_the_version(cache_dir, monkeypatch):
    key = cache.path_for("organ", name="liver", tets=1300)
    assert key == cache.path_for("organ", tets=1300, name="liver")
    assert key != cache.path_for("organ", name="liver", tets=1301)
    assert key != cache.path_for("organ", name="stomach", tets=1300)
    monkeypatch.setattr(cache, "VERSION", cache.VERSION + "+1")
    cache._generator_hash.cache_clear()
    try:
        assert key != cache.path_for("organ", name="liver", tets=1300)
    finally:
        cache._generator_hash.cache_clear()


def test_each_parameter_set_is_made_once(cache_dir):
    make, calls = counted(lambda: box(cells=(2, 1, 1)))
    for _ in range(2):
        cache.cached_mesh(make, "test", cells=2)
    assert len(calls) == 1
    cache.cached_mesh(make, "test", cells=3)
    assert len(calls) == 2 and len(list(cache_dir.glob("test-*.npz"))) == 2
    assert not list(cache_dir.glob("*.tmp"))


@pytest.mark.parametrize("damage", [b"", b"not a zip file", b"PK\x03\x04truncated"])
def test_a_damaged_file_is_regenerated_and_replaced(cache_dir, damage):
    make, calls = counted(lambda: box(cells=(2, 1, 1)))
    made = cache.cached_mesh(make, "test")
    path = cache.path_for("test")
    path.write_bytes(damage)
    assert same(cache.cached_mesh(make, "test"), made) and len(calls) == 2
    assert same(cache.cached_mesh(make, "test"), made) and len(calls) == 2   # the file was rewritten


def test_a_file_with_other_arrays_is_regenerated(cache_dir):
    make, calls = counted(lambda: box(cells=(2, 1, 1)))
    cache_dir.mkdir(parents=True)
    np.savez(cache.path_for("test"), points=np.zeros((3, 3)))
    assert same(cache.cached_mesh(make, "test"), make()) and len(calls) == 2


def test_the_cache_lives_under_TISSUE_CACHE_else_the_home(cache_dir, monkeypatch, tmp_path):
    assert cache.directory() == cache_dir
    monkeypatch.delenv("TISSUE_CACHE")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert cache.directory() == tmp_path / "home" / ".cache" / "tissue" / "meshes"


def test_an_unwritable_cache_is_skipped(tmp_path, monkeypatch):
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    monkeypatch.setenv("TISSUE_CACHE", str(blocker))     # meshes/ cannot be made under a file
    assert same(cache.cached_mesh(lambda: box(cells=(2, 1, 1)), "test"), box(cells=(2, 1, 1)))
    assert not (blocker / "meshes").exists()


def test_an_organ_with_other_tets_starts_from_the_cached_surface(cache_dir, monkeypatch):
    """The organ's surface (marching cubes, smoothing, decimation: most of an organ's seconds) is
    cached once for any number of tetrahedra: the stomach at 300 then at 320 tetrahedra extracts
    it once, and the second mesh equals one made from a freshly extracted surface."""
    from tissue.mesh import organs

    organs._cached.cache_clear()
    organ_mesh("stomach", target_tets=300)
    assert len(list(cache_dir.glob("organ_surface-*.npz"))) == 1
    extract = organs._extract

    def no_extraction(*args, **kwargs):
        raise AssertionError("the surface was extracted again")

    monkeypatch.setattr(organs, "_extract", no_extraction)
    organs._cached.cache_clear()
    from_cache = organ_mesh("stomach", target_tets=320)
    monkeypatch.setattr(organs, "_extract", extract)
    for path in cache_dir.glob("*.npz"):
        path.unlink()
    organs._cached.cache_clear()
    try:
        assert same(from_cache, organ_mesh("stomach", target_tets=320))
    finally:
        organs._cached.cache_clear()


def test_a_rest_compliance_is_inverted_once_per_rest_matrix_and_held_nodes(cache_dir, monkeypatch, backend):
    """The warped compliance's dense A₀⁻¹ is cached under a hash of A₀ and the held nodes: a second
    body with the same mesh, material, dt, damping and holds reads it back (no inversion), the
    same bits as the inversion gave; other held nodes make another A₀⁻¹."""
    from tissue.contact import warping
    from tissue.fem import CorotationalFEM, Material
    from tissue.solver import ImplicitEuler

    mesh = box(size=(0.1, 0.04, 0.04), cells=(4, 2, 2))

    def warped(held):
        solver = ImplicitEuler(CorotationalFEM(mesh, Material(5e4, 0.3, 1000.0)), 0.02, rayleigh_mass=0.1,
                               rayleigh_stiffness=0.01, fixed=held)
        return warping.WarpedCompliance(solver)

    clamped = np.flatnonzero(mesh.points[:, 0] == 0)
    first = warped(clamped).C0_host
    assert len(list(cache_dir.glob("rest_compliance-*.npz"))) == 1
    inverse = warping.rest_compliance
    counting, inversions = counted(lambda: None)

    def counted_inverse(*args, **kwargs):
        counting()
        return inverse(*args, **kwargs)

    monkeypatch.setattr(warping, "rest_compliance", counted_inverse)
    assert np.array_equal(warped(clamped).C0_host, first) and not inversions
    warped(clamped[:3])
    assert len(inversions) == 1 and len(list(cache_dir.glob("rest_compliance-*.npz"))) == 2
