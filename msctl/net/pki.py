"""The fleet's certificate authority and its identities, kept under ``$MSCTL_HOME/net``.

One CA per fleet signs one identity (key and certificate) per robot computer, ground station
and operator. The certificate's common name is what Zenoh's access control matches
(``cert_common_names``): the host name for a computer, ``operator:<name>`` for an operator.

Keys and certificates are made with the ``openssl`` command line rather than the
``cryptography`` package: every robot computer already has openssl, the venv does not carry
``cryptography``, and a dependency with a compiled core is one more thing to fail offline.

Layout::

    net/ca/ca.pem, ca.key                       the fleet CA (key 0600)
    net/identities/<file name>/cert.pem, key.pem  one directory per identity (key 0600)
    net/revoked.json                            common names revoked, with when
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import tempfile
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from components.assembly import state_dir

#: Prefix of an operator's common name (``operator:alice``).
OPERATOR_PREFIX = "operator:"
CA_NAME = "msctl fleet CA"
CA_DAYS = 3650
IDENTITY_DAYS = 365
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._@-]{0,62}$")


class PkiError(ValueError):
    """A fleet certificate operation that cannot be done; the message says what to run."""


@dataclass(frozen=True)
class Identity:
    """One identity the fleet CA signed.

    Attributes:
        common_name: Its certificate's CN (``robot1``, ``operator:alice``).
        role: ``host`` or ``operator``.
        cert: The certificate file.
        key: The private key file.
        expires: When the certificate stops being valid (UTC).
        revoked: Whether it was revoked (its files are gone; the CN stays listed).
    """

    common_name: str
    role: str
    cert: Path
    key: Path
    expires: datetime | None
    revoked: bool = False


def role_of(common_name: str) -> str:
    """``host``, ``operator`` or ``ros enclave`` (a CN that is a path, ``/field/viewer``)."""
    if common_name.startswith(OPERATOR_PREFIX):
        return "operator"
    return "ros enclave" if common_name.startswith("/") else "host"


def net_dir(home: Path | None = None) -> Path:
    """``$MSCTL_HOME/net``."""
    return (home or state_dir()) / "net"


def ca_cert(home: Path | None = None) -> Path:
    """The fleet CA's certificate."""
    return net_dir(home) / "ca" / "ca.pem"


def operator_cn(name: str) -> str:
    """The common name of operator ``name``."""
    return f"{OPERATOR_PREFIX}{name}"


def identity_dir(common_name: str, home: Path | None = None) -> Path:
    """Where an identity's files live (a CN's ``:`` is not welcome in file names)."""
    name = common_name.replace(":", "-")
    if name.startswith("/"):  # a ROS enclave path
        name = "enclave" + name.replace("/", "%")
    return net_dir(home) / "identities" / name


def check_name(name: str, what: str) -> str:
    """Reject a host or operator name a certificate or a file name cannot carry."""
    if not _NAME.match(name):
        raise PkiError(
            f"{what} {name!r} is not a usable name: use letters, digits, '.', '_', '@' or '-' "
            "(at most 63, starting with a letter or digit)"
        )
    return name


def initialised(home: Path | None = None) -> bool:
    """Whether ``msctl net init`` has made the fleet CA here (it can sign identities)."""
    return ca_cert(home).is_file() and (net_dir(home) / "ca" / "ca.key").is_file()


def trusts(home: Path | None = None) -> bool:
    """Whether this computer holds the fleet CA's certificate: all a member of the fleet
    needs to verify the others. The CA's key stays where identities are made (the ground
    station): whoever holds it can mint an identity every router admits."""
    return ca_cert(home).is_file()


