"""Link classes as data: what crosses each computer's link, and how soon it is dead.

The template's ``[network]`` table is checked by :mod:`msctl.net.radio` and kept in the
lock as :meth:`Network.as_dict`'s form; the runtime reads it back from there
(:meth:`Network.from_dict`) to know which topics reach a computer downsampled
(:func:`thinned_topics`): a recorder counts no loss in their sequence numbers' jumps.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

#: What the ground's views need of each module's high-rate telemetry. ``msctl health``
#: samples joint positions at 10 Hz and its topic rates come from the module's own health
#: monitor (on the robot, at the full rate); ``msctl teleop`` redraws at 10 Hz from
#: ``joint_read``. The rest (raw joint commands, poses, tf) is for a recorder or a view.
RADIO_DOWNSAMPLE_HZ: dict[str, float] = {
    "joint_states": 10.0,
    "joint_read": 10.0,
    "joint_commands": 10.0,
    "tip_pose": 10.0,
    "tf": 10.0,
}


@dataclass(frozen=True)
class LinkClass:
    """How links of one class are run.

    Attributes:
        name: ``radio`` or ``wired``.
        lease_s: Seconds of silence after which a link is dead (announced to the other
            end, which closes the link then; keep-alives every quarter of it).
        protocol: ``tls`` or ``quic``.
        max_message_bytes: Publications larger than this are not sent on the link
            (0: no limit).
        downsample_hz: Topic -> most samples a second sent on the link. A name without a
            leading slash is that topic of every module of the computer
            (``joint_states``); one with it is exactly that topic.
    """

    name: str
    lease_s: float
    protocol: str = "tls"
    max_message_bytes: int = 0
    downsample_hz: Mapping[str, float] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        """The class as plain data (the lock file's form)."""
        return {
            "lease_s": self.lease_s,
            "protocol": self.protocol,
            "max_message_bytes": self.max_message_bytes,
            "downsample_hz": dict(self.downsample_hz),
        }


#: Each class when the template says nothing of it.
DEFAULTS: dict[str, LinkClass] = {
    # Field Wi-Fi: a dead link noticed in 5 s.
    "radio": LinkClass("radio", 5.0, "tls", 65536, dict(RADIO_DOWNSAMPLE_HZ)),
    "wired": LinkClass("wired", 2.0, "tls", 0, {}),
    # A link as slow as Earth to the Moon (2.56 s round trip): TCP's retransmission of one
    # lost packet holds the stream back a timeout (over a round trip) plus a round trip, and
    # another loss in it doubles the timeout; with radio's 5 s lease such a link was closed
    # and opened again every 20-60 s (measured, 0.5 % loss). Both ends of such a link name it:
    # a lease is what a router tells the other end to wait for it.
    "deep-space": LinkClass("deep-space", 30.0, "tls", 65536, dict(RADIO_DOWNSAMPLE_HZ)),
}


@dataclass(frozen=True)
class Network:
    """Every link class of an assembly, and which class each computer's link is.

    Attributes:
        classes: Class name -> its settings (every name of :data:`CLASSES`).
        links: Computer -> its link's class, for those not ``radio``.
    """

    classes: Mapping[str, LinkClass] = field(default_factory=lambda: dict(DEFAULTS))
    links: Mapping[str, str] = field(default_factory=dict)

    def link_class(self, host: str) -> LinkClass:
        """The class of ``host``'s link."""
        return self.classes[self.links.get(host, "radio")]

    def as_dict(self) -> dict[str, Any]:
        """Plain data (the lock file's ``network``)."""
        return {
            "classes": {name: c.as_dict() for name, c in self.classes.items()},
            "links": dict(self.links),
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None) -> Network:
        """From :meth:`as_dict`'s form; an empty or missing one (a lock written before link
        classes) is the defaults."""
        if not data:
            return cls()
        classes = dict(DEFAULTS)
        for name, values in (data.get("classes") or {}).items():
            classes[name] = LinkClass(
                name,
                float(values["lease_s"]),
                str(values["protocol"]),
                int(values["max_message_bytes"]),
                {str(k): float(v) for k, v in values["downsample_hz"].items()},
            )
        return cls(classes, {str(k): str(v) for k, v in (data.get("links") or {}).items()})


def thinned_topics(
    network: Network, module_hosts: Mapping[str, str], here: str
) -> dict[str, float]:
    """Topic -> rate of each topic that reaches ``here`` downsampled on its way: published by
    a module on another computer, whose link class thins it on its radio links.

    A recorder on ``here`` sees such a topic's sequence numbers jump by design: those jumps
    are no losses. Only a fleet whose links are encrypted (the generated router configs)
    filters anything; the caller says whether it is one.

    Args:
        network: The assembly's link classes.
        module_hosts: Module slot -> its computer.
        here: This computer.
    """
    thinned: dict[str, float] = {}
    for module, host in module_hosts.items():
        if host == here:
            continue
        for topic, rate in network.link_class(host).downsample_hz.items():
            if not topic.startswith("/"):
                thinned[f"/{module}/{topic}"] = rate
            elif topic.split("/")[1] == module:
                thinned[topic] = rate
    return thinned
