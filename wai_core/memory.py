"""Memory a command will need, estimated before its work, against what this machine has now.

A command that would need more memory than is available would otherwise run for minutes and
end in the kernel's out-of-memory killer (or swap the machine to a halt). Each estimate counts
the arrays the code really holds at its peak, in bytes per pixel times pixels (the
renderer's: :mod:`mitsuba_wai.memory`; the video methods': :mod:`restoration.video.frames`),
and :func:`check_memory` refuses the command in one line, naming the option or file that sets
the size, when the estimate exceeds the memory available (``psutil``'s ``available``: free
memory plus the caches the kernel can reclaim).
"""

from __future__ import annotations

from wai_core.errors import WaiInputError

__all__ = ["GIB", "available_bytes", "check_memory"]

GIB = 2**30
"""Bytes in a GiB."""


def available_bytes() -> int:
    """The memory a new allocation can get now without swapping, bytes."""
    import psutil

    return int(psutil.virtual_memory().available)


def check_memory(need_bytes: float, what: str, work: str) -> None:
    """Refuse work whose estimated peak memory exceeds the memory available now.

    Parameters
    ----------
    need_bytes : float
        The work's estimated peak memory, bytes.
    what : str
        The option or file that sets the size, as the message names it (``--size 20000x20000``,
        ``big.toml: [camera_s] 20000 x 20000 px``).
    work : str
        What needs the memory, in words (``rendering``, ``registering 900 frames``).

    Raises
    ------
    WaiInputError
        ``WHAT: WORK needs about N GiB of memory; M GiB is available``.

    Examples
    --------
    >>> check_memory(1024, "--size 64x48", "rendering")
    >>> try:
    ...     check_memory(2**60, "--size 64x48", "rendering")
    ... except WaiInputError as exc:
    ...     print(str(exc).split(";")[0])
    --size 64x48: rendering needs about 1.07e+09 GiB of memory
    """
    available = available_bytes()
    if need_bytes > available:
        raise WaiInputError(f"{what}: {work} needs about {need_bytes / GIB:.3g} GiB of memory; "
                            f"{available / GIB:.3g} GiB is available")
