"""The back end: the map after the front end.

Owns what is done to the front end's map once it is made: a new segment joined to the map before it
(:mod:`.bridges`) or merged into it (:mod:`.merge`), a place seen again (:mod:`.loop_detector`) closed by a
Sim(3) pose graph (:mod:`.pose_graph`, :mod:`.loop_closer`), the adapted network's culling of map points
(:mod:`.culling`) and the global photometric BA (:mod:`.ba`), run on the map as it stands (:mod:`.refine`).

Entry points: :func:`.refine.refine_map` (culling + BA of the map now, the refinement handed back),
:class:`.refine.MapBA` (culling + BA of a snapshot, logged), :class:`.loop_closer.LoopCloser`,
:class:`.merge.SegmentMerger`, :func:`.bridges.plan_bridge`, :func:`.ba.global_ba.run_global_ba`.

What it hands back is a :class:`~mutualslam_cli.map.refinement.MapRefinement`, which stays with the front end
that takes it (the front end must not import the back end). May import the ground floor and the domain
(``vo``, ``adapt``, ``datasets``, ``config``, …); writes no file and no ``summary.json`` key (the stages do).
"""
