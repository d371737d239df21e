"""Typed errors. Each one reaches the user as one actionable line (see cli/errors.py)."""


class IllmError(Exception):
    """Base class: the message says what went wrong and what to do next."""


class UsageError(IllmError):
    """An option or argument the user gave cannot be used as given."""


class EngineUnreachableError(UsageError):
    """No engine answers where a served model's spec says (its identity cannot be asked): a backend's
    model only its engine can fingerprint (openai)."""


class UnknownEnvError(IllmError):
    """The environment id is not one illm knows how to render."""


class OutputExistsError(IllmError):
    """The output folder already holds data and neither --append nor --overwrite was given."""


class SchemaError(IllmError):
    """A dataset is of another kind or schema version than the reader supports."""


class ModelNotFoundError(IllmError):
    """A model alias, hub id or folder could not be resolved offline."""


class CacheError(IllmError):
    """The annotation cache is damaged or inconsistent."""


class DamagedFileError(IllmError):
    """A file illm wrote earlier cannot be read back as written (cut short, bits flipped, edited);
    the message names the file and how to recover (re-collect, repair, an older checkpoint)."""