def init_fleet(hosts: list[str], operators: list[str], home: Path | None = None) -> list[str]:
    """Make the fleet CA (unless it exists) and an identity for each host and operator.

    Identities that already exist are kept, so running it again after adding a host to the
    assembly only adds that host.

    Returns:
        The common names created now.
    """
    _need_openssl()
    ca_dir = net_dir(home) / "ca"
    if not initialised(home):
        ca_dir.mkdir(parents=True, exist_ok=True)
        _openssl(
            "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes",
            "-keyout", str(ca_dir / "ca.key"), "-out", str(ca_dir / "ca.pem"),
            "-days", str(CA_DAYS), "-subj", f"/CN={CA_NAME}",
            "-addext", "basicConstraints=critical,CA:TRUE",
            "-addext", "keyUsage=critical,keyCertSign,cRLSign",
        )  # fmt: skip
        os.chmod(ca_dir / "ca.key", 0o600)
    made = []
    for host in hosts:
        if not identity_dir(check_name(host, "host"), home).is_dir():
            issue(host, home=home)
            made.append(host)
    for name in operators:
        cn = operator_cn(check_name(name, "operator"))
        if not identity_dir(cn, home).is_dir():
            issue(cn, home=home)
            made.append(cn)
    return made


def issue(common_name: str, home: Path | None = None, days: int = IDENTITY_DAYS) -> Identity:
    """Sign a new identity for ``common_name`` with the fleet CA.

    A host's certificate names the host, ``localhost`` and ``127.0.0.1`` so a TLS client can
    check it is talking to the router it meant to; an operator's names only the operator.

    Raises:
        PkiError: If the fleet has no CA yet.
    """
    if not initialised(home):
        if trusts(home):
            raise PkiError(
                f"{net_dir(home)} holds the fleet CA's certificate but not its key (ca/ca.key "
                f"stays where `msctl net init` ran): make the identity of {common_name} there, "
                "then copy it here"
            )
        raise PkiError(f"no fleet CA in {net_dir(home)}: run `msctl net init` first")
    _need_openssl()
    target = identity_dir(common_name, home)
    target.parent.mkdir(parents=True, exist_ok=True)
    ca_dir = net_dir(home) / "ca"
    is_operator = common_name.startswith((OPERATOR_PREFIX, "/"))
    names = (
        f"URI:msctl:{common_name.replace('/', '%2F')}"
        if is_operator
        else f"DNS:{common_name},DNS:localhost,IP:127.0.0.1"
    )
    with tempfile.TemporaryDirectory(dir=target.parent) as scratch:
        work = Path(scratch)
        (work / "ext.cnf").write_text(
            "basicConstraints=critical,CA:FALSE\n"
            "keyUsage=critical,digitalSignature,keyEncipherment\n"
            "extendedKeyUsage=serverAuth,clientAuth\n"
            f"subjectAltName={names}\n"
        )
        _openssl(
            "req", "-new", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes",
            "-keyout", str(work / "key.pem"), "-out", str(work / "req.csr"),
            "-subj", "/CN=" + common_name.replace("/", "\\/"),  # '/' separates RDNs
        )  # fmt: skip
        _openssl(
            "x509", "-req", "-in", str(work / "req.csr"), "-CA", str(ca_dir / "ca.pem"),
            "-CAkey", str(ca_dir / "ca.key"), "-set_serial", str(time.time_ns()),
            "-days", str(days), "-extfile", str(work / "ext.cnf"), "-out", str(work / "cert.pem"),
        )  # fmt: skip
        os.chmod(work / "key.pem", 0o600)
        # The CN beside the files: configs list names without running openssl per identity.
        (work / "cn").write_text(common_name + "\n")
        (work / "ext.cnf").unlink()
        (work / "req.csr").unlink()
        if target.exists():
            shutil.rmtree(target)
        work.rename(target)
        # TemporaryDirectory wants its directory back to delete.
        work.mkdir()
    _forget_revocation(common_name, home)
    return read_identity(common_name, home)


def revoke(common_name: str, home: Path | None = None) -> None:
    """Delete an identity and record its CN as revoked, so generated ACLs leave it out.

    Raises:
        PkiError: If no such identity exists.
    """
    target = identity_dir(common_name, home)
    if not target.is_dir():
        known = ", ".join(i.common_name for i in identities(home)) or "none"
        raise PkiError(f"no identity {common_name!r} to revoke (known: {known})")
    shutil.rmtree(target)
    revoked = _revoked(home)
    revoked[common_name] = datetime.now(UTC).isoformat(timespec="seconds")
    _revoked_file(home).write_text(json.dumps(revoked, indent=2) + "\n")


