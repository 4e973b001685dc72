"""The ``mslam`` command line (typer + rich): the only package that imports either.

``app`` is the console script (``mslam = "mutualslam_cli.cli:app"``); importing the command
modules registers their commands on it. The command modules import the library inside each
command: ``mslam --help`` and a typo stay instant instead of importing torch first (seconds).
"""

from mutualslam_cli.cli import bench, book, data, grid, run  # noqa: F401 - register the commands
from mutualslam_cli.cli.common import app

__all__ = ["app"]
