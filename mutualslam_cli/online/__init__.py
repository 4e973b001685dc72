"""Algorithm 1 on one clock: the engine the adaptation stage (:mod:`mutualslam_cli.stages.adaptation`) drives.

Owns the online loop over the front end's events (:mod:`.loop`: :class:`~.loop.OnlineLoop` — per keyframe the
bridge, the merge, Algorithm 1's tick with labels read from the map of now, the global BA it requests and the
loop closure), the labels it reads from the map (:mod:`.labels`), the realtime schedule that charges its work on
the sequence's clock and delays its map changes until that work ends (:mod:`.realtime`), the online scores of
each frame with the model of its time (:mod:`.scores`), and Table 4's bridged credit (:mod:`.credit`).

May import the ground floor, the domain (``vo``, ``adapt``, ``datasets``, ``metrics``) and the back end; writes no
file and no summary key (the stages do), so the stages, the front doors and the CLI import it, never the other way.

Entry points: :class:`~.loop.OnlineLoop` (``run_loop()``), :class:`~.realtime.RealtimeSchedule`,
:class:`~.scores.OnlineScorer`, :func:`~.credit.front_end_alone`, :func:`~.credit.credit_bridges`.
"""
