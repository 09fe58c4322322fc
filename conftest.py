"""Collection for the doctests: which modules ``pytest --doctest-modules`` must not import.

The example scripts (``wai/examples``, also reached as ``examples/``) and ``__main__``
modules are programs, not libraries: they are run, and tested, as commands.
"""

collect_ignore = ["examples", "wai/examples"]
collect_ignore_glob = ["**/__main__.py"]
