"""Running cores: the Core base, Interface declarations, the Executor, and the registry of
injections and overrides."""

from components.executor.core import Core, Outbox, RecordingOutbox
from components.executor.interface import Every, InterfaceSpec, Publish, Serve, Subscribe

__all__ = [
    "Core",
    "Every",
    "InterfaceSpec",
    "Outbox",
    "Publish",
    "RecordingOutbox",
    "Serve",
    "Subscribe",
]
