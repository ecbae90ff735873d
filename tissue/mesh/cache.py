"""An on-disk cache of generated meshes: a procedural organ takes seconds to make, milliseconds to load.
Its surface is cached too (`cached_arrays`): every tetrahedralisation of the organ starts from it;
so is a body's dense rest compliance (tissue.contact.warping), keyed by a hash of its matrix.

Files are `.npz` under `$TISSUE_CACHE/meshes/`, else `~/.cache/tissue/meshes/`, named by a hash of
what the mesh depends on: the generator's name and parameters, `VERSION`, the source of the
generating modules and the VTK version (marching cubes, smoothing and decimation are VTK's). A
file that cannot be read is regenerated and replaced; a cache that cannot be written is skipped.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from functools import lru_cache
from pathlib import Path
from typing import Callable

import numpy as np

from .tetmesh import TetMesh

# Bump by hand when the meshes change for a reason the hashed sources do not show.
VERSION = "1"
SOURCES = ("organs.py", "isosurface.py", "tetrahedralize.py", "closed_surface.py", "stuffing.py", "optimisation.py", "topology.py",
           "quality.py", "tetmesh.py")


def directory() -> Path:
    root = os.environ.get("TISSUE_CACHE") or Path.home() / ".cache" / "tissue"
    return Path(root) / "meshes"


@lru_cache(maxsize=None)
def _generator_hash() -> str:
    from importlib import metadata      # here: a run whose meshes need no cache need not import it

    digest = hashlib.sha256(VERSION.encode())
    for name in SOURCES:
        digest.update((Path(__file__).parent / name).read_bytes())
    try:
        digest.update(metadata.version("vtk").encode())
    except metadata.PackageNotFoundError:
        pass
    return digest.hexdigest()


def path_for(kind: str, **params) -> Path:
    """The cache file of the mesh `kind` made with these (JSON-able) parameters."""
    key = json.dumps([_generator_hash(), kind, params], sort_keys=True)
    return directory() / f"{kind}-{hashlib.sha256(key.encode()).hexdigest()[:20]}.npz"


def cached_arrays(make: Callable[[], dict], names: tuple[str, ...], kind: str, **params) -> dict:
    """The arrays `names` of the dict `make()` returns, from the cache when it holds them for
    (kind, params)."""
    path = path_for(kind, **params)
    try:
        with np.load(path, allow_pickle=False) as data:
            return {name: data[name] for name in names}
    except Exception:  # noqa: BLE001 - missing, or damaged in any way: a cache miss
        pass
    arrays = make()
    _write(path, **{name: arrays[name] for name in names})
    return arrays


def cached_mesh(make: Callable[[], TetMesh], kind: str, **params) -> TetMesh:
    """The mesh `make()` returns, from the cache when it holds one for (kind, params)."""
    made = []

    def arrays():
        made.append(make())
        return dict(points=made[0].points, tets=made[0].tets, source=np.array(made[0].source))

    data = cached_arrays(arrays, ("points", "tets", "source"), kind, **params)
    return made[0] if made else TetMesh(data["points"], data["tets"], source=str(data["source"]))


def _write(path: Path, **arrays) -> None:
    """Write aside, then rename: a reader never sees half a file, even with runs in parallel."""
    temporary = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path.parent, prefix=path.stem, suffix=".tmp", delete=False) as f:
            temporary = Path(f.name)
            np.savez(f, **arrays)
        os.replace(temporary, path)
    except OSError:  # read-only or full: run without the cache
        if temporary is not None:
            temporary.unlink(missing_ok=True)
