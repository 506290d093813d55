"""The shipped operators' logic as pure cores: no I/O, no clocks, time passed in.

Each operator script (``operators/<name>.py``) only wires its core to the robot: it feeds it
what arrives and the time, and carries out what it answers (a halt, a correction, a status).
"""
