"""The back end: the map after the front end.

Owns what is done to the front end's map once it is made: a new segment joined to the map before it
(:mod:`.bridges`) or merged into it, a place seen again (:mod:`.loop_detector`) closed by a Sim(3) pose
graph (:mod:`.pose_graph`), the adapted network's culling of map points (:mod:`.culling`) and the global
photometric BA (:mod:`.ba`). What it hands back to the front end is a
:class:`~mutualslam_cli.vo.feedback.MapRefinement`, the record the front end takes changes in.

May import the ground floor and the domain (``vo``, ``adapt``, ``datasets``, ``config``, …); writes no file
and no ``summary.json`` key (the stages do). Imported by the stages, the front doors, the bench and the CLI.
"""
