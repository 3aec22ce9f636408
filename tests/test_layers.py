"""The import contracts of pyproject.toml (``[tool.importlinter]``) hold, and they bite.

The packages live in separate top-level folders mapped by ``package-dir``, which
lint-imports cannot see from the repository's root (it walks ``nanoasm/`` alone). So the
tests link every file of every listed package into a temporary tree laid out as it is
installed, and run lint-imports there against the repository's pyproject.toml.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PYPROJECT = ROOT / "pyproject.toml"
LINT_IMPORTS = Path(sys.executable).parent / "lint-imports"

#: One module per contract, each breaking it: (path in the installed layout, its import).
VIOLATIONS = {
    "executor-no-sim": ("nanoasm/executor/_probe.py", "nanoasm.world.sim"),
    "world-below-planner": ("nanoasm/world/_probe.py", "nanoasm.planner"),
    "planner-below-executor": ("nanoasm/planner/_probe.py", "nanoasm.executor"),
    "drift-alone": ("nanoasm/drift/_probe.py", "nanoasm.schema"),
}


def installed_layout(dest: Path) -> Path:
    """Link the .py files of every package of pyproject.toml under ``dest`` as installed."""
    tool = tomllib.loads(PYPROJECT.read_text())["tool"]["setuptools"]
    dirs = tool["package-dir"]
    for package in tool["packages"]:
        parts = package.split(".")
        prefix = next(".".join(parts[:k]) for k in range(len(parts), 0, -1) if ".".join(parts[:k]) in dirs)
        source = ROOT / dirs[prefix] / Path(*parts[len(prefix.split(".")):])
        target = dest / Path(*parts)
        target.mkdir(parents=True, exist_ok=True)
        for f in source.glob("*.py"):
            (target / f.name).symlink_to(f)
    return dest


def lint_imports(tree: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(tree), "COLUMNS": "200"}
    return subprocess.run([str(LINT_IMPORTS), "--config", str(PYPROJECT), "--no-cache"], cwd=tree,
                          env=env, capture_output=True, text=True, timeout=300)


def contracts() -> dict[str, str]:
    """Contract id -> name, from pyproject.toml."""
    table = tomllib.loads(PYPROJECT.read_text())["tool"]["importlinter"]
    return {c["id"]: c["name"] for c in table["contracts"]}


def test_contracts_hold(tmp_path):
    run = lint_imports(installed_layout(tmp_path))
    assert run.returncode == 0, run.stdout + run.stderr
    assert f"{len(contracts())} kept, 0 broken" in run.stdout, run.stdout


def test_every_contract_breaks_on_a_forbidden_import(tmp_path):
    assert set(VIOLATIONS) == set(contracts())
    tree = installed_layout(tmp_path)
    for path, imported in VIOLATIONS.values():
        (tree / path).write_text(f"import {imported}\n")
    run = lint_imports(tree)
    assert run.returncode == 1, run.stdout + run.stderr
    assert f"0 kept, {len(VIOLATIONS)} broken" in run.stdout, run.stdout
    for name in contracts().values():
        assert f"{name} BROKEN" in run.stdout, run.stdout
    for path, imported in VIOLATIONS.values():
        probe = path.removesuffix(".py").replace("/", ".")
        assert f"{probe} -> {imported}" in run.stdout, run.stdout


def test_drift_may_import_param_alone(tmp_path):
    tree = installed_layout(tmp_path)
    param = tree / "nanoasm" / "param.py"
    if not param.exists():              # the stdlib-only validation module, as it will be
        param.write_text("import math\n")
    (tree / "nanoasm/drift/_probe.py").write_text("import nanoasm.param\n")
    run = lint_imports(tree)
    assert run.returncode == 0, run.stdout + run.stderr


def test_executor_modules_stay_small():
    """The executor's parts stay readable alone: no module over 400 lines, the assembly
    (procedure, push and execution) at most 300."""
    sizes = {p.name: len(p.read_text().splitlines()) for p in (ROOT / "executor").glob("*.py")}
    assert sizes["assembly.py"] <= 300
    assert not {name: n for name, n in sizes.items() if n > 400}
