"""Errors that the CLI turns into a one-line message and exit code 2."""


class InputError(Exception):
    """Bad input or bad usage: names the file/record and what to do. Never a bug in uwbcal."""
