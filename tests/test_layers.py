"""The layers of hvc point one way (issue 20 item 1): the import-linter contracts in
pyproject.toml ([tool.importlinter]) hold, and a wrong-way import, even one hidden inside a
function, breaks them."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("importlinter")

ROOT = Path(__file__).resolve().parents[1]


def lint_imports(package_parent: Path) -> subprocess.CompletedProcess:
    """`lint-imports` with the repository's contracts, on the hvc package found in `package_parent`."""
    env = {**os.environ, "PYTHONPATH": str(package_parent)}
    return subprocess.run([sys.executable, "-c", "import sys; from importlinter.cli import lint_imports_command; "
                           "sys.exit(lint_imports_command())",
                           "--config", str(ROOT / "pyproject.toml"), "--no-cache"],
                          cwd=package_parent, env=env, capture_output=True, text=True, timeout=300)


def test_the_import_contracts_hold():
    run = lint_imports(ROOT)
    assert run.returncode == 0, run.stdout + run.stderr


@pytest.mark.parametrize("module, line", [
    ("hvc/mocap/wrong_way.py", "from hvc.lowlevel.library import ExpertLibrary\n"),
    ("hvc/envs/wrong_way.py", "def later():\n    from hvc.controllers.base import ControlledEnv\n"),
    ("hvc/lowlevel/wrong_way.py", "def later():\n    import hvc.runtime.hl_train\n"),
    ("hvc/analysis/wrong_way.py", "from hvc.runtime import run_dirs\n"),
])
def test_a_wrong_way_import_breaks_the_contracts(tmp_path, module, line):
    shutil.copytree(ROOT / "hvc", tmp_path / "hvc", ignore=shutil.ignore_patterns("__pycache__", "data"))
    (tmp_path / module).write_text(line)
    run = lint_imports(tmp_path)
    assert run.returncode != 0, run.stdout
    assert f"{module[:-3].replace('/', '.')} ->" in run.stdout, run.stdout
