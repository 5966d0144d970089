"""One import root: a wheel built from the checkout installs `treetraits` and nothing else
at the top level, every package folder is in it, and the layers import one way."""

from __future__ import annotations

import ast
import re
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from tests.helpers.paths import REPO

# Folder at the repository's root -> its package under `treetraits`.
ROOTS = {
    "treetraits": "treetraits",
    "drivers": "treetraits.drivers",
    "firmware_bridge": "treetraits.firmware_bridge",
    "pipeline": "treetraits.pipeline",
    "service": "treetraits.service",
    "sim": "treetraits.sim",
}
# What each layer may import of ours (docs/architecture.md); errors, the version, the
# kernels' decorator and the file helpers are the root package's and every layer may
# import them.
ALLOWED = {
    "treetraits.drivers": {"treetraits.drivers"},
    "treetraits.firmware_bridge": {"treetraits.firmware_bridge", "treetraits.drivers"},
    "treetraits.pipeline": {"treetraits.pipeline", "treetraits.drivers"},
    "treetraits.sim": {"treetraits.sim", "treetraits.drivers", "treetraits.firmware_bridge"},
    "treetraits.service": {
        "treetraits.service",
        "treetraits.pipeline",
        "treetraits.drivers",
        "treetraits.firmware_bridge",
    },
    # The offline tools sit beside the service, on top of it: nothing on the robot imports
    # them, so the robot's install needs none of their dependencies.
    "treetraits.season": {
        "treetraits.season",
        "treetraits.service",
        "treetraits.pipeline",
        "treetraits.drivers",
    },
    "treetraits.export": {
        "treetraits.export",
        "treetraits.service",
        "treetraits.pipeline",
        "treetraits.drivers",
    },
}
SHARED = {
    "treetraits",
    "treetraits.errors",
    "treetraits.jit",
    "treetraits.files",
    "treetraits.readonly",  # stores read by a command that only reads them
    "treetraits.damage",  # damage reported by every reader of a recording
}


def package_dirs() -> dict[str, Path]:
    found = {}
    for folder, package in ROOTS.items():
        for init in sorted((REPO / folder).rglob("__init__.py")):
            parts = init.parent.relative_to(REPO / folder).parts
            found[".".join((package, *parts))] = init.parent
    return found


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> zipfile.ZipFile:
    """Built from a copy of the sources: a `build/` left in the checkout can hold modules
    that no longer exist."""
    out = tmp_path_factory.mktemp("wheel")
    source = out / "source"
    skip = shutil.ignore_patterns(".*", "build", "out", "tests", "bench", "docs", "*.egg-info")
    shutil.copytree(REPO, source, ignore=skip)
    result = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-w", str(out), str(source)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    (path,) = out.glob("treetraits-*.whl")
    return zipfile.ZipFile(path)


def test_the_wheel_installs_only_treetraits_at_the_top(wheel):
    tops = {name.split("/")[0] for name in wheel.namelist()}
    assert {t for t in tops if not t.endswith(".dist-info")} == {"treetraits"}


def test_every_package_folder_is_in_the_wheel(wheel):
    names = set(wheel.namelist())
    for package, folder in package_dirs().items():
        init = package.replace(".", "/") + "/__init__.py"
        assert init in names, f"{folder} is not packaged: add {package} to pyproject.toml"
    assert "treetraits/sim/data/citrusfarm_calibration_v1.json" in names


