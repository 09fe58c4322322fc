"""Exceptions that the command line turns into a one-line message and exit code 2."""


class WaiInputError(ValueError):
    """Bad input: a missing or corrupt file, a wrong shape, NaNs, impossible geometry, too few
    features. The message names the problem in one line."""
