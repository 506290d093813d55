"""The fleet's certificate authority and its identities, kept under ``$MSCTL_HOME/net``.

One CA per fleet signs one identity (key and certificate) per robot computer, ground station
and operator. The certificate's common name is what Zenoh's access control matches
(``cert_common_names``, the only property of a certificate it can match: no serial, no
fingerprint, no revocation list): the identity's name (the host name for a computer,
``operator:<name>`` for an operator, the path of a ROS enclave) followed by ``#`` and a token
drawn anew at every issuance (``ground1#9f3a01c2``). The routers' access control names the
current certificate's CN, so a certificate replaced or revoked is refused by every config
generated afterwards, even though it is signed by the fleet CA and has not expired.

A revocation holds until it is lifted explicitly (``msctl net unrevoke``): nothing issues a
revoked name again before that, and the revoked certificate (CN, serial, SHA-256) is kept on
record and never admitted, lifted or not.

Private keys (the CA's and every identity's) are written 0600, and whatever reads one refuses
it when group or others may read it (:func:`check_key_mode`): ``MSCTL_HOME/net`` is copied
between computers, and a copy can lose its modes.

Keys and certificates are made with the ``openssl`` command line rather than the
``cryptography`` package: every robot computer already has openssl, the venv does not carry
``cryptography``, and a dependency with a compiled core is one more thing to fail offline
(those calls: :mod:`msctl.net.openssl`; the record of revocations: :mod:`msctl.net.revocation`).

Layout::

    net/ca/ca.pem, ca.key                       the fleet CA (key 0600)
    net/identities/<file name>/cert.pem, key.pem  one directory per identity (key 0600)
    net/revoked.json                            names revoked (with when) and every revoked
                                                or replaced certificate (CN, serial, SHA-256)
"""

from __future__ import annotations

import os
import re
import secrets
import shutil
import tempfile
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from components.assembly import state_dir
from msctl.net.openssl import (
    KeyModeError,
    PkiError,
    check_key_mode,
    expiry,
    fingerprint,
    subject_cn,
)
from msctl.net.openssl import need_openssl as _need_openssl
from msctl.net.openssl import run as _openssl
from msctl.net.revocation import read_record, record_certificate, write_record

#: Prefix of an operator's common name (``operator:alice``).
OPERATOR_PREFIX = "operator:"
CA_NAME = "msctl fleet CA"
CA_DAYS = 3650
IDENTITY_DAYS = 365
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._@-]*$")  # its length: _check_cn_length
#: Separates an identity's name from its issuance token in a certificate's CN.
ISSUANCE_MARK = "#"
#: Hex digits of the issuance token (32 random bits: two issuances of a name never share one).
TOKEN_HEX = 8
#: X.509's bound on a common name, name and token (openssl refuses a longer one).
CN_MAX = 64


class RevokedError(PkiError):
    """The name was revoked and the revocation was not lifted."""


@dataclass(frozen=True)
class Identity:
    """One identity the fleet CA signed.

    Attributes:
        common_name: Its name (``robot1``, ``operator:alice``, ``/field/viewer``): its
            certificate's CN without the issuance token.
        role: ``host``, ``operator`` or ``ros enclave``.
        cert: The certificate file.
        key: The private key file.
        expires: When the certificate stops being valid (UTC).
        revoked: Whether it was revoked (its files are gone; the name stays listed).
        certificate_cn: The CN of its current certificate, which the routers' access
            control names (``robot1#9f3a01c2``); empty when it has none.
    """

    common_name: str
    role: str
    cert: Path
    key: Path
    expires: datetime | None
    revoked: bool = False
    certificate_cn: str = ""


def name_of(certificate_cn: str) -> str:
    """The identity's name in a certificate's CN (``robot1#9f3a01c2`` -> ``robot1``)."""
    return certificate_cn.partition(ISSUANCE_MARK)[0]


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
    """Reject a host or operator name (``what``: ``operator``) a certificate cannot carry."""
    if not _NAME.match(name):
        raise PkiError(
            f"{what} {name!r} is not a usable name: use letters, digits, '.', '_', '@' or '-', "
            "starting with a letter or digit"
        )
    _check_cn_length(operator_cn(name) if what == "operator" else name, what)
    return name


