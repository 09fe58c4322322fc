"""The two ways a restoration stops: a frame the data cannot support, and bad input.

:class:`RestorationFailed` is the frame's own verdict (too few features matched, samples that
do not determine a surface, a degenerate reflection): the methods catch it and return a result
with status ``failed`` and its message. :class:`~wai_core.errors.WaiInputError` is the caller's
(a wrong shape, NaN in an image, an unknown option, impossible geometry in the configuration):
it leaves the method, and the command line prints it in one line with exit code 2.
"""

from __future__ import annotations

__all__ = ["RestorationFailed"]


class RestorationFailed(Exception):
    """A frame that the data cannot support: the input is well formed, but it holds too little
    (or too degenerate) evidence to build a surface. The message names why in one line.

    Examples
    --------
    >>> from restoration import RestorationFailed
    >>> str(RestorationFailed("too few features matched: 3 (need 16)"))
    'too few features matched: 3 (need 16)'
    >>> issubclass(RestorationFailed, ValueError)
    False
    """
