"""Options and argument parsing every command group shares (one definition, so they cannot drift)."""

from __future__ import annotations

import logging
import math
import os
import re
import sys
from typing import TYPE_CHECKING

import click

from autopower.errors import AutoPowerError

if TYPE_CHECKING:
    from autopower.model.scenario import Scenario

# The model and the policies (numpy, networkx, HiGHS: 0.6 s) are imported where they are used, not
# here: the operator's commands (`status`, `chain`, `fault`) use these options and load no scenario.

DEFAULT_SPEED = 10.0  # two 4 Hz blob chains at 10x = 80 frames of 230 KB a second: what 2 cores keep up with

class _FirstUseConsole:
    """rich's Console, made (and rich imported) on first use: every process of a team imports
    these options, and a robot's agent prints nothing with rich. Piped output (CI logs, `| less`)
    would otherwise be cut to 80 columns and truncate the tables, hence the width."""

    def __init__(self) -> None:
        self._console = None

    def __getattr__(self, name: str):
        if self._console is None:
            from rich.console import Console

            self._console = Console() if sys.stdout.isatty() else Console(width=200)
        return getattr(self._console, name)


console = _FirstUseConsole()


class FiniteFloat(click.ParamType):
    """A finite number, > 0 (or >= 0): `inf` and `nan` parse as floats but break every clock."""

    name = "number"

    def __init__(self, allow_zero: bool = False):
        self.allow_zero = allow_zero

    def convert(self, value, param, ctx):
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            number = float(value)
        else:
            try:
                number = float(str(value).strip())
            except ValueError:
                self.fail(f"{value!r} is not a number", param, ctx)
        if not math.isfinite(number):
            self.fail(f"{value!r} is not a finite number", param, ctx)
        if number < 0 or (number == 0 and not self.allow_zero):
            self.fail(f"{value!r}: expected a number {'>= 0' if self.allow_zero else '> 0'}", param, ctx)
        if number > MAX_OPTION_NUMBER:
            self.fail(f"{value!r} is too large (at most {MAX_OPTION_NUMBER:g})", param, ctx)
        return number


MAX_OPTION_NUMBER = 1e9  # a billion seconds (or times faster) is already far past any mission
POSITIVE = FiniteFloat()
NON_NEGATIVE = FiniteFloat(allow_zero=True)


class TeamName(click.ParamType):
    """A team name: one chunk of a Zenoh key expression and a directory name."""

    name = "team"

    def convert(self, value, param, ctx):
        from autopower.protocol.keys import check_name

        if len(str(value)) > 64:
            self.fail(f"{value!r} is longer than 64 characters", param, ctx)
        try:
            return check_name(str(value), "team name")
        except ValueError as exc:
            self.fail(str(exc), param, ctx)


TEAM_NAME = TeamName()

# Zenoh's locator protocols; a typo here would otherwise surface as a zenoh.ZError traceback.
_IP_PROTOCOLS = {"tcp", "udp", "tls", "quic", "ws"}
_PATH_PROTOCOLS = {"unixsock-stream", "unixpipe", "serial", "vsock"}
_HOST = re.compile(r"^(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9.-]+)$")


def check_endpoint(endpoint: str) -> str:
    """`endpoint` if it is a Zenoh locator such as tcp/127.0.0.1:7447, else ValueError saying why."""
    locator = endpoint.split("#", 1)[0].split("?", 1)[0]
    protocol, sep, address = locator.partition("/")
    if not sep or not address:
        raise ValueError(f"{endpoint!r} is not an endpoint; expected PROTOCOL/ADDRESS, e.g. tcp/127.0.0.1:7447")
    if protocol in _PATH_PROTOCOLS:
        return endpoint
    if protocol not in _IP_PROTOCOLS:
        raise ValueError(f"{endpoint!r}: unknown protocol {protocol!r}; use one of "
                         f"{', '.join(sorted(_IP_PROTOCOLS | _PATH_PROTOCOLS))}")
    host, sep, port = address.rpartition(":")
    if not sep or not _HOST.match(host) or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"{endpoint!r}: expected {protocol}/HOST:PORT with a port 0-65535, "
                         f"e.g. {protocol}/127.0.0.1:7447")
    return endpoint


class Endpoint(click.ParamType):
    name = "endpoint"

    def convert(self, value, param, ctx):
        try:
            return check_endpoint(str(value))
        except ValueError as exc:
            self.fail(str(exc), param, ctx)