def initialised(home: Path | None = None) -> bool:
    """Whether ``msctl net init`` has made the fleet CA here (it can sign identities)."""
    return ca_cert(home).is_file() and (net_dir(home) / "ca" / "ca.key").is_file()


def trusts(home: Path | None = None) -> bool:
    """Whether this computer holds the fleet CA's certificate: all a member of the fleet
    needs to verify the others. The CA's key stays where identities are made (the ground
    station): whoever holds it can mint an identity every router admits."""
    return ca_cert(home).is_file()


def init_fleet(
    hosts: list[str], operators: list[str], home: Path | None = None, lift: bool = False
) -> list[str]:
    """Make the fleet CA (unless it exists) and an identity for each host and operator.

    Identities that already exist are kept, so running it again after adding a host to the
    assembly only adds that host. An existing CA is verified before it signs anything.

    Args:
        hosts: Computers.
        operators: Operators (``alice@ground1``, without the ``operator:`` prefix).
        home: MSCTL_HOME (default: the environment's).
        lift: Lift the revocation of any of these names (their revoked certificates stay
            refused) instead of refusing them.

    Returns:
        The names of the identities created now.

    Raises:
        RevokedError: A name was revoked and ``lift`` is not given (nothing is written).
        PkiError: A name a certificate cannot carry, or an existing CA that is broken.
    """
    _need_openssl()
    wanted = [check_name(h, "host") for h in hosts]
    wanted += [operator_cn(check_name(o, "operator")) for o in operators]
    for name in [] if lift else wanted:  # the names' lengths: check_name
        refuse_revoked(name, home)
    ca_dir = net_dir(home) / "ca"
    if (ca_dir / "ca.pem").exists() or (ca_dir / "ca.key").exists():
        verify_ca(home)
    else:
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
    for name in wanted:
        if not identity_dir(name, home).is_dir():
            _sign(name, home, IDENTITY_DAYS)  # the CA was verified above, the names too
            if lift:
                _lift(name, home)
            made.append(name)
    return made


def issue(
    common_name: str, home: Path | None = None, days: int = IDENTITY_DAYS, lift: bool = False
) -> Identity:
    """Sign a new identity for ``common_name`` with the fleet CA.

    A host's certificate names the host, ``localhost`` and ``127.0.0.1`` so a TLS client can
    check it is talking to the router it meant to; an operator's names only the operator.
    Its CN is the name and a fresh issuance token: an identity issued again replaces the
    one before it in every config generated afterwards, and the one before is kept on
    record as replaced (never admitted again).

    Args:
        common_name: The identity's name (``robot1``, ``operator:alice``, ``/field/viewer``).
        home: MSCTL_HOME (default: the environment's).
        days: How long the certificate is valid.
        lift: Lift a revocation of the name (the revoked certificate stays refused).

    Raises:
        RevokedError: If the name was revoked and ``lift`` is not given.
        KeyModeError: If the CA's key may be read by others.
        PkiError: If the fleet has no CA here, or it is broken.
    """
    _check_cn_length(common_name)
    if not lift:
        refuse_revoked(common_name, home)
    if not initialised(home):
        if trusts(home):
            raise PkiError(
                f"{net_dir(home)} holds the fleet CA's certificate but not its key (ca/ca.key "
                f"stays where `msctl net init` ran): make the identity of {common_name} there, "
                "then copy it here"
            )
        raise PkiError(f"no fleet CA in {net_dir(home)}: run `msctl net init` first")
    _need_openssl()
    verify_ca(home)
    _sign(common_name, home, days)
    if lift:
        _lift(common_name, home)
    return read_identity(common_name, home)


