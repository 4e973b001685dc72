"""Rendered rooms: synthetic RGB-D sequences with exact z-depth and poses (DESIGN §3 "Synthetic").

Owns the scenes' layouts and camera paths (:mod:`.scenes`), their textures (:mod:`.textures`), the ray
caster (:mod:`.raycast`), and the sequences rendered from them and written in the TUM layout
(:mod:`.sequences`).

May import: the ground floor (errors, types) and the TUM trajectory writer
(:mod:`mutualslam_cli.datasets.associate`). Never :mod:`..download`, :mod:`..recordings` or the registry
(a written sequence is read back like any folder).

Entry points (from :mod:`.sequences`, re-exported here so ``from mutualslam_cli.datasets import
synthetic`` reads ``synthetic.iter_render``): :data:`SCENES`, :class:`SyntheticSequence`,
:func:`render_sequence`, :func:`iter_render`, :func:`write_tum`, :func:`bench_render`,
:func:`synthetic_intrinsics`.
"""

from mutualslam_cli.datasets.synthetic.sequences import (
    SCENES,
    SyntheticSequence,
    bench_render,
    iter_render,
    render_sequence,
    synthetic_intrinsics,
    write_tum,
)

__all__ = ["SCENES", "SyntheticSequence", "bench_render", "iter_render", "render_sequence",
           "synthetic_intrinsics", "write_tum"]
