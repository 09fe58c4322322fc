"""Choose the Mitsuba variant once, in one place, before Dr.Jit starts.

Dr.Jit 1.5 emits ``llvm.minimum``/``llvm.maximum``, which Debian 12's libLLVM 15 cannot lower: the
process aborts inside LLVM (no exception to catch). So the LLVM backend is only used with a libLLVM
of version 16 or newer, pinned through ``DRJIT_LIBLLVM_PATH`` before ``drjit`` is imported. Without
one (and no GPU), no variant can render: ``auto`` says so in one line
(:class:`~wai_core.errors.WaiInputError`). Scalar variants cannot run these renders (meshes,
textures and the particle tracer need JIT arrays) and are refused, as are unknown names.
"""

from __future__ import annotations

import ctypes.util
import glob
import os
import re
import sys
from types import ModuleType

from wai_core.errors import WaiInputError

_MIN_LLVM = 16
_LLVM_GLOBS = (
    "/usr/lib/x86_64-linux-gnu/libLLVM*.so*",
    "/usr/lib/aarch64-linux-gnu/libLLVM*.so*",
    "/usr/lib/llvm-*/lib/libLLVM*.so*",
    "/usr/local/lib/libLLVM*.so*",
)
_chosen: str | None = None


def _llvm_major(path: str) -> int | None:
    """Major version from a libLLVM file name (``libLLVM-19.so``, ``libLLVM.so.19.1``)."""
    m = re.search(r"libLLVM[-.]?(?:so\.)?(\d+)", os.path.basename(path))
    return int(m.group(1)) if m else None


def find_libllvm() -> str | None:
    """Path of the newest libLLVM with major version >= 16, or None.

    An explicit ``DRJIT_LIBLLVM_PATH`` wins when it names an existing file of a working version.
    """
    env = os.environ.get("DRJIT_LIBLLVM_PATH")
    if env and os.path.isfile(env) and (_llvm_major(env) or _MIN_LLVM) >= _MIN_LLVM:
        return env
    found = []
    for pattern in _LLVM_GLOBS:
        for path in glob.glob(pattern):
            major = _llvm_major(path)
            if major is not None and major >= _MIN_LLVM and os.path.isfile(path):
                found.append((major, path))
    return max(found)[1] if found else None


def _cuda_driver_present() -> bool:
    return ctypes.util.find_library("cuda") is not None or os.path.exists("/dev/nvidiactl")


SUPPORTED = ("cuda_ad_rgb", "llvm_ad_rgb")
"""Variants the renders run on: RGB, vectorised (the meshes, textures and the particle tracer
need JIT arrays; scalar and spectral variants are refused)."""


def _cuda_works() -> bool:
    """A CUDA device that Dr.Jit can initialise (a driver alone is not enough)."""
    if not _cuda_driver_present():
        return False
    try:
        import drjit as dr

        return bool(dr.has_backend(dr.JitBackend.CUDA))
    except (ImportError, RuntimeError, AttributeError):
        return False


def select_variant(requested: str = "auto") -> str:
    """Set the Mitsuba variant for this process and return its name.

    Parameters
    ----------
    requested : str
        ``auto`` picks ``cuda_ad_rgb`` when a GPU works, else ``llvm_ad_rgb`` when a working
        libLLVM is installed. Otherwise one of :data:`SUPPORTED`, set as given.

    Raises
    ------
    WaiInputError
        In one line starting with the variant's name: not a supported variant, or not usable
        on this machine (no GPU for ``cuda_ad_rgb``, no libLLVM >= 16 for ``llvm_ad_rgb``);
        for ``auto``, when neither works.

    Notes
    -----
    A process can hold one variant; asking again for the same one is a no-op, asking for another
    raises ``RuntimeError`` (a programming error, not bad input).
    """
    global _chosen
    if _chosen is not None and requested in ("auto", _chosen):
        return _chosen  # set already: no library search (the tracers ask on every call)
    if requested != "auto" and requested not in SUPPORTED:
        raise WaiInputError(
            f"{requested}: not a variant these renders run on (use auto, {', '.join(SUPPORTED)})"
        )
    llvm = find_libllvm()
    if requested.startswith("llvm") and not llvm:
        raise WaiInputError(
            f"{requested}: needs libLLVM >= {_MIN_LLVM} (apt-get install libllvm19)"
        )
    if llvm and "drjit" not in sys.modules:
        os.environ["DRJIT_LIBLLVM_PATH"] = llvm
    if requested.startswith("cuda") and not _cuda_works():
        raise WaiInputError(f"{requested}: needs a CUDA GPU, and none works on this machine")
    if _chosen is not None:
        if requested not in ("auto", _chosen):
            raise RuntimeError(f"variant already set to {_chosen}; cannot switch to {requested}")
        return _chosen
    import mitsuba as mi

    if requested == "auto":
        candidates = (["cuda_ad_rgb"] if _cuda_works() else []) + (["llvm_ad_rgb"] if llvm else [])
        if not candidates:
            raise WaiInputError(
                f"auto: no usable Mitsuba variant (no GPU, and no libLLVM >= {_MIN_LLVM}: "
                "apt-get install libllvm19)"
            )
    else:
        candidates = [requested]
    errors = []
    for name in candidates:
        try:
            mi.set_variant(name)
            _chosen = name
            return name
        except (ImportError, RuntimeError, AttributeError) as exc:
            errors.append(f"{name}: {exc}")
    raise WaiInputError(f"{requested}: not usable here ({'; '.join(errors)})")


def mitsuba(requested: str = "auto") -> ModuleType:
    """The ``mitsuba`` module with a variant set (``select_variant`` on first use)."""
    select_variant(requested)
    import mitsuba as mi

    return mi


def jit_arrays(requested: str = "auto") -> ModuleType:
    """The Dr.Jit array module of the renders' variant, the variant set on first use:
    ``drjit.cuda`` on ``cuda_ad_rgb`` (the GPU), ``drjit.llvm`` on ``llvm_ad_rgb`` (every
    core)."""
    if select_variant(requested).startswith("cuda"):
        import drjit.cuda as jit
    else:
        import drjit.llvm as jit
    return jit
