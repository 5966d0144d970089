"""`treetraits.jit.kernel`: kernels cached where NUMBA_CACHE_DIR says (the systemd unit's
CacheDirectory) and loaded from there by the next process; compiled in memory where no
cache can be kept."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np

from tests.helpers.paths import REPO
from treetraits.jit import kernel, kernel_layout, kernel_modules
from treetraits.service.runtime import KERNEL_PACKAGES

_LOAD_PIPELINE = """
from treetraits import jit
from treetraits.service.runtime import load_pipeline
load_pipeline()
kernels = [k for k in jit.KERNELS if k.signatures]
print(len(kernels), sum(len(k.signatures) for k in kernels),
      sum(sum(k.stats.cache_hits.values()) for k in kernels),
      sum(sum(k.stats.cache_misses.values()) for k in kernels))
"""


def test_kernels_are_cached_in_numba_cache_dir_and_loaded_from_it(tmp_path):
    """What `make install` does as the service's user (systemd/install.sh) and the service
    then does before READY: the first process compiles every kernel into NUMBA_CACHE_DIR,
    the next compiles none."""
    cache = tmp_path / "numba"
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    outputs = []
    for _ in range(2):
        run = subprocess.run(
            [sys.executable, "-c", _LOAD_PIPELINE],
            env=env,
            capture_output=True,
            text=True,
            timeout=600,
        )
        assert run.returncode == 0, run.stderr
        outputs.append([int(word) for word in run.stdout.split()])
    (kernels, compiled, hits, misses), (kernels_after, *_, hits_after, misses_after) = outputs
    assert kernels >= 2 and kernels_after == kernels
    assert compiled >= kernels  # one signature each, a few two
    assert (hits, misses) == (0, compiled)  # compiled, and written to the cache
    assert (hits_after, misses_after) == (compiled, 0)  # the next process loads them
    assert list(cache.rglob("packet._fill_points-*.nbi"))


def test_a_kernel_without_a_cache_location_is_compiled_in_memory():
    namespace = {"kernel": kernel}
    source = "@kernel\ndef total(a):\n    s = 0\n    for x in a:\n        s += x\n    return s\n"
    exec(compile(source, "<typed at a prompt>", "exec"), namespace)  # no file: no cache
    assert namespace["total"](np.arange(10)) == 45


def test_kernel_layout_is_c_ordered_writable_and_of_the_type_asked():
    """An array in the kernels' layout is passed on as it is (no copy); any other is
    copied into it, as np.require copies."""
    ready = np.arange(12.0).reshape(4, 3)
    assert kernel_layout(ready) is ready
    assert kernel_layout(np.arange(4), np.int64).dtype == np.int64
    frozen = ready.copy()
    frozen.flags.writeable = False
    for other in (ready[::-1], ready.T, ready.astype(np.float32), frozen, ready.tolist()):
        laid = kernel_layout(other)
        assert laid.flags.c_contiguous and laid.flags.writeable and laid.dtype == np.float64
        assert np.array_equal(laid, np.asarray(other, dtype=float))
        assert laid is not other


_SERVICE_WARM_UP = """
import importlib, sys
from treetraits import jit
from treetraits.service.runtime import load_pipeline
load_pipeline()  # what the service does before READY
for module in sys.argv[1:]:  # every module that makes kernels, imported now if not yet
    importlib.import_module(module)
print(*(f"{k.py_func.__module__}.{k.__name__}" for k in jit.KERNELS if not k.signatures))
"""


def _modules_with_kernels() -> list[str]:
    repo = REPO
    modules = []
    for folder in ("drivers", "pipeline", "service", "sim", "firmware_bridge", "treetraits"):
        for path in (repo / folder).rglob("*.py"):
            if "\n@kernel" in path.read_text():
                parts = path.relative_to(repo).with_suffix("").parts
                prefix = () if parts[0] == "treetraits" else ("treetraits",)
                modules.append(".".join(prefix + parts))
    return modules


def test_the_service_compiles_every_kernel_before_ready():
    """A kernel left to compile at its first call would hold the service's first scans
    for a second or more: every module with kernels is among (or imported by) the
    modules the service imports before READY, and registers a warm-up that reaches
    each of its kernels."""
    modules = _modules_with_kernels()
    assert "treetraits.drivers.velodyne.packet" in modules
    run = subprocess.run(
        [sys.executable, "-c", _SERVICE_WARM_UP, *modules],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "", f"not compiled before READY: {run.stdout}"


def test_kernel_modules_finds_the_modules_that_make_kernels(tmp_path, monkeypatch):
    """What the service imports before READY is found in the source: a new module with
    kernels cannot be left off a list."""
    made = "from treetraits.jit import kernel\n\n\n@kernel\ndef f(a):\n    return a\n"
    files = {
        "__init__.py": "",
        "made.py": made,
        "plain.py": "def kernel(a):\n    return a\n",  # the name alone makes none
        "inner/__init__.py": "",
        "inner/deep.py": made.replace("@kernel", "@jit.kernel"),
        "data/loose.py": made,  # not in a package: no module of ours
    }
    for name, text in files.items():
        path = tmp_path / "probe" / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    monkeypatch.syspath_prepend(str(tmp_path))
    assert sorted(kernel_modules("probe")) == ["probe.inner.deep", "probe.made"]


def test_the_service_looks_for_kernels_wherever_there_are_some():
    assert sorted(kernel_modules(*KERNEL_PACKAGES)) == sorted(_modules_with_kernels())