ENDPOINT = Endpoint()
LEASE_MS = click.IntRange(100, 3_600_000)  # below 100 ms a busy machine looks like a dead peer


def parse_energies(values: tuple[str, ...]) -> dict[str, float]:
    out = {}
    for item in values:
        name, sep, joules = item.partition("=")
        try:
            if not sep:
                raise ValueError
            out[name.strip()] = float(joules)
        except ValueError:
            raise AutoPowerError(f"--energy {item!r}: expected ROBOT=JOULES, e.g. --energy r1=32000") from None
    return out



def parse_pairs(values: tuple[str, ...], what: str, example: str) -> dict[str, str]:
    out = {}
    for item in values:
        key, sep, value = item.partition("=")
        if not sep or not key.strip() or not value.strip():
            raise AutoPowerError(f"{what} {item!r}: expected NAME=VALUE, e.g. {what} {example}")
        out[key.strip()] = value.strip()
    return out



def build_scenario(name: str, energy: tuple[str, ...] = (), energy_scale: float | None = None,
                   accounting: str | None = None, profile: str | None = None,
                   as_platform: str | None = None, *, to_run: bool = False,
                   control_plane: bool | None = None) -> Scenario:
    """The scenario with a latency profile, energy overrides (absolute, then scaled), an accounting
    mode, and the control plane charged or not (``None``: as the scenario says).

    Its plug-in components are imported and checked here, before anything starts (a one-line
    `ScenarioError` naming the file and line otherwise), and registered for this process;
    ``to_run``: every component must have code (a team runs it, not only the planner), including
    those an installed package declares (entry points; planning does not look for them).
    """
    from autopower.model.loading import apply_latency_profile, load_scenario

    scenario = load_scenario(name)
    if to_run or any(spec.implementation for spec in scenario.components.values()):
        # imported here: the components' imports are heavy, and planning alone needs no code
        from autopower.chains.plugins import register_scenario_components

        register_scenario_components(scenario.components, require_code=to_run)
    if profile:
        scenario = apply_latency_profile(scenario, profile, as_platform or scenario.basestation_platform)
    if energy:
        scenario = scenario.with_energies(parse_energies(energy))
    if energy_scale is not None:
        if not energy_scale > 0:
            raise AutoPowerError(f"--energy-scale must be > 0, got {energy_scale}")
        scenario = scenario.with_energies({r.name: r.energy_j * energy_scale for r in scenario.robots})
    return scenario.with_control_plane(control_plane).with_accounting(accounting)


def check_heartbeat(status_period: float, heartbeat: float) -> None:
    """A status goes out at most once a status period: a shorter heartbeat is a mistake, said."""
    if heartbeat < status_period:
        raise AutoPowerError(f"--heartbeat {heartbeat:g} is shorter than --status-period {status_period:g}: a "
                             f"status goes out at most once a status period; give --heartbeat >= {status_period:g}")


