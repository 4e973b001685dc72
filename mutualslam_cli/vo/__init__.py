"""The front end (DESIGN §2): our SVO-style monocular VO — tracking, keyframes, depth-filter seeds, the windowed
BA, map reuse, relocalisation and new segments — and the map as it makes it: :class:`~.map_state.MapState`
(the map and frame records, read by everyone else through its named accessors), kept as events
(:mod:`.journal`) so the map at any frame can be replayed; the oracles (``--vo gt``, ``gt-depth``) that stand in
for it as diagnostics; and its side of the mutual loop: taking a bridge's or a global BA's change between two
frames (:mod:`.feedback`: :class:`~.feedback.MapRefinement`), asking the adapted network at its keyframes
(:mod:`.depth_prior`), and a test fault (:mod:`.faults`); its stream of events frame by frame into the map the
adaptation loop reads (:mod:`.source`: :class:`~.source.FrontEndSource`) and the per-sequence cache of its
journal that lets every run of a grid start from the same front end (:mod:`.journal_cache`).

May import the ground floor only (and ``datasets`` for its sequences); the back end, the stages and above import
it, never the other way.

Entry points: :class:`~.frontend.FrontEnd` (``process(i, gray)`` per frame), :func:`~.frontend.run_vo`,
:class:`~.map_state.MapState`, :class:`~.result.VOResult` (a finished map), :class:`~.source.FrontEndSource`.
"""
