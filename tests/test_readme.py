"""The README's Python example runs as written and prints what it says."""
import re
from pathlib import Path

import numpy as np

README = Path(__file__).resolve().parent.parent / "README.md"


def test_readme_python_example_runs():
    block = re.search(r"```python\n(.*?)```", README.read_text(), re.S).group(1)
    scope = {}
    exec(compile(block, "README.md", "exec"), scope)
    assert abs(np.nanmedian(scope["res"].mean) - 0.5) < 0.01
    assert abs(np.nanmedian(scope["res"].gaussian) - 0.25) < 0.02
    assert np.linalg.norm(scope["smooth"], axis=1).mean() < 2.0      # MLS1 shrinks the sphere
    towards = np.array([0, 0, 10.0]) - scope["pts"]
    assert np.all(np.einsum("ij,ij->i", scope["n"], towards) > 0)        # facing the viewpoint
    assert scope["sv"].shape == (200_000,)


def test_readme_test_command_is_what_ci_runs():
    ci = (README.parent / ".ci" / "run").read_text()
    assert "make test" in ci and "make test" in README.read_text()
