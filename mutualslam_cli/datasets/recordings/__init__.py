"""The user's own recordings, converted once into a TUM-layout folder that runs like any sequence.

Owns: ROS 1 / ROS 2 bags (:mod:`.rosbag`), videos and plain image folders (:mod:`.video`), camera files
for recordings without ``CameraInfo`` (:mod:`.camera_file`), the options and the TUM-layout writer every
converter writes through (:mod:`.conversion`), and the conversion cache that picks a converter
(:mod:`.recording`).

May import: the ground floor (errors, atomic, geometry, types) and the file formats at the top of
:mod:`mutualslam_cli.datasets` (``associate``, ``tum``, ``image_files``). Never :mod:`..download`,
:mod:`..synthetic` or the registry: the registry imports this package (``load_sequence`` of a recording).

Entry points: :func:`.recording.open_recording`, :func:`.recording.recording_kind`,
:class:`.conversion.RecordingOptions`, :func:`.camera_file.read_camera_file`.
"""
