"""Timing and the machine: what every benchmark reports beside its figures.

Absolute times differ by 2-2.5x between the project's machines, so every benchmark also times a
fixed reference workload in the same run (:func:`reference_workload`) and reports its figures
against it as well.
"""

from __future__ import annotations

import os
import platform
import resource
import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np

__all__ = [
    "check_runs",
    "machine",
    "peak_rss_mib",
    "print_stage_table",
    "reference_workload",
    "runtime",
    "summarize",
    "time_runs",
]

_THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "DRJIT_NUM_THREADS")
REFERENCE_SIZE = 1000
"""Side of the square float64 matrices of the reference workload."""


def _cpu_model() -> str | None:
    """``model name`` of the first CPU in /proc/cpuinfo (Linux), else None."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return None


def _blas() -> str | None:
    """Name and version of the BLAS NumPy was built against."""
    try:
        blas = np.show_config(mode="dicts")["Build Dependencies"]["blas"]
        return f"{blas['name']} {blas.get('version', '')}".strip()
    except Exception:  # the layout of numpy's build record is not an API
        return None


def machine() -> dict[str, Any]:
    """What the numbers were measured on: CPU, core count and library versions."""
    return {
        "cpu": platform.processor() or platform.machine(),
        "cpu_model": _cpu_model(),
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "blas": _blas(),
    }


def runtime() -> dict[str, Any]:
    """Variant and thread counts of the libraries this process has loaded.

    Only modules already imported are asked (importing Mitsuba just to report on it would pick
    a variant): a restoration-only benchmark has no variant, since it never runs Dr.Jit.
    """
    out: dict[str, Any] = {"variant": None, "drjit_threads": None}
    if "mitsuba" in sys.modules:
        mi = sys.modules["mitsuba"]
        out["mitsuba"] = mi.__version__
        out["variant"] = mi.variant()
    if "drjit" in sys.modules:
        dr = sys.modules["drjit"]
        out["drjit"] = dr.__version__
        if hasattr(dr, "thread_count"):
            out["drjit_threads"] = int(dr.thread_count())
    if "cv2" in sys.modules:
        out["opencv_threads"] = int(sys.modules["cv2"].getNumThreads())
    if "numba" in sys.modules:  # the restoration's threads (wai_core.parallel.run_chunks)
        out["numba_threads"] = int(sys.modules["numba"].get_num_threads())
    # BLAS pools are sized by these when set.
    out["thread_env"] = {k: os.environ[k] for k in _THREAD_ENV if k in os.environ}
    return out


def peak_rss_mib() -> float:
    """Peak resident memory of this process so far, MiB (``ru_maxrss`` is KiB on Linux)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def summarize(samples_s: list[float]) -> dict[str, float]:
    """Median, min, max, quartiles and interquartile range of run times, milliseconds."""
    ms = np.asarray(samples_s) * 1e3
    q1, q3 = np.percentile(ms, [25, 75])
    return {
        "median_ms": float(np.median(ms)),
        "min_ms": float(ms.min()),
        "max_ms": float(ms.max()),
        "iqr_ms": float(q3 - q1),
        "q1_ms": float(q1),
        "q3_ms": float(q3),
        "runs": int(ms.size),
    }


def check_runs(runs: int) -> None:
    """Refuse fewer than one measured run (``--runs``), before any work.

    Raises
    ------
    WaiInputError
        ``runs`` below 1.
    """
    if runs < 1:
        from wai_core.errors import WaiInputError

        raise WaiInputError(f"--runs must be at least 1, got {runs}")


def time_runs(fn: Callable[[int], Any], runs: int) -> tuple[float, list[float]]:
    """One warm-up call (index -1), then ``runs`` timed calls; ``fn`` receives the run index."""
    t0 = time.perf_counter()
    fn(-1)
    warm = time.perf_counter() - t0
    samples = []
    for i in range(runs):
        t0 = time.perf_counter()
        fn(i)
        samples.append(time.perf_counter() - t0)
    return warm, samples


def reference_workload(runs: int = 5) -> dict[str, Any]:
    """Time a fixed workload on this machine, now: the median of ``runs`` products of two
    1000 x 1000 float64 matrices (seeded), plus a single-threaded NumPy loop-free sum.

    Figures divided by ``median_ms`` compare across machines and loads far better than
    milliseconds do (BLAS and memory bandwidth dominate both the workload and the
    restoration's dense steps).
    """
    rng = np.random.default_rng(0)
    a = rng.standard_normal((REFERENCE_SIZE, REFERENCE_SIZE))
    b = rng.standard_normal((REFERENCE_SIZE, REFERENCE_SIZE))
    _, samples = time_runs(lambda _i: a @ b, runs)
    return {"workload": f"{REFERENCE_SIZE}x{REFERENCE_SIZE} float64 matmul", **summarize(samples)}


def print_stage_table(
    stages: dict[str, dict[str, Any]], derived: list[str], notes: dict[str, str], runs: int
) -> None:
    """One line per stage: median, min, max and IQR in ms, and the median's share of the
    end-to-end median (when there is one); derived stages marked and explained. Parts (dotted
    names) and derived stages overlap the stages they belong to, so the shares do not add
    up to 100 %."""
    total = stages.get("end_to_end", {}).get("median_ms")
    print(f"{'stage':28s} {'median':>9s} {'min':>9s} {'max':>9s} {'IQR':>8s} {'share':>6s}"
          f"  (ms, {runs} runs)")
    for name, s in stages.items():
        mark = " *" if name in derived else ""
        label = f"  {name}" if "." in name else name  # parts under their stage
        share = f"{100.0 * s['median_ms'] / total:5.0f}%" if total else ""
        print(
            f"{label:28s} {s['median_ms']:9.2f} {s['min_ms']:9.2f} {s['max_ms']:9.2f} "
            f"{s['iqr_ms']:8.2f} {share:>6s}{mark}"
        )
    for name in derived:
        print(f"  * {name} = {notes.get(name, '')}")
