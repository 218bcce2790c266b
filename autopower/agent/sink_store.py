"""A sink's ledgers kept on disk, so a restarted sink neither repeats nor loses an output.

The base station is the operator's sink. When it is killed and started again, the producers'
custody (`autopower.agent.custody`) resends every output the old sink had not acknowledged yet
(acknowledgements travel in the status, every half second), including some it had received:
without its ledgers the new sink would hand those to the operator a second time. So the sink
writes its ledgers (`SinkLedger.state`: run, in-order prefix, what arrived above it, digest) each
time it takes in a new output, before handing the output on; the restarted sink starts from them,
counts the resent copies as redundant and reports the same prefix to the producers.

The file belongs to one mission (its clock's ``epoch_unix``): a new mission starts empty. It is
written whole to a temporary file and renamed over the old one, so a kill at any instant leaves
either the previous or the new state, never a torn one; a file that cannot be read is reported
and ignored (the sink then starts empty, as it did before this existed).
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

from autopower.agent.sequencing import SinkLedger

log = logging.getLogger(__name__)


class SinkStore:
    def __init__(self, path: Path):
        self.path = Path(path)
        self._tmp = self.path.with_name(self.path.name + ".tmp")
        self.failed = False  # a write failed (reported once; the sink goes on without)

    def load(self, mission_epoch_unix: float) -> dict[str, SinkLedger]:
        """The ledgers kept for this mission ({} for another mission, none kept, or a bad file)."""
        try:
            state = json.loads(self.path.read_text())
        except FileNotFoundError:
            return {}
        except (OSError, ValueError, UnicodeDecodeError) as exc:
            log.warning("sink state %s is unreadable (%s); starting the sinks empty", self.path, exc)
            return {}
        if not isinstance(state, dict) or state.get("mission_epoch_unix") != mission_epoch_unix:
            return {}  # another mission's (or a file we did not write)
        try:
            ledgers = {str(chain): SinkLedger.from_state(s) for chain, s in state["sinks"].items()}
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            log.warning("sink state %s is not a sink state (%s); starting the sinks empty", self.path, exc)
            return {}
        log.info("sinks go on from %s: %s", self.path,
                 ", ".join(f"{c} run {l.run} seq {l.contiguous}" for c, l in sorted(ledgers.items())) or "none")
        return ledgers

    def save(self, mission_epoch_unix: float, sinks: dict[str, SinkLedger]) -> None:
        data = json.dumps({"mission_epoch_unix": mission_epoch_unix,
                           "sinks": {chain: ledger.state() for chain, ledger in sinks.items()}},
                          separators=(",", ":")).encode()
        try:
            fd = os.open(self._tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            try:
                os.write(fd, data)
            finally:
                os.close(fd)
            os.replace(self._tmp, self.path)
        except OSError as exc:
            if not self.failed:
                log.error("cannot keep the sink state in %s (%s); a restart may repeat outputs", self.path, exc)
            self.failed = True
