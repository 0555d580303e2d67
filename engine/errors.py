"""Engine exceptions: one flat family, mapped to HTTP errors in one place in the service."""


class EngineError(Exception):
    """Base class for every error the engine raises on purpose."""


class InvalidInputError(EngineError, ValueError):
    """An argument to a public engine function is out of range or malformed."""


class MeshValidationError(InvalidInputError):
    """A mesh failed validation (bad indices, non-finite vertices, ...).

    ``source`` names the file or object, ``counts`` holds the offending counts.
    """

    def __init__(self, message: str, *, source: str = "", counts: dict[str, int] | None = None):
        super().__init__(message)
        self.source = source
        self.counts = dict(counts or {})


class ImageFormatError(InvalidInputError):
    """An image file is unreadable, truncated, too large or of an unsupported format."""


class NonFiniteOutputError(EngineError, ArithmeticError):
    """A kernel produced NaN or Inf; the render fails instead of writing the image."""
