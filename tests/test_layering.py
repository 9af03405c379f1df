"""The direction of imports (DESIGN 2) as import-linter contracts (``[tool.importlinter]`` in pyproject.toml):
``harness -> reports -> evaluation -> recognition -> sensors -> scenes``, and the core never imports
evaluation, reports, harness or the truth of ``scenes.perturb``: it sees only what a real robot has."""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("harness", "reports", "evaluation", "recognition", "sensors", "scenes")


def _lint_imports(cwd: Path) -> subprocess.CompletedProcess:
    exe = Path(sys.executable).with_name("lint-imports")
    return subprocess.run([str(exe), "--no-cache"], cwd=cwd, capture_output=True, text=True, timeout=300,
                          env={"PATH": str(exe.parent), "PYTHONPATH": str(cwd)})


def test_the_import_contracts_hold():
    out = _lint_imports(ROOT)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "2 kept, 0 broken" in out.stdout


def _toy_tree(root: Path, imports: dict[str, str]) -> None:
    """The six packages (and ``scenes.perturb``), empty but for ``imports`` (module path -> source), under the
    project's contracts."""
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]
    lines = ["[tool.importlinter]", f"root_packages = {list(config['root_packages'])!r}"]
    for c in config["contracts"]:
        lines.append("[[tool.importlinter.contracts]]")
        lines += [f"{k} = {v!r}" for k, v in c.items()]
    (root / "pyproject.toml").write_text("\n".join(lines).replace("'", '"') + "\n")
    for pkg in PACKAGES:
        (root / pkg).mkdir()
        (root / pkg / "__init__.py").write_text("")
    (root / "scenes" / "perturb.py").write_text("")
    for module, source in imports.items():
        (root / module).write_text(source)


def test_a_broken_contract_fails(tmp_path):
    """Both contracts bite: a sensor importing the core breaks the layers, the core reading the perturbation's
    truth breaks the forbidden contract (the same packages without those imports pass)."""
    clean = tmp_path / "clean"
    clean.mkdir()
    _toy_tree(clean, {"recognition/core.py": "import sensors\nimport scenes\n",
                      "evaluation/truth.py": "import scenes.perturb\n"})
    assert _lint_imports(clean).returncode == 0
    for name, imports in {"layers": {"sensors/bad.py": "import recognition\n"},
                          "truth": {"recognition/bad.py": "import scenes.perturb\n"}}.items():
        root = tmp_path / name
        root.mkdir()
        _toy_tree(root, imports)
        out = _lint_imports(root)
        assert out.returncode != 0, out.stdout
        assert "1 kept, 1 broken" in out.stdout, out.stdout
