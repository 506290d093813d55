"""The link emulator's spec: which computers it links, where it answers, how it is seeded.

The spec (:class:`Spec`) is JSON::

    {
      "control": "/run/msr/ctl.sock",          # unix socket of the control protocol
      "ready": "/run/msr/ready",               # written (atomically) once every device is up
      "seed": 1,                                # seeds every link (a run can be replayed)
      "profiles_file": null,                    # a user profiles file, null: $MSCTL_LINK_PROFILES
      "subnet": "10.77.0.0/24",
      "hosts": [
        {"name": "ground1", "netns": "msr-ab12-ground1", "address": "10.77.0.11",
         "profile": "wifi", "device": "rh0"}
      ]
    }
"""

from __future__ import annotations

import ipaddress
import json
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from msctl.errors import InputError, NotFoundError, did_you_mean

_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
_SPEC_KEYS = ("control", "ready", "seed", "profiles_file", "subnet", "hosts")
_HOST_KEYS = ("name", "netns", "address", "profile", "device")


@dataclass(frozen=True)
class HostSpec:
    """One computer of the rehearsal, as the emulator sees it.

    Attributes:
        name: The computer's name (``ground1``), as the control protocol names it.
        netns: Its network namespace, under ``/run/netns``.
        address: Its IPv4 address on the rehearsal's subnet.
        profile: The link profile it starts with.
        device: The TUN device's name in its namespace (15 characters at most).
    """

    name: str
    netns: str
    address: str
    profile: str
    device: str = "rh0"


@dataclass(frozen=True)
class Spec:
    """What the emulator serves. See the module's docstring for the JSON form.

    Attributes:
        control: The control socket's path.
        ready: The file written once every device is up.
        hosts: The computers, in order.
        seed: Seeds every link.
        profiles_file: A user profiles file over the built-ins; None: ``$MSCTL_LINK_PROFILES``.
        subnet: The rehearsal's IPv4 subnet; every address is in it.
    """

    control: Path
    ready: Path
    hosts: tuple[HostSpec, ...]
    seed: int = 0
    profiles_file: Path | None = None
    subnet: str = "10.77.0.0/24"

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], source: str = "spec") -> Spec:
        """A spec from its JSON form, checked.

        Args:
            data: The parsed JSON.
            source: Names the spec in errors (its file).

        Raises:
            InputError: Naming the source and the field at fault.
        """
        if not isinstance(data, Mapping):
            raise InputError(f"{source}: a spec is a JSON object, got {data!r}")
        _known_keys(data, _SPEC_KEYS, source)
        for key in ("control", "ready", "hosts"):
            if key not in data:
                raise InputError(f"{source}: {key} is missing")
        control, ready = (_text(data, key, source) for key in ("control", "ready"))
        seed = data.get("seed", 0)
        if isinstance(seed, bool) or not isinstance(seed, int):
            raise InputError(f"{source}: seed must be a whole number, got {seed!r}")
        profiles_file = data.get("profiles_file")
        if profiles_file is not None:
            profiles_file = Path(_text(data, "profiles_file", source))
        subnet_text = data.get("subnet", "10.77.0.0/24")
        try:
            subnet = ipaddress.IPv4Network(subnet_text)
        except (ValueError, TypeError) as error:
            raise InputError(
                f"{source}: subnet must be an IPv4 network like 10.77.0.0/24, got {subnet_text!r}"
            ) from error
        hosts_data = data["hosts"]
        if not isinstance(hosts_data, list) or not hosts_data:
            raise InputError(f"{source}: hosts must be a non-empty list, got {hosts_data!r}")
        hosts = tuple(
            _host(item, f"{source}: hosts[{index}]", subnet)
            for index, item in enumerate(hosts_data)
        )
        for key in ("name", "address"):
            seen: dict[str, str] = {}
            for host in hosts:
                value = getattr(host, key)
                if value in seen:
                    raise InputError(
                        f"{source}: hosts {seen[value]!r} and {host.name!r} have the same "
                        f"{key} {value!r}"
                    )
                seen[value] = host.name
        pairs = [(h.netns, h.device) for h in hosts]
        if len(set(pairs)) != len(pairs):
            raise InputError(f"{source}: two hosts have the same device in the same netns")
        return cls(
            control=Path(control),
            ready=Path(ready),
            hosts=hosts,
            seed=seed,
            profiles_file=profiles_file,
            subnet=str(subnet),
        )

    @classmethod
    def load(cls, path: Path) -> Spec:
        """A spec from a JSON file.

        Raises:
            NotFoundError: No such file.
            InputError: Not JSON, or a field at fault.
        """
        try:
            data = json.loads(Path(path).read_text())
        except FileNotFoundError:
            raise NotFoundError(f"{path}: no such emulator spec") from None
        except ValueError as error:
            raise InputError(f"{path}: not valid JSON: {error}") from error
        return cls.from_dict(data, str(path))

    def to_dict(self) -> dict[str, Any]:
        """The JSON form (what :meth:`from_dict` reads)."""
        return {
            "control": str(self.control),
            "ready": str(self.ready),
            "seed": self.seed,
            "profiles_file": None if self.profiles_file is None else str(self.profiles_file),
            "subnet": self.subnet,
            "hosts": [
                {
                    "name": h.name,
                    "netns": h.netns,
                    "address": h.address,
                    "profile": h.profile,
                    "device": h.device,
                }
                for h in self.hosts
            ],
        }


def _known_keys(data: Mapping[str, Any], known: Sequence[str], where: str) -> None:
    for key in data:
        if key not in known:
            near = did_you_mean(str(key), known)
            raise InputError(
                f"{where}: unknown field {key!r}"
                + (f" ({near})" if near else "")
                + f"; fields: {', '.join(known)}"
            )


def _text(data: Mapping[str, Any], key: str, where: str) -> str:
    value = data.get(key)
    if not isinstance(value, str) or not value:
        raise InputError(f"{where}: {key} must be a non-empty string, got {value!r}")
    return value


def _host(item: object, where: str, subnet: ipaddress.IPv4Network) -> HostSpec:
    if not isinstance(item, Mapping):
        raise InputError(f"{where} must be an object, got {item!r}")
    _known_keys(item, _HOST_KEYS, where)
    name, netns, address, profile = (
        _text(item, key, where) for key in ("name", "netns", "address", "profile")
    )
    device = _text(item, "device", where) if "device" in item else "rh0"
    for key, value in (("name", name), ("netns", netns), ("device", device)):
        if not _NAME.match(value):
            raise InputError(
                f"{where}: {key} must be letters, digits, '_', '.' or '-', got {value!r}"
            )
    if len(device) > 15:
        raise InputError(f"{where}: device must be at most 15 characters, got {device!r}")
    try:
        parsed = ipaddress.IPv4Address(address)
    except ValueError:
        raise InputError(f"{where}: address must be an IPv4 address, got {address!r}") from None
    if parsed not in subnet or parsed in (subnet.network_address, subnet.broadcast_address):
        raise InputError(f"{where}: address must be a host address of {subnet}, got {address!r}")
    return HostSpec(name=name, netns=netns, address=address, profile=profile, device=device)
