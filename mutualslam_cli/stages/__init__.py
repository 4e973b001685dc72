"""The stages of a run: each reads a sequence's state, calls the domain packages, the back end
(:mod:`mutualslam_cli.backend`) and the online loop (:mod:`mutualslam_cli.online`), and writes its own files and
``summary.json`` keys. :mod:`mutualslam_cli.pipeline` calls them in order (entry points: each stage's
``run_stage``; the adaptation stage, :mod:`.adaptation`, drives Algorithm 1's loop over the front end and the
back end on one clock). Nothing here is not a stage but what stages share: the run's context (:mod:`.context`),
the summary keys they write (:mod:`.adaptation_summary`, :mod:`.ate_keys`) and the run record (:mod:`.run_record`).
May import the ground floor, the domain, the back end, ``online`` and ``results``; never the report, the front
doors or the CLI."""
