"""Errors that end a run with one line naming the option or file at fault, instead of a traceback."""


class ContinualNerfError(ValueError):
    """Bad input or configuration; its message is one line naming the option or file."""


class ContinualConfigError(ContinualNerfError):
    """An option value that cannot form a continual run."""


class DatasetError(ContinualNerfError):
    """A dataset file or folder that cannot be read."""
