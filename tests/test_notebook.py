"""The research notebook ``notebooks/quickstart.ipynb`` runs top to bottom (at toy size).

The kernel is the interpreter running pytest: a ``python3`` kernelspec pointing at
``sys.executable`` is installed into a temporary prefix and put first on ``JUPYTER_PATH`` (a
kernelspec already on the machine may launch a different ``python``). The kernel gets
``JSCRATCH_NOTEBOOK_SMALL=1`` (read by the notebook's parameter cell), ``JAX_PLATFORMS=cpu``, the
repository root on ``PYTHONPATH`` (so the checkout is what runs, installed or not) and test-only
XLA options that trade run time for compile time (the notebook's run time is almost all
compilation at this size; results are the same).
"""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path

import nbformat
import pytest

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOK = ROOT / "notebooks" / "quickstart.ipynb"
GENERATOR = ROOT / "notebooks" / "make_quickstart.py"
FAST_XLA = "--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true"


def _read():
    return nbformat.read(NOTEBOOK, as_version=4)


def test_committed_notebook_is_generated_and_clean():
    """The committed notebook is exactly what the generator writes, without outputs."""
    spec = importlib.util.spec_from_file_location("make_quickstart", GENERATOR)
    gen = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gen)
    assert NOTEBOOK.read_text(encoding="utf-8") == gen.render_text(gen.build()), (
        "notebooks/quickstart.ipynb differs from notebooks/make_quickstart.py: edit the generator "
        "and run `python notebooks/make_quickstart.py`")
    nb = _read()
    code = [c for c in nb.cells if c.cell_type == "code"]
    assert code and all(not c.outputs and c.execution_count is None for c in code)
    assert "parameters" in code[0].metadata.get("tags", [])
    assert "JSCRATCH_NOTEBOOK_SMALL" in code[0].source


def _kernel_manager(tmp_path, monkeypatch):
    from ipykernel.kernelspec import install
    from jupyter_client.manager import KernelManager

    install(prefix=str(tmp_path / "prefix"), kernel_name="python3")
    data = tmp_path / "prefix" / "share" / "jupyter"
    monkeypatch.setenv("JUPYTER_PATH", os.pathsep.join([str(data), os.environ.get("JUPYTER_PATH", "")]))
    km = KernelManager(kernel_name="python3")
    argv = km.kernel_spec.argv
    assert Path(argv[0]).resolve() == Path(sys.executable).resolve(), argv
    return km


def test_quickstart_notebook_runs(tmp_path, monkeypatch):
    """Execute every cell in a fresh kernel; any exception (including the notebook's own sanity
    checks) fails the test."""
    from nbclient import NotebookClient

    km = _kernel_manager(tmp_path, monkeypatch)
    env = dict(os.environ)
    env.update({
        "JSCRATCH_NOTEBOOK_SMALL": "1",
        "JAX_PLATFORMS": "cpu",
        "XLA_FLAGS": FAST_XLA,
        "PYTHONPATH": os.pathsep.join([str(ROOT)] + [p for p in [env.get("PYTHONPATH")] if p]),
        "MPLBACKEND": "module://matplotlib_inline.backend_inline",
        "TMPDIR": str(tmp_path),
    })
    nb = _read()
    client = NotebookClient(nb, km=km, timeout=600, allow_errors=False,
                            resources={"metadata": {"path": str(tmp_path)}})
    client.execute(env=env, cwd=str(tmp_path))

    code = [c for c in nb.cells if c.cell_type == "code"]
    assert all(c.execution_count is not None for c in code)
    outputs = [o for c in code for o in c.outputs]
    assert not [o for o in outputs if o.output_type == "error"]
    # Every plotting cell showed its figure(s): 1a, 1b, 1c, 2, loss + renders, discard, preview.
    images = [o for o in outputs if o.output_type == "display_data" and "image/png" in o.data]
    assert len(images) >= 8, len(images)
    text = "".join(o.get("text", "") for o in outputs if o.output_type == "stream")
    assert "all checks passed" in text
    assert "G21 G90" in text
