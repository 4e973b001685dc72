"""The stages of a run: each reads a sequence's state, calls the domain packages and the back end
(:mod:`mutualslam_cli.backend`), and writes its own files and ``summary.json`` keys.
:mod:`mutualslam_cli.pipeline` calls them in order (entry points: each stage's ``run_stage``; the adaptation
stage drives the front end and the back end on one clock, :mod:`.adaptation`). May import the ground floor,
the domain, the back end and ``results``; never the report, the front doors or the CLI."""
