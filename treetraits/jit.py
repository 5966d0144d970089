"""Compiled loops (numba) where NumPy would need many passes over the same data: the one
decorator every kernel is made with, so that all compile, cache and fail alike.

A kernel is compiled on its first call for that call's argument types (about half a
second each; a new combination of types or array layouts compiles again), and kept on
disk by numba's cache: in NUMBA_CACHE_DIR when it is set (the systemd unit points it into
its CacheDirectory), else in the `__pycache__` beside the module when that is writable,
else in the user's cache directory. Where none of these can be written (source that is
not a file), it is compiled in memory at every start. A module with kernels registers a
`warm_up` that calls them as real data would; the service imports every such module
(`kernel_modules` finds them by their `@kernel` lines, so none is left off a list) and
runs the warm-ups (`compile_all`) before READY.

Compiling needs memory that is first written and then made executable, which a process
under MemoryDenyWriteExecute (systemd) or PR_SET_MDWE refuses: `import numba` then fails,
and this module says so in a `PlatformError` instead of a traceback from llvmlite.
"""

from __future__ import annotations

import importlib.util
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import DTypeLike

from treetraits.errors import PlatformError

try:
    import numba
except PermissionError as exc:  # llvmlite's check that it may map executable memory
    raise PlatformError(
        "the compiled kernels (numba) cannot map executable memory here "
        f"({exc.strerror or exc}): remove MemoryDenyWriteExecute=yes from the service's "
        "unit, or the W^X policy (PR_SET_MDWE, SELinux execmem) that refuses it"
    ) from exc


KERNELS: list[Any] = []  # every kernel made, to check that warm-ups reach them all
_WARM_UPS: list[Callable[[], None]] = []


def kernel(function: Callable[..., Any]) -> Callable[..., Any]:
    """`numba.njit` as every kernel uses it: no Python objects inside, the GIL released
    while it runs (the service's receive threads go on beside a scan), cached on disk
    where there is a place for it."""
    try:
        compiled = numba.njit(cache=True, nogil=True)(function)
    except RuntimeError:  # "cannot cache function ...: no locator available for file"
        compiled = numba.njit(nogil=True)(function)
    KERNELS.append(compiled)
    return compiled


def warm_up(function: Callable[[], None]) -> Callable[[], None]:
    """Register a module's warm-up: a call of its kernels on a little made-up data of
    the types (and layouts) real data gives them. `compile_all` runs them."""
    _WARM_UPS.append(function)
    return function


def kernel_layout(array: Any, dtype: DTypeLike = np.float64) -> np.ndarray:
    """`array` in the one layout the kernels are compiled for (C-ordered, writable, of
    `dtype`): numba compiles a kernel anew for a read-only or strided array. An array
    already in it is returned as np.require would, without np.require's checks, which
    cost more than the small arrays a scan passes its kernels many times over
    (docs/performance.md)."""
    if isinstance(array, np.ndarray):
        flags = array.flags
        if flags.c_contiguous and flags.writeable and array.dtype == dtype:
            return array
    return np.require(array, dtype, ["C", "W"])


# A kernel's definition: `@kernel` (or `@jit.kernel`) at the start of a line.
_KERNEL_LINE = re.compile(rb"^[ \t]*@(?:\w+\.)*kernel\b", re.MULTILINE)


def kernel_modules(*packages: str) -> list[str]:
    """The modules of `packages` (sub-packages included) that make compiled kernels, found
    in their source, not by importing them: what `compile_all` needs imported, without a
    hand-kept list that a new module with kernels could be left off."""
    found = []
    for package in packages:
        spec = importlib.util.find_spec(package)
        for location in (spec and spec.submodule_search_locations) or ():
            root = Path(location)
            for path in sorted(root.rglob("*.py")):
                parts = path.relative_to(root).with_suffix("").parts
                if parts[-1] == "__init__":
                    parts = parts[:-1]
                # A folder without __init__.py (data, scripts) holds no module of ours.
                folders = (root.joinpath(*parts[:depth]) for depth in range(1, len(parts)))
                if all((folder / "__init__.py").is_file() for folder in folders) and (
                    _KERNEL_LINE.search(path.read_bytes())
                ):
                    found.append(".".join((package, *parts)))
    return found


def compile_all() -> None:
    """Compile (or load from the cache) the kernels of every module imported so far: the
    service does it before READY, so that its first scans do not wait for the compiler."""
    for function in _WARM_UPS:
        function()
