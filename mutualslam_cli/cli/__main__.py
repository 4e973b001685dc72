"""``python -m mutualslam_cli.cli``: the ``mslam`` command line."""

from mutualslam_cli.cli import app

app()
