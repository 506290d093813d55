"""Emulated motor hardware (servo chains, CAN drives) for tests, demos and off-robot runs."""
