"""The two ways work stops: bad input, and a frame the data cannot support.

:class:`WaiInputError` is the caller's (a missing or corrupt file, a wrong shape, NaN in an
image, an unknown option, impossible geometry in the configuration): the command line prints
it in one line with exit code 2. :class:`RestorationFailed` is a frame's own verdict (too few
features matched, samples that do not determine a surface, a degenerate reflection): the
restoration's methods catch it and return a result with status ``failed`` and its message.
"""

__all__ = ["RestorationFailed", "WaiInputError"]


class WaiInputError(ValueError):
    """Bad input: a missing or corrupt file, a wrong shape, NaNs, impossible geometry, too few
    features. The message names the problem in one line."""


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
