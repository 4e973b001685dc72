"""The front end (DESIGN §2): our SVO-style monocular VO — tracking and local mapping: KLT tracks, keyframes,
depth-filter seeds, the windowed BA (:mod:`.mapper`), map reuse (:mod:`.local_map`), relocalisation and new
segments. The map it builds is :mod:`mutualslam_cli.map`'s (:class:`~mutualslam_cli.map.state.MapState`, the
map's one writer, every change journaled); the front end holds one door to it (``FrontEnd.state_map``).
Also here: the oracles (``--vo gt``, ``gt-depth``) that stand in for it as diagnostics; its side of the mutual
loop: taking a bridge's or a global BA's change between two frames (:mod:`.feedback`), asking the adapted
network at its keyframes (:mod:`.depth_prior`), and a test fault (:mod:`.faults`); its stream of events frame by
frame into the map the adaptation loop reads (:mod:`.source`: :class:`~.source.FrontEndSource`) and the
per-sequence cache of its journal that lets every run of a grid start from the same front end
(:mod:`.journal_cache`).

May import the ground floor and the map only (and ``datasets`` for its sequences); the back end, the stages and
above import it, never the other way.

Entry points: :class:`~.frontend.FrontEnd` (``process(i, gray)`` per frame), :func:`~.frontend.run_vo`,
:class:`~.source.FrontEndSource`.
"""
