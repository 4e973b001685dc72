"""Downloading and unpacking published sequences safely (``mslam datasets download``).

Owns everything between a ``datasets.yaml`` entry's ``download:`` block and a checked sequence folder:
HTTP that resumes only the same file (:mod:`.fetch`), one process per file (:mod:`.lock`), mslam's own
files in ``<data root>/_downloads/`` (:mod:`.files`, :mod:`.checksums`), names from outside
(:mod:`.safe_names`), and unpacking within limits (:mod:`.limits`, :mod:`.archive_scan`, :mod:`.members`,
:mod:`.unpack`; a 7-Scenes scene zip: :mod:`.seven_scenes`).

May import: the ground floor (errors, atomic, geometry, types) and the top of :mod:`mutualslam_cli.datasets`
(the registry's entries, the check a new folder must pass). Never :mod:`..recordings` or :mod:`..synthetic`;
nothing else in :mod:`mutualslam_cli.datasets` imports it.

Entry points: :func:`.entry.download_sequence`, :func:`.entry.downloadable_specs`,
:func:`.entry.data_root_of`, :data:`.entry.DOWNLOAD_DIR`, :class:`.limits.UnpackLimits`.
"""
