"""The monocular front end (DSO/SVO-style VO) and its oracles.

Owns the map as the front end makes it: :class:`~.map_state.MapState` (the map and frame records, read by
everyone else through its named accessors), the journal of its changes (:mod:`.journal`), tracking, mapping,
relocalisation, and how it takes a change from the back end or the network (:mod:`.feedback`:
:class:`~.feedback.MapRefinement`) or a test fault (:mod:`.faults`). Entry point: :class:`~.frontend.FrontEnd`.

May import the ground floor only (and ``datasets`` for its sequences); the back end, the stages and above
import it, never the other way.
"""
