"""The ``latentz`` command line (:mod:`~latentz.cli.main`), its option parsing, the file-level
steps behind it, resumable chunked runs, and the demo."""

from latentz.cli.main import main

__all__ = ["main"]
