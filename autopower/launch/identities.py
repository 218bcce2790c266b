"""The certificates of a team started on this machine (`up`, `demo`, the testbed).

The same mechanism as a fleet on real hosts (`autopower.deploy`): a CA made for this team alone
and one identity per node plus the operator, under ``<state dir>/tls/<team>/`` (0700, keys
0600). Every link is then mutual TLS against that CA and every node enforces the team's access
control. The directory is removed when the team stops: nothing outside it holds the CA's key.
"""

from __future__ import annotations

import logging
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

from autopower.basestation.operator import TLS_DIR, state_dir
from autopower.deploy.pki import TeamCA, identity_in
from autopower.protocol.access import OPERATOR
from autopower.runtime.bus import TlsFiles, ZenohSettings

log = logging.getLogger(__name__)

LOCAL_NAMES = ("127.0.0.1", "localhost")


@dataclass
class LocalIdentities:
    directory: Path

    @classmethod
    def create(cls, team: str, nodes, directory: Path | None = None,
               addresses: dict[str, list[str]] | None = None) -> "LocalIdentities":
        """A new CA and identities for ``nodes`` and the operator (SAN: loopback + ``addresses``)."""
        directory = Path(directory) if directory else state_dir() / TLS_DIR / team
        directory.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
        directory.mkdir(parents=True, exist_ok=True, mode=0o700)
        os.chmod(directory, 0o700)
        ca = TeamCA.create(directory / "ca", team)
        for node in [*nodes, OPERATOR]:
            ca.issue(node, [*LOCAL_NAMES, *(addresses or {}).get(node, [])], directory)
        log.info("team %s: certificates in %s", team, directory)
        return cls(directory)

    def files(self, node: str) -> TlsFiles:
        return identity_in(self.directory, node)

    def operator_settings(self, base_endpoint: str) -> ZenohSettings:
        return ZenohSettings(connect=(base_endpoint,), tls=self.files(OPERATOR))

    def remove(self) -> None:
        shutil.rmtree(self.directory, ignore_errors=True)
