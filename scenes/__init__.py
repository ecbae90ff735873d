"""The scenes `tissue run NAME` knows: one module per scene, found by its file name.

Each module defines one `tissue.scene.Scene` subclass (a dataclass with good defaults whose
docstring's first line says what it shows). Adding a scene is adding a module here; nothing to
register. `tissue run path/to/my_scene.py` runs a scene module kept anywhere else.
"""

from __future__ import annotations

import importlib
import importlib.util
import inspect
import pkgutil
from pathlib import Path

from tissue.errors import TissueError
from tissue.options import suggestion
from tissue.scene import Scene


def names() -> list[str]:
    """The scene names: the modules of this package, in alphabetical order."""
    return sorted(m.name for m in pkgutil.iter_modules(__path__) if not m.name.startswith("_"))


def _scene_class(module, where: str) -> type[Scene]:
    found = [c for _, c in inspect.getmembers(module, inspect.isclass)
             if issubclass(c, Scene) and c is not Scene and c.__module__ == module.__name__]
    if len(found) != 1:
        raise TissueError(f"{where}: a scene module must define exactly one Scene subclass, "
                          f"found {len(found)}{' (' + ', '.join(c.__name__ for c in found) + ')' if found else ''}")
    return found[0]


def load(name: str) -> type[Scene]:
    """The Scene class of scene `name`, or of the module file `name` if it ends in .py."""
    if name.endswith(".py"):
        path = Path(name)
        if not path.is_file():
            raise TissueError(f"{name}: no such scene file")
        spec = importlib.util.spec_from_file_location(f"scenes._file_{path.stem}", path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return _scene_class(module, name)
    known = names()
    if name not in known:
        raise TissueError(f"{name}: unknown scene{suggestion(name, known)}")
    return _scene_class(importlib.import_module(f"{__name__}.{name}"), f"scenes/{name}.py")


def catalogue() -> dict[str, type[Scene]]:
    """{name: Scene class} of every scene."""
    return {name: load(name) for name in names()}
