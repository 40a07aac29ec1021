"""Every module of the package has a test file of its own, named after it.

The mapping (paths relative to the repository root):

- ``jscratch/<m>.py`` -> ``tests/test_<m>.py``;
- ``jscratch/design/<m>.py`` -> ``tests/test_design_<m>.py``;
- ``jscratch/bench/<m>.py`` -> ``tests/test_bench_<m>.py``, or ``tests/test_bench.py`` for the
  whole benchmark package (its modules run together through ``python -m jscratch.bench``);
- any other subpackage ``jscratch/<p>/<m>.py`` -> ``tests/test_<p>_<m>.py``.

Exceptions: ``__init__.py`` and ``__main__.py`` files (re-exports and entry points, tested
through the modules and command lines they expose). Nothing else is exempt.
"""

import pathlib

ROOT = pathlib.Path(__file__).resolve().parents[1]
EXEMPT = ("__init__.py", "__main__.py")
WHOLE_PACKAGE = {"bench": "test_bench.py"}  # subpackages one test file may cover


def untested_modules(root: pathlib.Path) -> list[str]:
    """Modules under ``root/jscratch`` without their test file in ``root/tests`` (module paths
    relative to ``root``), by the mapping of this file's docstring."""
    tests = root / "tests"
    missing = []
    for path in sorted((root / "jscratch").rglob("*.py")):
        if path.name in EXEMPT:
            continue
        parts = path.relative_to(root / "jscratch").with_suffix("").parts
        candidates = ["test_" + "_".join(parts) + ".py"]
        if len(parts) > 1 and parts[0] in WHOLE_PACKAGE:
            candidates.append(WHOLE_PACKAGE[parts[0]])
        if not any((tests / c).is_file() for c in candidates):
            missing.append(f"{path.relative_to(root)} (wants tests/{candidates[0]})")
    return missing


def test_every_module_has_its_test_file():
    missing = untested_modules(ROOT)
    assert not missing, "modules without a test file: " + "; ".join(missing)


def test_the_check_can_fail(tmp_path):
    for rel in ("jscratch/__init__.py", "jscratch/a.py", "jscratch/design/b.py",
                "jscratch/design/__main__.py", "jscratch/bench/c.py", "jscratch/other/d.py",
                "tests/test_a.py"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text("")
    assert untested_modules(tmp_path) == [
        "jscratch/bench/c.py (wants tests/test_bench_c.py)",
        "jscratch/design/b.py (wants tests/test_design_b.py)",
        "jscratch/other/d.py (wants tests/test_other_d.py)",
    ]
    (tmp_path / "tests/test_bench.py").write_text("")
    (tmp_path / "tests/test_design_b.py").write_text("")
    (tmp_path / "tests/test_other_d.py").write_text("")
    assert untested_modules(tmp_path) == []