def read_identity(common_name: str, home: Path | None = None) -> Identity:
    """One identity, with its expiry read from its certificate."""
    target = identity_dir(common_name, home)
    cert = target / "cert.pem"
    return Identity(
        common_name=common_name,
        role=role_of(common_name),
        cert=cert,
        key=target / "key.pem",
        expires=expiry(cert) if cert.is_file() else None,
    )


def identities(home: Path | None = None, with_revoked: bool = False) -> list[Identity]:
    """Every identity, hosts then operators, each sorted by name; revoked ones last."""
    root = net_dir(home) / "identities"
    found = []
    for cert in sorted(root.glob("*/cert.pem")) if root.is_dir() else []:
        found.append(read_identity(subject_cn(cert), home))
    found.sort(key=lambda i: (("host", "operator", "ros enclave").index(i.role), i.common_name))
    if with_revoked:
        for cn in sorted(_revoked(home)):
            found.append(Identity(cn, role_of(cn),
                                  Path(), Path(), None, revoked=True))  # fmt: skip
    return found


def common_names(home: Path | None = None) -> list[str]:
    """Every identity's CN, read from the ``cn`` file beside it (fast: no openssl)."""
    root = net_dir(home) / "identities"
    names = []
    for folder in sorted(root.iterdir()) if root.is_dir() else []:
        if (folder / "cn").is_file() and (folder / "cert.pem").is_file():
            names.append((folder / "cn").read_text().strip())
        elif (folder / "cert.pem").is_file():
            names.append(subject_cn(folder / "cert.pem"))
    return names


def expiry(cert: Path) -> datetime:
    """When ``cert`` stops being valid (UTC)."""
    text = _openssl("x509", "-in", str(cert), "-noout", "-enddate").strip()
    stamp = text.split("=", 1)[1]
    return datetime.strptime(stamp, "%b %d %H:%M:%S %Y %Z").replace(tzinfo=UTC)


def subject_cn(cert: Path) -> str:
    """The common name in ``cert``'s subject."""
    text = _openssl("x509", "-in", str(cert), "-noout", "-subject", "-nameopt", "multiline")
    for line in text.splitlines():
        key, _, value = line.strip().partition("=")
        if key.strip() == "commonName":
            return value.strip()
    raise PkiError(f"{cert} has no common name in its subject")


def verify(cert: Path, home: Path | None = None) -> str | None:
    """Why ``cert`` does not verify against the fleet CA, or ``None`` when it does."""
    try:
        _openssl("verify", "-CAfile", str(ca_cert(home)), str(cert))
    except PkiError as exc:
        return str(exc)
    return None


def _revoked_file(home: Path | None) -> Path:
    return net_dir(home) / "revoked.json"


def _revoked(home: Path | None) -> dict[str, str]:
    path = _revoked_file(home)
    if not path.is_file():
        return {}
    try:
        return dict(json.loads(path.read_text()))
    except (ValueError, TypeError) as exc:
        raise PkiError(
            f"{path} is not a JSON object of revoked names: {exc}; fix or delete it"
        ) from exc


def revoked_names(home: Path | None = None) -> set[str]:
    """Common names revoked with ``msctl net revoke``."""
    return set(_revoked(home))


def _forget_revocation(common_name: str, home: Path | None) -> None:
    revoked = _revoked(home)
    if revoked.pop(common_name, None) is not None:
        _revoked_file(home).write_text(json.dumps(revoked, indent=2) + "\n")


def _need_openssl() -> None:
    if shutil.which("openssl") is None:
        raise PkiError(
            "the openssl command is not installed; install it (apt-get install openssl) and run "
            "`msctl net init` again"
        )


def _openssl(*args: str) -> str:
    # umask 077: a key is never readable by others, not even between write and chmod.
    result = subprocess.run(
        ["openssl", *args], capture_output=True, text=True, preexec_fn=lambda: os.umask(0o077)
    )
    if result.returncode != 0:
        detail = (result.stderr or result.stdout).strip().splitlines()
        raise PkiError(f"openssl {args[0]} failed: {detail[-1] if detail else result.returncode}")
    return result.stdout
