"""``msctl rehearse``: an assembly's real multi-computer deployment on one Linux machine.

One network namespace per computer of the resolved plan (robot computers and ground
stations), each with its own host name, ``MSCTL_HOME``, address, router and agent, linked to a
simulated access point through a userspace link emulator on TUN devices (no netem needed).
"""
