"""The project's narrow exception tree, and the exit status each kind ends a command with.

Messages say what was expected, what came, and what to do about it. The CLI
(`treetraits.cli.main`) prints one line per error and exits with the error's `exit_code`;
the table of codes is in docs/cli.md.
"""

# Exit statuses of every `treetraits` command (docs/cli.md, "Exit codes").
EXIT_OK = 0
EXIT_BUG = 1  # an unexpected error: a traceback, a bug to report
EXIT_USAGE = 2  # a bad input file or option (TreetraitsError), argparse's own errors
EXIT_DATA_LOSS = 3  # completed, but the input was damaged: part of it was not read
EXIT_OUTPUT_EXISTS = 4  # an earlier run's outputs are there; --force replaces them
EXIT_OUTPUT_BUSY = 5  # another run is writing the same output
EXIT_IO = 6  # the system refused a read or write: permission, disk full, not a directory
EXIT_INTERRUPTED = 130  # Ctrl-C (128 + SIGINT)
EXIT_TERMINATED = 143  # SIGTERM (128 + 15): kill, a CI runner's timeout


class TreetraitsError(Exception):
    """Base of every error treetraits raises on purpose."""

    exit_code = EXIT_USAGE


class ParseError(TreetraitsError):
    """Bytes that do not follow the wire format they claim to be."""


class SourceError(TreetraitsError):
    """A sensor source that cannot be opened or read (bad URI, missing file, port in use)."""


class CalibrationError(TreetraitsError):
    """A calibration file or value that is malformed or inconsistent."""


class ConfigError(TreetraitsError):
    """A configuration value that is missing, malformed or out of range."""


class OutputExistsError(TreetraitsError):
    """The outputs of an earlier run are where this run would write; nothing was touched."""

    exit_code = EXIT_OUTPUT_EXISTS


class OutputBusyError(TreetraitsError):
    """Another run holds the lock of the output; nothing was touched."""

    exit_code = EXIT_OUTPUT_BUSY


class FileAccessError(TreetraitsError):
    """A file or directory the system would not let us read or write (permission denied,
    disk full, a file where a directory should be, an I/O error)."""

    exit_code = EXIT_IO


class PlatformError(TreetraitsError):
    """The machine refuses something the code needs to run at all (executable memory for
    the compiled kernels); what to change is in the message."""

    exit_code = EXIT_IO


class MissingExtraError(TreetraitsError):
    """A command of an offline tool whose optional dependencies are not installed (the
    robot's install leaves them out); the message names the extra to install."""