def test_outside_the_checkout_only_treetraits_is_ours(tmp_path):
    probe = (
        "import importlib.util as u, treetraits.service.replay, treetraits.sim.run\n"
        "print([n for n in ('drivers', 'pipeline', 'sim', 'firmware_bridge', 'service') "
        "if u.find_spec(n) is not None])"
    )
    result = subprocess.run(
        [sys.executable, "-c", probe], cwd=tmp_path, capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "[]"


def imports_of(path: Path, package: str) -> set[str]:
    """Our modules that `path` imports (absolute and relative)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                names.add(f"{base}.{node.module}" if node.module else base)
            elif node.module:
                names.add(node.module)
    return {n for n in names if n == "treetraits" or n.startswith("treetraits.")}


def test_the_layers_import_one_way():
    wrong = []
    for package, folder in package_dirs().items():
        layer = next((lay for lay in ALLOWED if package.startswith(lay)), None)
        if layer is None:
            continue  # the CLI and the evaluation sit on top and may import anything
        for module in folder.glob("*.py"):
            for name in imports_of(module, package):
                if name in SHARED:
                    continue
                if not any(name == a or name.startswith(a + ".") for a in ALLOWED[layer]):
                    wrong.append(f"{module.relative_to(REPO)} imports {name}")
    assert not wrong, "\n".join(wrong)


# --- the tests' own layout ------------------------------------------------------------------

TESTS = REPO / "tests"
# Folders of tests/ that hold no tests: the shared builders and the fixture data.
NOT_TESTS = {"helpers", "fixtures"}
# `from tests... import` or `import tests...` in a string (code a test hands a subprocess).
IMPORT_IN_TEXT = re.compile(r"\b(?:from|import)\s+(tests(?:\.\w+)*)")


def modules_of_tests() -> list[Path]:
    """Every Python file of tests/ (the fixture data left out)."""
    return sorted(p for p in TESTS.rglob("*.py") if "fixtures" not in p.relative_to(TESTS).parts)


def module_of(path: Path) -> str:
    return ".".join(path.relative_to(REPO).with_suffix("").parts)


def is_test_module(name: str) -> bool:
    """`tests.<...>.test_*` or `tests.conftest`: a module with tests or fixtures."""
    parts = name.split(".")
    return parts[0] == "tests" and (parts[-1] == "conftest" or parts[-1].startswith("test_"))


def modules_imported(path: Path) -> set[str]:
    """Every module (and `from X import name`: X.name too) that `path` imports, relative
    imports resolved, plus the `tests.` imports in its strings."""
    package = module_of(path).rsplit(".", 1)[0]
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                module = f"{base}.{node.module}" if node.module else base
            else:
                module = node.module or ""
            names.add(module)
            names |= {f"{module}.{a.name}" for a in node.names}
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            names |= set(IMPORT_IN_TEXT.findall(node.value))
    return names


def test_no_test_module_imports_another():
    """Test modules share code through tests/helpers only: a test module imported by
    another runs its module-level code twice and ties the two files together."""
    wrong = [
        f"{path.relative_to(REPO)} imports {name}"
        for path in modules_of_tests()
        for name in sorted(modules_imported(path))
        if is_test_module(name)
    ]
    assert not wrong, "\n".join(wrong)


def test_the_tests_mirror_the_code():
    """Each test file sits in the folder of tests/ that mirrors the code it tests (a
    package or folder of the checkout, or of `treetraits/`); at tests/ itself only the
    tests of the root package (`treetraits/<name>.py`) and of the packaging. Every folder
    of tests is a package (unique module names)."""
    wrong = []
    for path in modules_of_tests():
        parts = path.relative_to(TESTS).parts
        folder, name = parts[:-1], parts[-1]
        if folder and folder[0] in NOT_TESTS:
            if name.startswith("test_"):
                wrong.append(f"{path.relative_to(REPO)}: tests in tests/{folder[0]}")
            continue
        if not (path.parent / "__init__.py").exists():
            wrong.append(f"{path.relative_to(REPO)}: no __init__.py beside it")
        if not name.startswith("test_"):
            continue
        if not folder:
            subject = name.removeprefix("test_")
            if name != "test_packaging.py" and not (REPO / "treetraits" / subject).is_file():
                wrong.append(f"{path.relative_to(REPO)}: not a test of treetraits/{subject}")
        elif not any((root / Path(*folder)).is_dir() for root in (REPO, REPO / "treetraits")):
            wrong.append(f"{path.relative_to(REPO)}: no folder {Path(*folder)} in the code")
    assert not wrong, "\n".join(wrong)