def _sign(common_name: str, home: Path | None, days: int) -> None:
    """Make and sign ``common_name``'s key and certificate, replacing any it had."""
    target = identity_dir(common_name, home)
    target.parent.mkdir(parents=True, exist_ok=True)
    ca_dir = net_dir(home) / "ca"
    is_operator = common_name.startswith((OPERATOR_PREFIX, "/"))
    names = (
        f"URI:msctl:{common_name.replace('/', '%2F')}"
        if is_operator
        else f"DNS:{common_name},DNS:localhost,IP:127.0.0.1"
    )
    certificate_cn = f"{common_name}{ISSUANCE_MARK}{secrets.token_hex(TOKEN_HEX // 2)}"
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
            "-subj", "/CN=" + certificate_cn.replace("/", "\\/"),  # '/' separates RDNs
        )  # fmt: skip
        _openssl(
            "x509", "-req", "-in", str(work / "req.csr"), "-CA", str(ca_dir / "ca.pem"),
            "-CAkey", str(ca_dir / "ca.key"), "-set_serial", str(time.time_ns()),
            "-days", str(days), "-extfile", str(work / "ext.cnf"), "-out", str(work / "cert.pem"),
        )  # fmt: skip
        os.chmod(work / "key.pem", 0o600)
        # The CN beside the files: configs list names without running openssl per identity.
        (work / "cn").write_text(certificate_cn + "\n")
        (work / "ext.cnf").unlink()
        (work / "req.csr").unlink()
        if (target / "cert.pem").is_file():
            # Kept on record first: the certificate replaced is never admitted again.
            _record_certificate(common_name, target, "replaced", home)
        if target.exists():
            shutil.rmtree(target)
        work.rename(target)
        # TemporaryDirectory wants its directory back to delete.
        work.mkdir()


def revoke(common_name: str, home: Path | None = None) -> None:
    """Delete an identity and record it revoked: its name is issued again only once the
    revocation is lifted (:func:`unrevoke`), and its certificate is never admitted again.

    Raises:
        PkiError: If no such identity exists (or it was revoked already).
    """
    target = identity_dir(common_name, home)
    if not target.is_dir():
        when = _revoked(home)["names"].get(common_name)
        if when:
            raise PkiError(f"{common_name} was revoked already ({when})")
        known = ", ".join(sorted(common_names(home))) or "none"
        raise PkiError(f"no identity {common_name!r} to revoke (known: {known})")
    # Recorded before the files go: a revocation half done must still hold.
    record = _revoked(home)
    record["names"][common_name] = datetime.now(UTC).isoformat(timespec="seconds")
    _write_revoked(record, home)
    _record_certificate(common_name, target, "revoked", home)
    shutil.rmtree(target)


def unrevoke(common_name: str, home: Path | None = None) -> str:
    """Lift the revocation of a name, so it can be issued again; its revoked certificates
    stay refused (they stay on record).

    Returns:
        When it had been revoked.

    Raises:
        PkiError: If the name is not revoked.
    """
    when = _revoked(home)["names"].get(common_name)
    if when is None:
        revoked = ", ".join(sorted(_revoked(home)["names"])) or "none"
        raise PkiError(f"{common_name} is not revoked (revoked: {revoked})")
    _lift(common_name, home)
    return when


def read_identity(common_name: str, home: Path | None = None) -> Identity:
    """One identity, with its expiry read from its certificate.

    Raises:
        PkiError: If its certificate cannot be read, naming the file and what to do.
    """
    target = identity_dir(common_name, home)
    cert = target / "cert.pem"
    expires = None
    certificate_cn = ""
    if cert.is_file():
        try:
            expires = expiry(cert)
        except PkiError as exc:
            raise PkiError(
                f"{cert} is not a readable certificate ({exc}): {reissue_hint(common_name)}"
            ) from None
        certificate_cn = _cn_file(target) or subject_cn(cert)
    return Identity(
        common_name=common_name,
        role=role_of(common_name),
        cert=cert,
        key=target / "key.pem",
        expires=expires,
        certificate_cn=certificate_cn,
    )


def reissue_hint(common_name: str) -> str:
    """What to run to give ``common_name`` a working identity again."""
    if common_name.startswith(OPERATOR_PREFIX):
        return f"issue it again with `msctl net add-operator {cli_name(common_name)}`"
    folder = identity_dir(common_name)
    return (
        f"copy {folder.name}/ again from where `msctl net init` ran, or delete it there and "
        f"run `msctl net init --host {common_name}`"
    )


def cli_name(common_name: str) -> str:
    """How the ``msctl net`` commands name an identity (an operator without its prefix)."""
    return common_name.removeprefix(OPERATOR_PREFIX)


