"""The project's narrow exception tree.

Messages say what was expected, what came, and what to do about it.
"""


class TreetraitsError(Exception):
    """Base of every error treetraits raises on purpose."""


class ParseError(TreetraitsError):
    """Bytes that do not follow the wire format they claim to be."""


class SourceError(TreetraitsError):
    """A sensor source that cannot be opened or read (bad URI, missing file, port in use)."""


class CalibrationError(TreetraitsError):
    """A calibration file or value that is malformed or inconsistent."""


class ConfigError(TreetraitsError):
    """A configuration value that is missing, malformed or out of range."""
