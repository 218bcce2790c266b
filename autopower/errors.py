"""One exception tree for everything AutoPower reports to a user.

Every message says what was wrong, where (file, field, robot, key) and what to do about it,
so the CLI can print it as-is and exit non-zero without a traceback.
"""


class AutoPowerError(Exception):
    """Base of every error AutoPower raises on purpose."""


class ScenarioError(AutoPowerError):
    """A scenario file (or an override of it) is malformed or inconsistent."""


class InfeasibleError(AutoPowerError):
    """No allocation meets the CPU and radio limits."""


class ProtocolError(AutoPowerError):
    """A message could not be decoded: unknown kind, wrong version, wrong fields, garbage."""


class RecordingError(AutoPowerError):
    """A Rerun recording is missing, corrupt, or not an AutoPower run."""
