"""The stages of a run: each reads a sequence's state, calls the domain packages, and writes its
own files and ``summary.json`` keys. :mod:`mutualslam_cli.pipeline` calls them in order."""
