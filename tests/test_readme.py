"""The README's Python snippet runs as written, and imports nothing it does not use."""
import ast
import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


def _snippets():
    return re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)


def test_python_snippet_runs_and_uses_its_imports():
    (code,) = _snippets()
    tree = ast.parse(code)
    imported = {a.asname or a.name.split(".")[0] for node in ast.walk(tree)
                if isinstance(node, (ast.Import, ast.ImportFrom)) for a in node.names}
    used = {node.id for node in ast.walk(tree) if isinstance(node, ast.Name)}
    assert imported <= used, f"imported but unused: {imported - used}"
    scope = {}
    exec(compile(code, str(README), "exec"), scope)
    assert scope["kpd"].kp.shape == (20, 3, 340)        # the shape the snippet promises
    assert "(20, 3, 340)" in code


@pytest.mark.parametrize("command", ["pytest -m \"not slow\"", "kpifs demo -o demo_output",
                                     "kpifs info curve.fits"])
def test_readme_names_the_commands(command):
    assert command in README.read_text()
