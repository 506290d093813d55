"""The ``openssl`` command line, and what msctl reads from certificates and keys with it.

Keys and certificates are made and read with ``openssl`` rather than the ``cryptography``
package (see :mod:`msctl.net.pki`): every robot computer already has it.
"""

from __future__ import annotations

import base64
import hashlib
import os
import re
import shutil
import stat
import subprocess
from datetime import UTC, datetime
from pathlib import Path


class PkiError(ValueError):
    """A fleet certificate operation that cannot be done; the message says what to run."""


class KeyModeError(PkiError):
    """A private key group or others may read; the message names the ``chmod`` that fixes it."""


def expiry(cert: Path) -> datetime:
    """When ``cert`` stops being valid (UTC)."""
    text = run("x509", "-in", str(cert), "-noout", "-enddate").strip()
    stamp = text.split("=", 1)[1]
    return datetime.strptime(stamp, "%b %d %H:%M:%S %Y %Z").replace(tzinfo=UTC)


def subject_cn(cert: Path) -> str:
    """The common name in ``cert``'s subject."""
    text = run("x509", "-in", str(cert), "-noout", "-subject", "-nameopt", "multiline")
    for line in text.splitlines():
        key, _, value = line.strip().partition("=")
        if key.strip() == "commonName":
            return value.strip()
    raise PkiError(f"{cert} has no common name in its subject")


def fingerprint(cert: Path) -> str | None:
    """The SHA-256 fingerprint of a PEM certificate (of its DER bytes, as openssl prints
    it), or ``None`` when the file holds none."""
    try:
        text = cert.read_text(errors="replace")
    except OSError:
        return None
    match = re.search(r"-----BEGIN CERTIFICATE-----(.+?)-----END CERTIFICATE-----", text, re.S)
    if not match:
        return None
    try:
        der = base64.b64decode("".join(match.group(1).split()), validate=True)
    except ValueError:
        return None
    digest = hashlib.sha256(der).hexdigest().upper()
    return ":".join(digest[i : i + 2] for i in range(0, len(digest), 2))


def check_key_mode(path: Path) -> None:
    """Refuse a private key group or others may read (or write).

    Raises:
        KeyModeError: Naming the file, its mode and the ``chmod`` that fixes it.
    """
    mode = stat.S_IMODE(path.stat().st_mode)
    if mode & 0o077:
        raise KeyModeError(
            f"private key {path} is open to others (mode {mode:04o}): run `chmod 600 {path}`"
        )


def need_openssl() -> None:
    """Refuse to go on without the openssl command, saying how to install it."""
    if shutil.which("openssl") is None:
        raise PkiError(
            "the openssl command is not installed; install it (apt-get install openssl) and run "
            "`msctl net init` again"
        )


def run(*args: str) -> str:
    """``openssl <args>``: its output.

    Raises:
        PkiError: Naming the openssl command that failed and its last line of error.
    """
    # umask 077: a key is never readable by others, not even between write and chmod.
    result = subprocess.run(
        ["openssl", *args], capture_output=True, text=True, preexec_fn=lambda: os.umask(0o077)
    )
    if result.returncode != 0:
        detail = (result.stderr or result.stdout).strip().splitlines()
        raise PkiError(f"openssl {args[0]} failed: {detail[-1] if detail else result.returncode}")
    return result.stdout
