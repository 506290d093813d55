"""CANopen CiA 402 drives (H-line robots) on python-can, through the ``canopen`` library.

One job per module:

- :mod:`.cia402`: the drive profile's words, states, modes and error codes (data);
- :mod:`.units`: drive units to SI joint units and back, in one place;
- :mod:`.drive`: what the backend knows of one drive;
- :mod:`.pdo`: the PDO layouts, the command frames and the feedback they bring;
- :mod:`.supervision`: configuring drives over SDO, heartbeats, the enable sequence, the bus;
- :mod:`.diagnostics`: what a drive's state means to an operator;
- :mod:`.backend`: :class:`~.backend.CanopenBackend`, the lifecycle and the data path.
"""