def setup_logging(level: str) -> None:
    logging.basicConfig(level=getattr(logging, level.upper(), logging.INFO), stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")


def zenoh_settings(listen: tuple[str, ...], connect: tuple[str, ...], lease_ms: int, keep_alive: int = 4):
    from autopower.runtime.bus import ZenohSettings

    if lease_ms < 100:
        raise AutoPowerError(f"--lease-ms {lease_ms} is too short; use >= 100 ms")
    # No shared memory: Zenoh carries a message over 3 kB between two processes on one host through
    # it (measured on 1.10: 25 bytes of a 230 kB frame crossed the TCP link), so a team on one host
    # would not put its frames on the links its radios stand for (the proxies, the meter's counts)
    return ZenohSettings(listen=tuple(listen), connect=tuple(connect), lease_ms=lease_ms, keep_alive=keep_alive,
                         shared_memory=False)



TRANSPORT_OPT = click.option(
    "--transport", type=click.Choice(["tls", "quic"]), default="tls", show_default=True,
    help="What carries the links between nodes: TLS over TCP, or Zenoh's QUIC link (UDP, TLS 1.3 inside, the "
         "same certificates and access control), which keeps a lossy radio's link open where TCP stalls. "
         "The operator CLI reaches the base station over TLS either way.")

INSECURE_OPT = click.option("--insecure", is_flag=True,
                            help="Plain tcp, no certificates, no access control: anyone who reaches a port "
                                 "controls the team. Default: mutual TLS and default-deny access control.")


def warn_insecure(insecure: bool) -> None:
    """Said on every insecure start, on stderr (so --json output stays one object)."""
    if insecure:
        click.echo("warning: --insecure: no TLS and no access control; anyone who can reach this team's "
                   "ports can read its data and command it; relayed messages and subgroup votes are not "
                   "signed", err=True)


SCENARIO_ARG = click.argument("scenario", default="paper-fig7", metavar="SCENARIO")
ENERGY_OPT = click.option("--energy", multiple=True, metavar="ROBOT=J", help="Override a robot's starting energy (repeatable).")
ACCOUNTING_OPT = click.option("--accounting", type=click.Choice(["paper", "physical"]), default=None,
                              help="Message accounting (default: the scenario's).")
CONTROL_PLANE_OPT = click.option(
    "--control-plane/--no-control-plane", "control_plane", default=None,
    help="Charge the team's own statuses and keep-alives on every link (the scenario's [control_plane]; "
         "default: as the scenario says, off for the paper's scenarios).")


def profile_opts(f):
    f = click.option("--latency-profile", "profile", default=None, metavar="FILE",
                     help="Latencies measured by `autopower profile` ...")(f)
    return click.option("--as-platform", default=None, metavar="PLATFORM",
                        help="... applied to this platform (default: the base station's).")(f)


JSON_OPT = click.option("--json", "as_json", is_flag=True, help="Print one JSON object instead of a table.")


def _remember(ctx: click.Context, param: click.Parameter, value):
    """Keep a security option in the context instead of every command's signature."""
    if value is not None:
        ctx.meta[f"autopower.{param.name}"] = value
    return value


FLEET_HELP = "A directory `autopower deploy init` wrote (or one node's copy of it): team, scenario, mTLS, ACL."


def security_options(f):
    """--fleet DIR (a deployed node) and --tls DIR (an identity for endpoints given on the command line)."""
    f = click.option("--fleet", type=click.Path(file_okay=False), default=None, expose_value=False,
                     callback=_remember, metavar="DIR", help=FLEET_HELP)(f)
    return click.option("--tls", "tls_dir", type=click.Path(file_okay=False), default=None, expose_value=False,
                        callback=_remember, metavar="DIR", hidden=True,
                        help="Mutual TLS with the identity in DIR (ca.pem, NODE.pem, NODE.key) and the "
                             "team's access control (what `up` passes its children).")(f)


def fleet_dir() -> str | None:
    return click.get_current_context().meta.get("autopower.fleet")


def tls_dir() -> str | None:
    return click.get_current_context().meta.get("autopower.tls_dir")


def secure(settings, node: str, scenario: Scenario, team: str):
    """``settings`` with mutual TLS and the team's access control when --tls DIR was given."""
    import dataclasses

    directory = tls_dir()
    if directory is None:
        return settings
    from autopower.deploy.fleet import team_access
    from autopower.deploy.pki import identity_in
    from autopower.runtime.access_control import zenoh_access_control

    return dataclasses.replace(settings, tls=identity_in(directory, node),
                               access_control=zenoh_access_control(team_access(scenario, team)))


def network_options(f):
    f = security_options(f)
    f = click.option("--scenario", "scenario_name", default="paper-fig7", show_default=True,
                     help="Built-in scenario name or path to a .toml file.")(f)
    f = click.option("--team", default="default", show_default=True, type=TEAM_NAME,
                     help="Team name: every key is under autopower/<team>/.")(f)
    f = click.option("--listen", multiple=True, metavar="ENDPOINT", type=ENDPOINT,
                     help="Zenoh endpoint to listen on, e.g. tcp/127.0.0.1:7447 (repeatable).")(f)
    f = click.option("--connect", multiple=True, metavar="ENDPOINT", type=ENDPOINT,
                     help="Zenoh endpoint of a peer to connect to (repeatable; peers do not relay).")(f)
    f = click.option("--lease-ms", default=1000, show_default=True, type=LEASE_MS,
                     help="Zenoh lease: a frozen peer or cut link is noticed after about this long.")(f)
    f = click.option("--keep-alive", default=4, show_default=True, type=click.IntRange(2, 16),
                     help="Zenoh keep-alives per lease on an idle link: a link survives a silence of "
                          "lease x (1 - 1/N) between them (lost or late keep-alives); fewer is less CPU at rest.")(f)
    f = click.option("--status-period", default=0.5, type=POSITIVE, show_default=True,
                     help="Wall seconds within which a change (a plan, a stage, a link) is said in a status.")(f)
    f = click.option("--heartbeat", default=2.0, type=POSITIVE, show_default=True,
                     help="Wall seconds between statuses with nothing new in them (counts move, nothing "
                          "changes); at least --status-period.")(f)
    f = click.option("--duration", type=POSITIVE, default=None, help="Stop after this many wall seconds.")(f)
    f = click.option("--parent-pid", type=int, default=None, hidden=True)(f)
    f = click.option("--record-dir", type=click.Path(file_okay=False), default=None,
                     help="Write this process's Rerun recording into DIR (the run's shared recording id).")(f)
    f = click.option("--log-level", default="info", show_default=True,
                     type=click.Choice(["debug", "info", "warning", "error"]))(f)
    return f


STAGE_WORKER_CHOICES = ("off", "on", "auto")


def stage_workers_option(f):
    """``--stage-workers``: each hosted stage's component in a worker process of its own."""
    return click.option(
        # auto by default: a worker's inputs are acknowledged only once their outputs are out and a
        # full worker refuses inputs before the gate, so workers lose nothing a crash would not
        # (docs/tutorials/own-component.md); auto keeps them where they were measured to pay
        "--stage-workers", type=click.Choice(STAGE_WORKER_CHOICES), default="auto", show_default=True,
        help="Run each hosted stage's component in a worker process of its own, called asynchronously, so "
             f"stages run in parallel on several cores; auto: on for the base station of a mission at x{AUTO_WORKERS_SPEED:g} "
             f"or faster on a machine with {AUTO_WORKERS_CORES} cores or more, else off.")(f)


# When `auto` puts the base station's stages in worker processes. Measured on a 2-core machine
# running the whole team (docs/performance.md): at x10 the loop keeps up alone and workers only
# cost CPU (+10 points of a core); from x50 on the workers' extra CPU (+30-60 points) came out of
# the robots' agents on the same 2 cores and more periods were missed than without. They pay where
# cores are spare: not measured here (no such machine), hence at least 4.
AUTO_WORKERS_SPEED = 20.0
AUTO_WORKERS_CORES = 4


def stage_workers_wanted(choice: str, basestation: bool, speed: float | None = None) -> bool:
    """What ``--stage-workers CHOICE`` means for this process (``speed``: the mission's, if known)."""
    if choice == "auto":
        return (basestation and len(os.sched_getaffinity(0)) >= AUTO_WORKERS_CORES
                and speed is not None and speed >= AUTO_WORKERS_SPEED)
    return choice == "on"


def mission_options(f):
    """The mission settings `basestation` and `up` share (one definition, so they cannot drift)."""
    from autopower.policies import POLICY_NAMES

    for option in reversed([
        click.option("--energy", multiple=True, metavar="ROBOT=J", help="Starting energy of a robot (repeatable)."),
        click.option("--energy-scale", type=POSITIVE, default=None,
                     help="Multiply every starting energy, e.g. 0.01 to watch a whole mission in a minute or two."),
        click.option("--accounting", type=click.Choice(["paper", "physical"]), default=None),
        click.option("--topology", type=click.Choice(["fully-connected", "relay", "explicit"]), default=None),
        click.option("--media", multiple=True, metavar="GROUP=MEDIUM",
                     help="Fix a link group's medium, e.g. laptop-robot=gsm (default: the planner chooses)."),
        click.option("--pin", multiple=True, metavar="STAGE=NODE", help="Keep a stage on a node (repeatable)."),
        click.option("--no-replan", is_flag=True,
                     help="No decisions on battery drift, periodically or when a schedule's phase ends."),
        click.option("--policy", type=click.Choice(list(POLICY_NAMES)), default="rebalance", show_default=True,
                     help="What decides the placement (the simulator's policies): static never moves by choice, "
                          "reactive replans on events, rebalance follows a time-sharing schedule, subgroup "
                          "reallocates within the parts of the team that reach each other."),
    ]):
        f = option(f)
    return f


def operator_options(f):
    f = security_options(f)
    f = click.option("--team", default=None, type=TEAM_NAME,
                     help="Team name (default: the only team `autopower up` runs on this machine).")(f)
    f = click.option("--connect", multiple=True, metavar="ENDPOINT", type=ENDPOINT,
                     help="The base station's endpoint (default: the last `autopower up`).")(f)
    f = click.option("--timeout", type=POSITIVE, default=5.0, show_default=True)(f)
    return f


