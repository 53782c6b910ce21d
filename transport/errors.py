"""Errors shared by the file readers."""


class TakeFileError(ValueError):
    """A take file that cannot be read; the message names the file and the problem."""
