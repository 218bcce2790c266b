"""Launching teams: the localhost launcher, per-link proxies and fault injection.

Owns: starting a team's processes and waiting until it is ready (`localhost.py`), one TCP proxy
per topology link that a fault silences (`linkproxy.py`), and the fault controller with its
Unix-socket channel that keeps working while Zenoh links are cut (`faults.py`).

May import every layer below: the processes (`autopower.agent`, `autopower.basestation`), the
runtime, recording, policies and the model. Only `autopower.cli` imports this.
"""