def scan(home: Path | None = None) -> tuple[list[Identity], list[tuple[Path, str]]]:
    """Every identity that can be read, and each one that cannot (its certificate file and
    why), so a listing or a preflight goes on past a broken one."""
    root = net_dir(home) / "identities"
    found: list[Identity] = []
    broken: list[tuple[Path, str]] = []
    for cert in sorted(root.glob("*/cert.pem")) if root.is_dir() else []:
        try:
            name = name_of(_cn_file(cert.parent) or subject_cn(cert))
            found.append(read_identity(name, home))
        except PkiError as exc:
            why = str(exc)
            if str(cert) not in why:  # whose it is unknown too: no CN file, no CN read
                why = (
                    f"{cert} is not a readable certificate ({why}): copy {cert.parent.name}/ "
                    "again from where `msctl net init` ran, or delete it there and issue it again"
                )
            broken.append((cert, why))
    found.sort(key=lambda i: (("host", "operator", "ros enclave").index(i.role), i.common_name))
    return found, broken


def identities(home: Path | None = None, with_revoked: bool = False) -> list[Identity]:
    """Every identity, hosts then operators, each sorted by name; revoked ones last.

    Raises:
        PkiError: If a certificate cannot be read (naming it; :func:`scan` goes on past).
    """
    found, broken = scan(home)
    if broken:
        path, why = broken[0]
        raise PkiError(why if str(path) in why else f"{path}: {why}")
    if with_revoked:
        for cn in sorted(_revoked(home)["names"]):
            found.append(Identity(cn, role_of(cn),
                                  Path(), Path(), None, revoked=True))  # fmt: skip
    return found


def common_names(home: Path | None = None) -> list[str]:
    """Every identity's name, read from the ``cn`` file beside it (fast: no openssl)."""
    return sorted(admitted(home, every=True))


def admitted(home: Path | None = None, every: bool = False) -> dict[str, str]:
    """The certificate CN each identity's routers admit it by, name -> CN.

    Left out: revoked names, and a certificate on record as revoked or replaced (a copy
    of an old ``net/`` put back must not bring it back).

    Args:
        home: MSCTL_HOME (default: the environment's).
        every: Every identity on disk, revoked or not.
    """
    root = net_dir(home) / "identities"
    record = _revoked(home)
    refused_cns = {c.get("cn") for c in record["certificates"]}
    refused_prints = {c.get("sha256") for c in record["certificates"]} - {None}
    names: dict[str, str] = {}
    for folder in sorted(root.iterdir()) if root.is_dir() else []:
        cert = folder / "cert.pem"
        if not cert.is_file():
            continue
        try:
            certificate_cn = _cn_file(folder) or subject_cn(cert)
        except PkiError:
            continue  # unreadable: admitted by nobody (doctor and `net show` say so)
        name = name_of(certificate_cn)
        if not every and (
            name in record["names"]
            or certificate_cn in refused_cns
            or fingerprint(cert) in refused_prints
        ):
            continue
        names[name] = certificate_cn
    return names


def verify(cert: Path, home: Path | None = None) -> str | None:
    """Why ``cert`` does not verify against the fleet CA, or ``None`` when it does."""
    try:
        _openssl("verify", "-CAfile", str(ca_cert(home)), str(cert))
    except PkiError as exc:
        return str(exc)
    return None


def verify_ca(home: Path | None = None) -> None:
    """Check the fleet CA here can sign: its certificate and key read, belong together, and
    the key is kept private.

    Raises:
        KeyModeError: If others may read ``ca.key``.
        PkiError: Naming the file at fault and what to do.
    """
    ca_dir = net_dir(home) / "ca"
    pem, key = ca_dir / "ca.pem", ca_dir / "ca.key"
    start_over = (
        f"restore it from a backup, or move {ca_dir} away to make a new fleet CA (every "
        "identity must then be issued again and copied to every computer)"
    )
    if not pem.is_file():
        raise PkiError(f"{key} is here but not the CA's certificate {pem}: {start_over}")
    if not key.is_file():
        raise PkiError(
            f"{ca_dir} holds the fleet CA's certificate but not its key (ca.key stays where "
            "`msctl net init` first ran): run it there, then copy its MSCTL_HOME/net here "
            "(all but ca/ca.key)"
        )
    check_key_mode(key)
    try:
        cert_public = _openssl("x509", "-in", str(pem), "-noout", "-pubkey")
    except PkiError as exc:
        raise PkiError(f"{pem} is not a certificate ({exc}): {start_over}") from None
    try:
        key_public = _openssl("pkey", "-in", str(key), "-pubout")
    except PkiError as exc:
        raise PkiError(f"{key} is not a private key ({exc}): {start_over}") from None
    if cert_public.strip() != key_public.strip():
        raise PkiError(f"{key} is not the key of {pem} (a copy from another fleet?): {start_over}")
    try:
        _openssl("x509", "-in", str(pem), "-noout", "-checkend", "0")
    except PkiError:
        raise PkiError(f"{pem} has expired: {start_over}") from None


