"""Recording the data plane to rosbag2 (MCAP) bags: the part a component runs.

A bag is what ``ros2 bag record -s mcap`` makes on Jazzy: a directory holding
``metadata.yaml`` and ``<dirname>_<N>.mcap`` files. The data archiver records with these
modules inside its executor, and ``msctl record`` with the same; reading, recovering,
playing and pulling bags is the operator's side (:mod:`msctl.recorder`).

- :mod:`~components.recording.definitions`: message definitions (``ros2msg``) and QoS
  profiles, from msctl's own type registry.
- :mod:`~components.recording.metadata`: ``metadata.yaml`` (version 9): building, writing
  atomically, reading with errors that name the key at fault.
- :mod:`~components.recording.writer`: :class:`BagWriter`, the MCAP files of one bag, split
  by size or duration, chunks flushed often enough that a crash loses only the unflushed tail.
- :mod:`~components.recording.recorder`: the live recorder (graph discovery, subscriptions,
  a bounded queue, the writer thread); :mod:`~components.recording.keys`: what a data key
  and a sample's attachment say.
- :mod:`~components.recording.thinned`: the topics that reach this computer downsampled by
  a radio link (no loss counted in their sequence numbers' jumps).
"""
