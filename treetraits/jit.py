"""Compiled loops (numba) where NumPy would need many passes over the same data: the one
decorator every kernel is made with, so that all compile, cache and fail alike.

A kernel is compiled on its first call for that call's argument types (about half a
second each; a new combination of types or array layouts compiles again), and kept on
disk by numba's cache: in NUMBA_CACHE_DIR when it is set (the systemd unit points it into
its CacheDirectory), else in the `__pycache__` beside the module when that is writable,
else in the user's cache directory. Where none of these can be written (source that is
not a file), it is compiled in memory at every start. A module with kernels registers a
`warm_up` that calls them as real data would; the service runs them all (`compile_all`)
before READY.

Compiling needs memory that is first written and then made executable, which a process
under MemoryDenyWriteExecute (systemd) or PR_SET_MDWE refuses: `import numba` then fails,
and this module says so in a `PlatformError` instead of a traceback from llvmlite.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

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


def compile_all() -> None:
    """Compile (or load from the cache) the kernels of every module imported so far: the
    service does it before READY, so that its first scans do not wait for the compiler."""
    for function in _WARM_UPS:
        function()
