"""The map (the Atlas): keyframes, map points and frame records of all segments, and everything that writes them.

Owns:

- the store (:mod:`.store`: :class:`~.store.Map`): keyframes (frame, time, pose ``T_wc``, segment) and map points
  (host keyframe, host pixel, inverse depth, σ, observations, cached world positions);
- the map state (:mod:`.state`: :class:`~.state.MapState`), the map's **one writer**: every change to the store and
  the frame records (which frame was tracked from which keyframe, losses, relocalisations, segments, the map units
  bridges joined) is one of its methods, and its read accessors are what the loop and the back end read;
- the journal (:mod:`.journal`): each change as an event in frame order, which a replica replays bit for bit;
- the map units (:meth:`~.state.MapState.unit`): which segments share one frame and scale;
- a global BA's change and how it is written (:mod:`.refinement`: :class:`~.refinement.MapRefinement`,
  :func:`~.refinement.apply_refinement`);
- the finished map as a record (:mod:`.result`: :class:`~.result.VOResult`) and its assembly from the store
  (:mod:`.assemble`).

Sits on the ground floor only: tracking and local mapping (:mod:`mutualslam_cli.vo`), the back end and the
online loop import it, never the other way round.
"""
