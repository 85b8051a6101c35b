"""What ``setup.cfg`` puts in a wheel: every folder of the package, and every data file it reads at run time."""

from __future__ import annotations

import fnmatch
import re
from pathlib import Path

import pytest
from setuptools.config.setupcfg import read_configuration

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def options(monkeypatch: pytest.MonkeyPatch) -> dict:
    monkeypatch.chdir(ROOT)  # setuptools finds the packages from the project's root
    return read_configuration(str(ROOT / "setup.cfg"))["options"]


def package_files() -> dict[str, list[Path]]:
    """The package's folders (as dotted names) with the files each holds directly, caches left out."""
    folders: dict[str, list[Path]] = {}
    for path in sorted((ROOT / "sb3_poplin").rglob("*")):
        if path.is_file() and "__pycache__" not in path.parts and path.suffix != ".pyc":
            name = ".".join(path.parent.relative_to(ROOT).parts)
            folders.setdefault(name, []).append(path)
    return folders


def test_every_folder_of_the_package_is_declared(options: dict) -> None:
    # a data-only folder (hyperparams/) missing here is copied with a setuptools warning, and not at all by a stricter
    # build backend
    assert sorted(options["packages"]) == sorted(package_files())


def packaged(path: Path, package_data: dict[str, list[str]]) -> bool:
    """Whether a pattern of ``package_data`` matches the file, relative to the folder of the package that names it."""
    for package, patterns in package_data.items():
        folder = ROOT.joinpath(*package.split("."))
        if folder in path.parents:
            relative = path.relative_to(folder).as_posix()
            if any(fnmatch.fnmatch(relative, pattern) for pattern in patterns):
                return True
    return False


def test_every_data_file_of_the_package_is_in_the_wheel(options: dict) -> None:
    files = [path for paths in package_files().values() for path in paths if path.suffix != ".py"]
    missing = [str(path.relative_to(ROOT)) for path in files if not packaged(path, options["package_data"])]
    assert not missing, f"files the package holds but setup.cfg's package_data leaves out: {missing}"
    assert ROOT / "sb3_poplin/hyperparams/poplin_cpu.yml" in files  # the zoo's default hyperparameter file


def test_only_the_runner_parses_command_lines_and_the_algorithm_imports_none_of_it() -> None:
    """argparse only in sb3_poplin/experiments/; the algorithm's modules import neither the runner nor the analyses."""
    package = Path(__file__).resolve().parent.parent / "sb3_poplin"
    tooling = ("experiments", "analysis")
    aliases = {"zoo.py", "compare.py", "resume.py", "presets.py", "demo.py"}  # python -m entry points, deprecated imports
    for path in package.rglob("*.py"):
        relative = path.relative_to(package)
        source = path.read_text()
        if relative.parts[0] != "experiments":
            assert "import argparse" not in source, f"{relative} parses a command line: move it to sb3_poplin/experiments"
        if relative.parts[0] not in tooling and str(relative) not in aliases:
            imports = re.findall(
                r"^\s*((?:from|import) sb3_poplin\.(?:experiments|analysis)\b"
                r"|from sb3_poplin import .*\b(?:experiments|analysis)\b)",
                source,
                re.MULTILINE,
            )
            assert not imports, f"{relative} imports {imports}: the algorithm must not depend on the runner"


def test_the_package_tests_import_nothing_from_benchmarks() -> None:
    """The benchmark scripts' tests live in benchmarks/tests; tests/ checks the package alone."""
    for path in (Path(__file__).resolve().parent).glob("*.py"):
        if path.name == Path(__file__).name:
            continue
        source = path.read_text()
        assert "load_benchmark" not in source and not re.search(r"^\s*(from|import) benchmarks", source, re.MULTILINE), path


def test_the_old_module_paths_are_the_runner_s_modules() -> None:
    import importlib
    import sys
    import warnings

    from sb3_poplin.experiments import checkpoints, compare, demo, presets, zoo

    for name, module in (("zoo", zoo), ("demo", demo)):  # entry points: no warning
        sys.modules.pop(f"sb3_poplin.{name}", None)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            assert importlib.import_module(f"sb3_poplin.{name}") is module
    for name, module in (("compare", compare), ("resume", checkpoints), ("presets", presets)):
        sys.modules.pop(f"sb3_poplin.{name}", None)
        with pytest.warns(DeprecationWarning, match=f"sb3_poplin.{name} moved to sb3_poplin.experiments"):
            assert importlib.import_module(f"sb3_poplin.{name}") is module
