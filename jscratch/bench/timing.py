"""Timing and report helpers of the bench: ahead-of-time compilation timed apart
(`compile_once`), medians of `block_until_ready` runs (`median_time`, `time_compiled`), the
machine (`machine_info`, `machine_line`, `cpu_model`), Markdown tables (`md_table`) and
one-figure PNG plots (`plot`)."""

from __future__ import annotations

import datetime
import os
import platform
import statistics
import time
from pathlib import Path

import jax
import numpy as np


_COMPILED: dict = {}


def compile_once(fn, *args, options: dict | None = None):
    """``jax.jit(fn)`` compiled ahead of time for the shapes and dtypes of `args` (with XLA
    compiler `options`), cached per ``(fn, shapes, dtypes, options)`` for the process, so sections
    that run the same function on the same shapes share one compilation. Returns ``(compiled,
    compile_s)``, ``compile_s`` measured at the first compilation."""
    options = dict(options or {})
    key = (fn, tuple((np.shape(a), np.dtype(a.dtype).str) for a in args),
           tuple(sorted(options.items())))
    if key not in _COMPILED:
        t0 = time.perf_counter()
        compiled = jax.jit(fn).lower(*args).compile(options)
        _COMPILED[key] = (compiled, time.perf_counter() - t0)
    return _COMPILED[key]


def median_time(fn, reps: int = 5, min_time: float = 0.0):
    """`(median_s, out)`: ``fn()`` run once to warm up, then timed with `block_until_ready` at
    least `reps` times and, up to 50 runs, until `min_time` seconds have passed."""
    out = jax.block_until_ready(fn())
    times = []
    t_start = time.perf_counter()
    while len(times) < max(1, reps) or (time.perf_counter() - t_start < min_time
                                        and len(times) < 50):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def time_compiled(fn, *args, reps: int = 5, min_time: float = 0.2, options: dict | None = None):
    """Compile `fn` for `args` (`compile_once`, with XLA compiler `options`; timed apart) and
    return `(compile_s, median_run_s, out)` (`median_time` with `reps` and `min_time`)."""
    compiled, compile_s = compile_once(fn, *args, options=options)
    med, out = median_time(lambda: compiled(*args), reps, min_time)
    return compile_s, med, out


def cpu_model(cpuinfo: str | Path = "/proc/cpuinfo") -> str:
    """The CPU's model name (the first ``model name`` line of Linux's `cpuinfo`); elsewhere, or
    when that file has none, `platform.processor()` or the machine's architecture. Shared
    machines change CPUs between runs, and the same code rounds differently on each."""
    try:
        with open(cpuinfo, encoding="utf-8", errors="replace") as f:
            for line in f:
                key, sep, value = line.partition(":")
                if sep and key.strip() == "model name" and value.strip():
                    return " ".join(value.split())
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_info() -> dict:
    """Where and when a benchmark ran: the date and time (UTC), the CPU model, the 1-minute load
    average at the call, the platform and the versions."""
    dev = jax.devices()[0]
    now = datetime.datetime.now(datetime.timezone.utc)
    return {
        "date": now.date().isoformat(),
        "time_utc": now.strftime("%H:%M"),
        "cpu_model": cpu_model(),
        "load": round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None,
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "device": f"{dev.platform}:{getattr(dev, 'device_kind', '')}",
        "n_devices": len(jax.devices()),
        "jax": jax.__version__,
        "python": platform.python_version(),
    }


def machine_line(info: dict | None = None) -> str:
    """`machine_info` as one line for a report's header: date, time, CPU, cores, load,
    device and versions."""
    m = machine_info() if info is None else info
    load = "-" if m.get("load") is None else f"{m['load']:.2f}"
    return (f"{m['date']} {m['time_utc']} UTC; {m['cpu_model']}, {m['cpu_count']} CPUs, "
            f"load {load}; device {m['device']}; {m['platform']}; jax {m['jax']}, "
            f"python {m['python']}")


def md_table(rows: list[dict], cols: list[str]) -> str:
    """A Markdown table of `rows` (dicts) with columns `cols`; floats to 4 significant digits,
    None (not measured) as "-"."""

    def fmt(v):
        if v is None:
            return "-"
        if isinstance(v, float):
            if v == 0:
                return "0"
            if abs(v) >= 1e4 or abs(v) < 1e-3:
                return f"{v:.3g}"
            return f"{v:.4g}"
        return str(v)

    head = "| " + " | ".join(cols) + " |\n|" + "|".join("---" for _ in cols) + "|\n"
    return head + "".join("| " + " | ".join(fmt(r.get(c, "")) for c in cols) + " |\n" for r in rows)


def plot(path: Path, draw, xlabel: str, ylabel: str, title: str) -> None:
    """One PNG: `draw(ax)` plots, this labels it (and adds the legend when anything is labelled)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6, 4), dpi=110)  # no pyplot: leaves the user's backend alone
    ax = fig.subplots()
    draw(ax)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)


