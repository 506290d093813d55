"""Recording the data plane to rosbag2 (MCAP) bags, and reading, recovering and playing them.

A bag is what ``ros2 bag record -s mcap`` makes on Jazzy: a directory holding
``metadata.yaml`` and ``<dirname>_<N>.mcap`` files. Modules:

- :mod:`~msctl.recorder.definitions`: message definitions (``ros2msg``) and QoS profiles,
  from msctl's own type registry.
- :mod:`~msctl.recorder.metadata`: ``metadata.yaml`` (version 9): building, writing
  atomically, reading with errors that name the key at fault.
- :mod:`~msctl.recorder.writer`: :class:`BagWriter`, the MCAP files of one bag, split by size
  or duration, chunks flushed often enough that a crash loses only the unflushed tail.
- :mod:`~msctl.recorder.scan`: reading every MCAP file record by record, past truncation.
- :mod:`~msctl.recorder.recover`: rebuilding summaries and ``metadata.yaml`` after a crash.
- :mod:`~msctl.recorder.bag`: opening a bag for ``info`` and ``play``.
- :mod:`~msctl.recorder.recorder`: the live recorder (graph discovery, subscriptions, a
  bounded queue, the writer thread).
- :mod:`~msctl.recorder.player`: republishing a bag onto the data plane.
- :mod:`~msctl.recorder.shelf`: a computer's own bags (``MSCTL_HOME/bags``), listed and read
  by its agent for ``msctl bag pull``, nothing outside them.
- :mod:`~msctl.recorder.pull`: ``msctl bag pull HOST``: chunked copies over the fleet that
  resume after a cut and verify every file.
"""
