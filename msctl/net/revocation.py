"""The record of revoked names and certificates (``MSCTL_HOME/net/revoked.json``).

It is what keeps a revocation: a name revoked stays refused until it is lifted, and every
revoked or replaced certificate stays refused for good (:mod:`msctl.net.pki`).
"""

from __future__ import annotations

import json
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from msctl.net.openssl import PkiError, fingerprint, run


def read_record(path: Path) -> dict[str, Any]:
    """``{"names": {name: when}, "certificates": [{name, cn, serial, sha256, why, when}]}``;
    the first form of the file (``{name: when}``) is read as its names."""
    if not path.is_file():
        return {"names": {}, "certificates": []}
    fix = "fix it or restore it from a backup: it keeps revoked names from being issued again"
    try:
        document = json.loads(path.read_text())
    except (ValueError, OSError) as exc:
        raise PkiError(f"{path} is not JSON ({exc}): {fix}") from None
    if isinstance(document, dict) and "names" in document:
        names, certificates = document.get("names"), document.get("certificates", [])
    else:
        names, certificates = document, []
    if (
        not isinstance(names, dict)
        or not all(isinstance(k, str) and isinstance(v, str) for k, v in names.items())
        or not isinstance(certificates, list)
        or not all(isinstance(c, dict) for c in certificates)
    ):
        raise PkiError(f"{path} is not a record of revoked names and certificates: {fix}")
    return {"names": dict(names), "certificates": list(certificates)}


def write_record(path: Path, record: dict[str, Any]) -> None:
    """Replace the record at ``path`` in one step."""
    scratch = path.with_suffix(".json.tmp")
    scratch.write_text(json.dumps(record, indent=2) + "\n")
    scratch.replace(path)  # never half a record: it is what keeps a revocation


def record_certificate(path: Path, name: str, cn: str, cert: Path, why: str) -> None:
    """Add ``cert`` (its CN, serial and SHA-256) to the record at ``path``, refused for good.

    Args:
        path: The record file.
        name: The identity's name (its CN without the issuance token).
        cn: The certificate's common name.
        cert: The certificate file.
        why: ``"revoked"`` or ``"replaced"``.
    """
    try:
        serial = run("x509", "-in", str(cert), "-noout", "-serial").strip().split("=")[-1]
    except PkiError:
        serial = None
    record = read_record(path)
    record["certificates"].append(
        {
            "name": name,
            "cn": cn,
            "serial": serial,
            "sha256": fingerprint(cert),
            "why": why,
            "when": datetime.now(UTC).isoformat(timespec="seconds"),
        }
    )
    write_record(path, record)
