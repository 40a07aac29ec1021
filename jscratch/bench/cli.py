"""The driver of `python -m jscratch.bench`: `run_bench(sections, quick, out)` and `main`."""

from __future__ import annotations

import json
import math
import shlex
import sys
import time
from pathlib import Path

import jax

from jscratch.bench import kernel, rendering
from jscratch.bench.timing import machine_info, machine_line
from jscratch.errors import EXIT_STATUS_HELP, InputError, JscratchError, report
from jscratch.options import OneLineParser

DESCRIPTION = ("`python -m jscratch.bench`: run time against error, numerical stress, and the"
               " recorded results.")
SECTIONS = ("kernel", "stability", "render", "brute", "design")


def _json_safe(v):
    """`v` with numpy numbers and arrays as Python ones and non-finite floats as None (strict
    JSON)."""
    if hasattr(v, "tolist"):  # numpy scalars and arrays
        v = v.tolist()
    if isinstance(v, dict):
        return {k: _json_safe(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_json_safe(x) for x in v]
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def run_bench(sections=SECTIONS, quick: bool = False, out: str | Path = "bench_out",
              command: str | None = None) -> dict:
    """Run the chosen sections; write `bench.json`, `bench.md` and plots to `out`; return the
    results dict (`machine`, the `command` that ran it, one entry per section, each with a
    `markdown` table)."""
    unknown = set(sections) - set(SECTIONS)
    if unknown:
        raise InputError(f"unknown bench sections {sorted(unknown)}; choose from {SECTIONS}")
    sections = list(dict.fromkeys(sections))  # each section once, in the order given
    if not str(out).strip():
        raise InputError("--out is empty: give the output folder")
    out = Path(out)
    _check_out(out)
    # float64 rows and references need x64; float32 paths build float32 arrays explicitly.
    jax.config.update("jax_enable_x64", True)
    out.mkdir(parents=True, exist_ok=True)
    runners = {"kernel": kernel.bench_kernel, "stability": kernel.bench_stability,
               **rendering.RUNNERS}
    if command is None:
        command = f"run_bench({list(sections)!r}, quick={quick!r}, out={str(out)!r})"
    res = {"machine": machine_info(), "quick": quick, "command": command}
    for s in sections:
        if s not in runners:
            res[s] = {"skipped": "not available in this build", "markdown": "(skipped)"}
            continue
        t0 = time.perf_counter()
        res[s] = runners[s](quick, out)
        res[s]["section_wall_s"] = time.perf_counter() - t0
    md = [f"# jscratch bench ({'quick' if quick else 'full'})\n",
          f"Machine: {machine_line(res['machine'])}\n\nCommand: `{command}`\n"]
    for s in sections:
        md.append(f"\n## {s}\n\n{res[s].get('markdown', '')}\n")
        if "note" in res[s]:
            md.append(f"\n{res[s]['note']}\n")
    text = "".join(md)
    (out / "bench.md").write_text(text)
    (out / "bench.json").write_text(json.dumps(_json_safe(res), indent=1, allow_nan=False))
    return res


def _check_out(out: Path) -> None:
    """Refuse an output folder that cannot be one (`InputError`), before any work."""
    for p in (out, *out.parents):
        if p.exists():
            if not p.is_dir():
                raise InputError(f"--out {str(out)!r}: {str(p)!r} exists and is not a folder")
            break


def main(argv=None) -> int:
    """Command line entry point; returns the exit status (`jscratch.errors.EXIT_STATUS_HELP`: 0 ok,
    1 a file could not be written, 2 refused input, 130 interrupted)."""
    p = OneLineParser(prog="python -m jscratch.bench", description=DESCRIPTION,
                      epilog="The options are checked before any section runs; a refusal is one "
                             "line 'error: ...' on stderr. " + EXIT_STATUS_HELP)
    p.add_argument("--quick", action="store_true", help="small sizes (30-45 s on 2 CPU cores)")
    p.add_argument("--out", default="bench_out", help="output folder (default: bench_out)")
    p.add_argument("--sections", nargs="+", default=list(SECTIONS), choices=SECTIONS,
                   help="sections to run (default: all)")
    a = p.parse_args(argv)
    try:
        run_bench(a.sections, a.quick, a.out, command=shlex.join(
            ["python", "-m", "jscratch.bench", *(sys.argv[1:] if argv is None else argv)]))
    except KeyboardInterrupt:
        return 130
    except (JscratchError, OSError) as exc:
        return report(exc)
    print((Path(a.out) / "bench.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
