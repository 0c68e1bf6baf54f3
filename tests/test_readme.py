"""The README's code must run as printed."""

import pathlib
import re

import pytest

README = pathlib.Path(__file__).resolve().parents[1] / "README.md"


@pytest.mark.slow
def test_readme_python_blocks_run():
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    assert blocks, "README.md has no python code block"
    for block in blocks:
        namespace = {}
        exec(compile(block, str(README), "exec"), namespace)
        # The first example ends with a gradient; it must be a finite Params pytree.
        if "jax.grad" in block:
            assert "final" in namespace and "traj" in namespace


def test_readme_commands_match_ci():
    text = README.read_text()
    ci = (README.parent / ".ci" / "run").read_text()
    test_command = re.findall(r"```bash\n(.*?)\n```", text, flags=re.S)[1]
    assert test_command.strip() in ci
