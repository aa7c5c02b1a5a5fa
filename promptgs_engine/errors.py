"""Errors the engine reports to users as one clear line (CLI exit code 2)."""


class PromptGSError(Exception):
    """Base class: a problem with the user's input or setup, not a bug."""


class DatasetError(PromptGSError, ValueError):
    """A dataset folder, COLMAP model or image that cannot be used as given."""


class PromptError(PromptGSError, ValueError):
    """A prompt file or prompt box that cannot be used (bad format, seen by no camera)."""


class TrainingError(PromptGSError, RuntimeError):
    """Training cannot go on (NaN/inf in a parameter, out of memory); the last good checkpoint is kept."""
