"""The depth network and its online adaptation (DESIGN §4–6): Monodepth2's depth (and pose) networks, their
released-weights loading and pre-training, the losses of Eq. 3–9, the keyframe buffer and replay, the EWC /
MAS / SI regularisers (Eq. 1–2, 19) and :class:`~mutualslam_cli.adapt.online.OnlineAdapter` — Algorithm 1's
tick and Algorithm 2's steps on one keyframe at a time — plus the CoMoDa-style baseline and the fast
inference paths (bf16, OpenVINO, int8).

A domain package: it imports the ground floor (``config``, ``errors``, ``types``, ``device``, …) and the
other domain packages (``datasets`` for the synthetic source domain), never ``stages`` or above.

Entry points: :class:`~mutualslam_cli.adapt.online.OnlineAdapter`, :func:`~mutualslam_cli.adapt.depthnet.predict_depth`,
:func:`~mutualslam_cli.adapt.inputs.load_network`, :mod:`~mutualslam_cli.adapt.schemes` (``get_scheme``).
"""
