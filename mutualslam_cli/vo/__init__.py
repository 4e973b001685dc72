"""The front end (DESIGN §2): our SVO-style monocular VO — tracking, keyframes, depth-filter seeds, the windowed
BA, map reuse, relocalisation and new segments — and the map it keeps, as events (:mod:`.journal`) that
:class:`~mutualslam_cli.vo.map_state.MapState` applies, so the map at any frame can be replayed; the oracles
(``--vo gt``, ``gt-depth``) that stand in for it as diagnostics; and the front end's side of the mutual loop:
taking a bridge's or a global BA's change between two frames (:mod:`.feedback`) and asking the adapted
network at its keyframes (:mod:`.depth_prior`).

A domain package: it imports the ground floor and ``datasets`` (frames), never ``stages`` or above.

Entry points: :class:`~mutualslam_cli.vo.frontend.FrontEnd` (``process(i, gray)`` per frame),
:func:`~mutualslam_cli.vo.frontend.run_vo`, :class:`~mutualslam_cli.vo.map_state.MapState`,
:class:`~mutualslam_cli.vo.result.VOResult` (a finished map).
"""
