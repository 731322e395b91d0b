"""Starting node processes safely from any caller: a script without a ``__main__`` guard, a
Jupyter kernel, a source tree beside an installed canbrake, a user's own controller module.

Used by :mod:`canbrake.run` (the orchestrator) and :mod:`canbrake.nodes`' processes."""
from __future__ import annotations

import os
import sys
import types
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from canbrake.scenario import Scenario, ScenarioError

#: the directory this canbrake package was imported from; every node process must import the same
PACKAGE_ENV = {"CANBRAKE_PACKAGE_DIR": str(Path(__file__).resolve().parent)}


@contextmanager
def children_skip_main() -> Iterator[None]:
    """While starting node processes, show multiprocessing a ``__main__`` without a file or spec.

    A ``spawn`` or ``forkserver`` child re-imports the parent's main module (as ``__mp_main__``)
    before it unpickles its target; for a user's script without an ``if __name__ == "__main__":``
    guard that re-runs the script in every node. The nodes need nothing from ``__main__`` (their
    target is :func:`_child_main`), so they are started with an empty stand-in, as from an
    interactive session or a Jupyter kernel."""
    real = sys.modules.get("__main__")
    sys.modules["__main__"] = types.ModuleType("__main__")
    try:
        yield
    finally:
        if real is not None:
            sys.modules["__main__"] = real


@contextmanager
def server_imports_this_canbrake() -> Iterator[None]:
    """Start the forkserver so that it preloads *this* canbrake, not one in the working directory.

    The server runs ``python -c ...``, whose ``sys.path`` starts with the working directory (and
    Python 3.11 ignores the ``sys_path`` it is handed), so from a source tree it would import that
    tree's canbrake while the orchestrator runs the installed one. PYTHONSAFEPATH (3.11+) drops the
    working directory; PYTHONPATH adds this package's directory when it is not a site directory."""
    import site

    root = str(Path(__file__).resolve().parent.parent)
    saved = {k: os.environ.get(k) for k in ("PYTHONSAFEPATH", "PYTHONPATH")}
    cwd = os.getcwd()
    try:
        os.environ["PYTHONSAFEPATH"] = "1"
        sites = {str(Path(p).resolve()) for p in site.getsitepackages() + [site.getusersitepackages()]}
        if root not in sites:
            os.environ["PYTHONPATH"] = os.pathsep.join([root] + ([saved["PYTHONPATH"]] if saved["PYTHONPATH"] else []))
        if sys.version_info < (3, 11):  # no PYTHONSAFEPATH: make the working directory this root
            os.chdir(root)
        yield
    finally:
        os.chdir(cwd)
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def check_same_package(env: dict[str, str]) -> None:
    """A node process refuses to run a different canbrake than its orchestrator's."""
    want = env.get("CANBRAKE_PACKAGE_DIR")
    have = PACKAGE_ENV["CANBRAKE_PACKAGE_DIR"]
    if want and want != have:
        raise RuntimeError(f"node process imported canbrake from {have}, the orchestrator from {want} "
                           f"(a stale forkserver? set CANBRAKE_START_METHOD=spawn)")
    import importlib

    for mod in filter(None, env.get("CANBRAKE_IMPORT", "").split(",")):
        importlib.import_module(mod)  # registers the scenario's user-defined controller


def controller_modules(scn: Scenario) -> list[str]:
    """Modules a node process must import to find the scenario's controller (a user's controller
    registered with :func:`canbrake.control.base.register` outside canbrake); [] for built-ins.
    Raises :class:`ScenarioError` for a controller defined in ``__main__`` (a script or notebook),
    which no other process can import."""
    from canbrake.control.base import _REGISTRY, available

    available()
    mod = getattr(_REGISTRY.get(scn.controller.name), "__module__", None) or ""
    if mod in ("__main__", "__mp_main__"):
        raise ScenarioError(f"controller.name: controller {scn.controller.name!r} is defined in your script or "
                            f"notebook (__main__), which node processes cannot import: move it into a module, "
                            f"or run with bus='inprocess' or bus='virtual'")
    return [] if not mod or mod == "canbrake" or mod.startswith("canbrake.") else [mod]


class _CallableModule(types.ModuleType):
    """A submodule that is also the API function of the same name (``canbrake.run``,
    ``canbrake.sweep``): importing a submodule rebinds the package attribute to the module, so the
    module itself is made callable and calls :mod:`canbrake.api`'s function."""

    def __call__(self, *args: object, **kwargs: object) -> object:
        from canbrake import api

        return getattr(api, self.__name__.rsplit(".", 1)[-1])(*args, **kwargs)


def make_module_callable(name: str) -> None:
    """Let ``canbrake.<name>(...)`` call the API whichever of module or function was imported first."""
    sys.modules[name].__class__ = _CallableModule
