"""Errors that end a run with one line naming the option or file at fault, instead of a traceback."""


class ContinualNerfError(ValueError):
    """Bad input or configuration; its message is one line naming the option or file."""


class ContinualConfigError(ContinualNerfError):
    """An option value that cannot form a continual run."""


class DatasetError(ContinualNerfError):
    """A dataset file or folder that cannot be read."""


class CheckpointError(ContinualNerfError):
    """A checkpoint that cannot be found, read or resumed from."""


class OutputError(ContinualNerfError):
    """A file of the run that cannot be written: no space left, a read-only folder, ..."""


def first_line(error: BaseException) -> str:
    """The first line of an error's message, its first detail when that line only introduces a list (ends with ':'),
    or the error's type when the message is empty (a bare assert)."""
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    if len(lines) > 1 and lines[0].endswith(":"):
        return lines[1]
    return lines[0] if lines else type(error).__name__


def plural(count: int, noun: str) -> str:
    """`count` and `noun`, in the plural unless it is 1 (1 task, 3 tasks)."""
    return f"{count} {noun}{'' if count == 1 else 's'}"
