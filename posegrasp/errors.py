"""posegrasp's exceptions: one root, ``PosegraspError``, and a few kinds below it.

A ``UserError`` (and its kinds ``ConfigError``, ``DatasetError``, ``WeightsError``, ``ProviderError``) is bad
input: the ``posegrasp`` command prints its one-line message and exits with status 2, without a traceback. A
``NoSpaceError`` is a full disk: the command prints its one line and exits with status 74. A
``SimulationError`` or ``PerceptionError`` ends one trial episode, which records it as its failure. A function
called with arguments outside its documented contract (a programming error, not input) raises the builtin
``ValueError``.

Kinds that replace a builtin still derive from it (``ConfigError`` is a ``ValueError``, ``SimulationError`` a
``RuntimeError``), so code catching the builtin keeps working.
"""


class PosegraspError(Exception):
    """The root of every exception posegrasp raises on purpose."""


class UserError(PosegraspError):
    """Bad input from the user: the message says what is wrong and how to fix it (the CLI prints it, exit 2)."""


class ConfigError(UserError, ValueError):
    """A setting is unusable: a TOML file that is missing, malformed or names unknown keys, or a value out of
    range (also when a settings dataclass is built in code)."""


class DatasetError(UserError):
    """Data read from disk is missing, malformed or mismatched: a BOP dataset or results file, an object set,
    a trials run folder."""


class DatasetFileError(DatasetError):
    """One file of a BOP dataset is missing, unreadable, or holds a value of the wrong shape, type or range, or one
    that disagrees with another file: the one-line message names the file, the key and what was expected."""


class WeightsError(UserError):
    """Trained network weights are missing, corrupt, or do not match the model or the run they are used with."""


class ProviderError(UserError):
    """A ``--perception`` spec names no provider, or its plugin fails to load or to build."""


class NoSpaceError(PosegraspError):
    """A write found the disk full (or the user's quota spent) in ``folder``; what it was writing was not kept."""

    def __init__(self, folder: str):
        super().__init__(folder)
        self.folder = folder

    def __str__(self) -> str:
        return f"no space left on {self.folder}"


class SimulationError(PosegraspError, RuntimeError):
    """The physics went unstable (NaN, runaway velocities or a MuJoCo warning); a trial episode records
    "simulation error"."""


class SceneUnsettled(SimulationError):
    """A scene's dropped blocks did not come to rest as required (inside the pick area, one upright, ...)
    within the allowed number of drops."""


class PerceptionError(PosegraspError):
    """A provider raised, hung past its time limit or returned what the planner cannot use; the message is one
    line saying what was wrong (the episode fails with "perception error" and records it)."""
