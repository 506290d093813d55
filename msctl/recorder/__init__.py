"""Reading, recovering, playing and pulling rosbag2 (MCAP) bags: the operator's side.

A bag is what ``ros2 bag record -s mcap`` makes on Jazzy: a directory holding
``metadata.yaml`` and ``<dirname>_<N>.mcap`` files. Modules:

- :mod:`components.recording`: what a component records with (message definitions,
  ``metadata.yaml``, the MCAP writer, the live recorder); shared with ``msctl record``.
- :mod:`~msctl.recorder.scan`: reading every MCAP file record by record, past truncation.
- :mod:`~msctl.recorder.recover`: rebuilding summaries and ``metadata.yaml`` after a crash.
- :mod:`~msctl.recorder.bag`: opening a bag for ``info`` and ``play``.
- :mod:`~msctl.recorder.player`: republishing a bag onto the data plane.
- :mod:`~msctl.recorder.shelf`: a computer's own bags (``MSCTL_HOME/bags``), listed and read
  by its agent for ``msctl bag pull``, nothing outside them.
- :mod:`~msctl.recorder.pull`: ``msctl bag pull HOST``: chunked copies over the fleet that
  resume after a cut and verify every file.
"""
