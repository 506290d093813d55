"""msctl: the field-operations toolkit for modular, multi-computer robots."""

__version__ = "0.1.0"
