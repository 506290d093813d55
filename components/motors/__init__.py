"""Motor interfaces: backends that talk to real (or emulated) motors, chosen by name from data."""
