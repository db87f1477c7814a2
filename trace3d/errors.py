"""User-facing errors.

Every problem caused by the user's input (a missing or corrupt file, a wrong shape, an invalid
config, a failed reconstruction) is raised as a :class:`Trace3DError` whose message is one sentence
that names the file and what is wrong.  The CLI prints that sentence and exits with status 2,
without a traceback; anything else is a bug and keeps its traceback.
"""


class Trace3DError(Exception):
    """An error caused by the input, reported to the user as one clear sentence."""


class SceneFormatError(Trace3DError):
    """A canonical scene directory (or a file in it) is missing or malformed."""


class ConfigError(Trace3DError):
    """A parameter set given to a step is invalid."""
