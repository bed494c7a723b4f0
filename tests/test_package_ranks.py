"""The package tree is the code map (issue 65): sub-packages ranked by the data flow, each importing only its
own sub-package and lower ranks, anywhere in a module (inside functions and under TYPE_CHECKING too); no
import circles; the modules that moved keep working at their old paths."""

import ast
import importlib
import subprocess
import sys
from pathlib import Path

import pytest

import softac

PACKAGE = Path(softac.__file__).parent
# lowest first; a module of rank r imports modules of rank <= r. errors and version: anyone's
RANKS = ["base", "config", "envs", "replay", "learner", "run", "outputs", "agent", "peers", "sweep", "cli"]
LEAVES = {"softac.errors", "softac.version"}
TOP = {"softac", "softac.__main__"}  # the package's face and `python -m softac`: above every rank


def module_name(path: Path) -> str:
    return ".".join(["softac", *path.relative_to(PACKAGE).with_suffix("").parts]).removesuffix(".__init__")


def softac_imports(source: str, importer: str) -> set[str]:
    """The softac modules a module imports, anywhere in it. `from softac.x import y` counts as softac.x.y where
    that is a module (a sub-module imported by name), else as softac.x; relative imports are resolved."""
    found = set()
    package = importer if (PACKAGE / Path(*importer.split(".")[1:]) / "__init__.py").exists() else importer.rsplit(".", 1)[0]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names if alias.name.split(".")[0] == "softac"}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package.split(".")[: len(package.split(".")) - node.level + 1] + ([base] if base else []))
            if base.split(".")[0] != "softac":
                continue
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                found.add(sub if is_module(sub) else base)
    return found


def is_module(name: str) -> bool:
    parts = name.split(".")[1:]
    if not parts:  # the package itself
        return True
    path = PACKAGE / Path(*parts)
    return path.with_suffix(".py").exists() or (path / "__init__.py").exists()


def rank(module: str) -> float:
    if module in LEAVES:
        return -1
    if module in TOP:
        return len(RANKS)
    return RANKS.index(module.split(".")[1])


def package_imports() -> dict[str, set[str]]:
    return {module_name(path): softac_imports(path.read_text(), module_name(path)) for path in PACKAGE.rglob("*.py")}


def back_imports(imports: dict[str, set[str]]) -> list[str]:
    return sorted(f"{importer} (rank {RANKS[int(rank(importer))] if 0 <= rank(importer) < len(RANKS) else importer}) "
                  f"imports {imported}"
                  for importer, found in imports.items() for imported in found if rank(imported) > rank(importer))


def test_every_module_has_a_rank():
    """A new top-level module or sub-package must be placed in RANKS (and in docs/development.md's map)."""
    unranked = []
    for module in package_imports():
        try:
            rank(module)
        except ValueError:
            unranked.append(module)
    assert unranked == []


def test_no_module_imports_a_higher_rank():
    assert back_imports(package_imports()) == []


@pytest.mark.parametrize("planted", [
    "from softac.run.loop import TrainingLoop\n",
    "def f():\n    from softac.outputs import plots\n",
    "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from softac.agent import SAC\n",
    "import softac.cli.commands\n",
    "from softac.learner.learner import Learner\n",
])
def test_a_planted_back_import_is_found(planted):
    """The check itself: a learner-level import planted in the config (at module level, in a function, under
    TYPE_CHECKING, as `import x.y`) is reported."""
    imports = package_imports()
    name = "softac.config.sac_config"
    before = back_imports(imports)
    imports[name] = imports[name] | softac_imports(planted, name)
    new = sorted(set(back_imports(imports)) - set(before))
    assert len(new) == 1 and new[0].startswith(f"{name} (rank config) imports softac."), new


def test_the_package_has_no_import_cycle():
    """No module of softac imports one that imports it back: not at run time, not inside a function, not for
    type hints (a reader need not hold a circle in mind). A package's __init__ that re-exports its own
    modules (config, cli) is part of its package, not a circle."""
    imports = {name: {m for m in found if m != name and not name.startswith(f"{m}.")}
               for name, found in package_imports().items()}

    def reaches(start: str, goal: str, seen: set[str]) -> bool:
        for module in imports.get(start, ()):
            if module == goal or (module not in seen and reaches(module, goal, seen | {module})):
                return True
        return False

    assert [m for m in sorted(imports) if reaches(m, m, {m})] == []


def test_no_module_below_the_agent_imports_it():
    """The agent composes the parts (learner, collector, run state, loop); none of them imports it, not even for
    a type or inside a function: only the ranks above it do."""
    importers = sorted(name for name, found in package_imports().items()
                       if "softac.agent" in found and rank(name) <= rank("softac.agent") and name != "softac.agent")
    assert importers == []


@pytest.mark.parametrize("old", sorted(softac.MOVED))
def test_a_moved_module_is_the_same_module_at_its_old_path(old):
    assert importlib.import_module(f"softac.{old}") is importlib.import_module(f"softac.{softac.MOVED[old]}")


def test_python_m_at_an_old_path_runs_the_module():
    done = subprocess.run([sys.executable, "-m", "softac.bench", "--help"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and "usage:" in done.stdout, done.stderr
