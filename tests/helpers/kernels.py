"""Shared checks of compiled kernels (treetraits.jit) for the kernel tests."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any


def assert_warm_ups_cover(
    kernels: Iterable[Any], warm_ups: Iterable[Callable[[], None]], run: Callable[[], object]
) -> None:
    """The modules' warm-ups compile each kernel once, and `run` (real data through the
    code that calls them) compiles no other signature: the service's first scans do not
    wait for the compiler."""
    kernels = tuple(kernels)
    for warm_up in warm_ups:
        warm_up()
    warmed = [list(k.signatures) for k in kernels]
    assert all(len(signatures) == 1 for signatures in warmed)
    run()
    assert [list(k.signatures) for k in kernels] == warmed
