"""The ``feedmon`` command line, on top of everything: one module per sub-command
(``*_cmd.py``), each a thin adapter over the library packages (``monitor``, ``replay``,
``feedio``) that adds flag hints, tables and progress bars."""

from feedio import __version__

__all__ = ["__version__"]
