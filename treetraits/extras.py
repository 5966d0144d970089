"""The optional dependency groups of the offline tools (pyproject.toml's extras).

The robot's install is the core only: the service never imports Dask, matplotlib or
protobuf. A command that needs an extra checks for it first, so a missing one is one line
naming what to install, not a traceback halfway through the work.
"""

from __future__ import annotations

import importlib.util

from treetraits.errors import MissingExtraError

# extra -> the top-level modules it provides (import names, not distribution names).
EXTRA_MODULES: dict[str, tuple[str, ...]] = {
    "season": ("dask", "distributed", "matplotlib"),
    "export": ("google.protobuf", "foxglove_schemas_protobuf"),
    "eval": ("matplotlib",),
}


def _missing(module: str) -> bool:
    try:
        return importlib.util.find_spec(module) is None
    except (ImportError, ValueError):  # a parent package missing, or a broken one
        return True


def require_extra(extra: str, command: str, modules: tuple[str, ...] | None = None) -> None:
    """Raise MissingExtraError when a module of `extra` (or of `modules`, the part of it
    that `command` uses) cannot be imported."""
    missing = [m for m in modules or EXTRA_MODULES[extra] if _missing(m)]
    if missing:
        raise MissingExtraError(
            f"{command} needs the '{extra}' extra ({', '.join(missing)} not installed): "
            f"pip install 'treetraits[{extra}]'"
        )
