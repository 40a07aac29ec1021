"""The README's Python example runs as written (in a fresh process, in a scratch folder), and the
README holds the two commands a fresh machine needs."""

import os
import re
import subprocess
import sys
from pathlib import Path

README = Path(__file__).resolve().parents[1] / "README.md"


def _blocks(lang):
    return re.findall(rf"^```{lang}\n(.*?)^```$", README.read_text(), flags=re.S | re.M)


def test_readme_python_example_runs(tmp_path):
    (code,) = _blocks("python")
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True,
                          text=True, timeout=900, env={**os.environ, "JAX_PLATFORMS": "cpu"})
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = proc.stdout.splitlines()
    assert "scratches kept" in out[0]
    assert "targets must be at least 16x16" in out[-1]  # the refusal, caught by JscratchError
    for name in ("design.npz", "result.npz", "metrics.json", "config.json", "view0_render.png"):
        assert (tmp_path / "my_board" / name).is_file(), name


def test_readme_has_main_and_test_commands():
    (main,) = _blocks("sh main")
    (test,) = _blocks("sh test")
    assert "python -m jscratch.design" in main and "pip install" in main
    assert "pytest" in test and 'pip install -e ".[test]"' in test
    ci = (README.parent / ".ci" / "run").read_text()
    assert "sh test" in ci  # .ci/run runs exactly the README's test command
