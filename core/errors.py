"""One exception hierarchy for the whole project.

Every error a user can cause carries a one-line message that names the field, argument or file
and says what was wrong, so the command line can print it and exit with code 2.
"""


class HapticloudError(Exception):
    """Base of every error raised on purpose by hapticloud."""


class ConfigError(HapticloudError, ValueError):
    """A parameter, scene file or override is invalid (names the field and the allowed range)."""


class InputError(HapticloudError, ValueError):
    """An argument has the wrong shape, dtype or value (names the argument)."""


class SourceError(HapticloudError):
    """A camera or recording source failed or delivered something unusable."""


class DriveError(HapticloudError):
    """The drive bus or a drive reported a fault."""


class RecordingError(HapticloudError):
    """A recording file is missing, truncated or not a hapticloud recording."""