def loose_keys(home: Path | None = None) -> list[tuple[Path, str]]:
    """Every private key under ``MSCTL_HOME/net`` group or others may read: the file, and
    the error reading it raises (its mode and the ``chmod`` that fixes it)."""
    root = net_dir(home)
    keys = [root / "ca" / "ca.key", *sorted((root / "identities").glob("*/key.pem"))]
    found = []
    for key in keys:
        try:
            if key.is_file():
                check_key_mode(key)
        except KeyModeError as exc:
            found.append((key, str(exc)))
    return found


def _check_cn_length(common_name: str, what: str = "") -> None:
    prefix = len(OPERATOR_PREFIX) if common_name.startswith(OPERATOR_PREFIX) else 0
    longest, name = CN_MAX - len(ISSUANCE_MARK) - TOKEN_HEX - prefix, common_name[prefix:]
    if len(name) > longest:
        raise PkiError(
            f"{what or role_of(common_name)} {name!r} is too long: {len(name)} characters, at "
            f"most {longest} for {role_of(common_name)} names (a certificate's CN carries the "
            "name and an issuance token): choose a shorter name"
        )


def _cn_file(folder: Path) -> str:
    """The certificate CN written beside it (``""``: none, an identity from elsewhere, or
    one that does not name this folder's identity, which the certificate then tells)."""
    try:
        text = (folder / "cn").read_text().strip()
    except (OSError, UnicodeDecodeError):
        return ""
    name = name_of(text)
    try:
        ours = bool(name) and identity_dir(name, folder.parent.parent.parent).name == folder.name
    except ValueError:
        ours = False
    return text if ours else ""


def refuse_revoked(common_name: str, home: Path | None = None) -> None:
    """Refuse a name revoked and not lifted, saying when and how to lift it.

    Raises:
        RevokedError: If ``common_name`` is revoked.
    """
    when = _revoked(home)["names"].get(common_name)
    if when is None:
        return
    name = cli_name(common_name)
    again = (
        f"`msctl net add-operator {name} --lift`"
        if common_name.startswith(OPERATOR_PREFIX)
        else f"`msctl net init --host {name} --lift`"
    )
    raise RevokedError(
        f"{common_name} was revoked ({when}) and stays revoked: to give it a new identity, "
        f"lift the revocation with `msctl net unrevoke {name}` or {again} (its revoked "
        "certificate stays refused)"
    )


def _revoked_file(home: Path | None) -> Path:
    return net_dir(home) / "revoked.json"


def _revoked(home: Path | None) -> dict[str, Any]:
    """The record of revocations (:func:`msctl.net.revocation.read_record`)."""
    return read_record(_revoked_file(home))


def _write_revoked(record: dict[str, Any], home: Path | None) -> None:
    write_record(_revoked_file(home), record)


def _record_certificate(common_name: str, folder: Path, why: str, home: Path | None) -> None:
    cn = _cn_file(folder) or common_name
    record_certificate(_revoked_file(home), common_name, cn, folder / "cert.pem", why)


def revoked_names(home: Path | None = None) -> set[str]:
    """Names revoked with ``msctl net revoke`` and not lifted."""
    return set(_revoked(home)["names"])


def revoked_certificates(home: Path | None = None) -> list[dict[str, Any]]:
    """Every certificate revoked or replaced (name, cn, serial, sha256, why, when)."""
    return list(_revoked(home)["certificates"])


def _lift(common_name: str, home: Path | None) -> None:
    record = _revoked(home)
    if record["names"].pop(common_name, None) is not None:
        _write_revoked(record, home)
