"""Small shared types for the API schemas.

Numbers are *strict*: JSON ``true`` or ``"1.5"`` is an error, not a silent 1.0 or 1.5
(the pbrt-v4 ``ReportUnused`` spirit: a typo must not render something). Integers in
JSON are accepted where a float is expected. NaN and infinities are rejected
everywhere, so no validator downstream has to re-check finiteness.

From Python, numpy scalars are accepted for floats; numpy arrays are accepted for the
bulk mesh arrays (see :func:`ndarray_to_list`) and numpy integers for scalar ints.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from typing import Annotated, Any

import numpy as np
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, StringConstraints, ValidationError
from pydantic_core import InitErrorDetails, PydanticCustomError

__all__ = [
    "NAME_PATTERN",
    "RGB",
    "FiniteFloat",
    "FrozenModel",
    "Loc",
    "Name",
    "NonNegativeFloat",
    "PositiveFloat",
    "PositiveVec3",
    "StrictBool",
    "StrictInt",
    "Vec3",
    "numpy_scalar",
    "error_at",
    "ndarray_to_list",
    "raise_errors",
    "unit_vector",
]


def _require_discriminator(schema: dict[str, Any], cls: type[Any]) -> None:
    # A variant's ``type`` has a default for Python callers, but in a document it is what
    # selects the variant, so the JSON Schema must list it as required.
    if "type" in schema.get("properties", {}):
        required = schema.setdefault("required", [])
        if "type" not in required:
            required.insert(0, "type")


class FrozenModel(BaseModel):
    """Base of every schema model: unknown fields are errors, instances are immutable.

    ``use_attribute_docstrings`` turns the docstring under each field into its JSON
    Schema description, so the schema documents units and conventions.
    """

    model_config = ConfigDict(
        extra="forbid",
        frozen=True,
        use_attribute_docstrings=True,
        json_schema_extra=_require_discriminator,
    )


def numpy_scalar(value: Any) -> Any:
    """Before-validator: numpy integers/booleans become int/bool (strict mode rejects them).

    Place it *after* the ``Field(strict=True, ge=..., le=...)`` in an Annotated type:
    bounds added after a before-validator become non-standard ``ge``/``le`` keys in the
    JSON Schema.
    """
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    return value


def ndarray_to_list(value: Any) -> Any:
    """Accept numpy arrays for bulk fields by converting them to nested lists first."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    return value


FiniteFloat = Annotated[float, Field(strict=True, allow_inf_nan=False)]
"""Any finite number (JSON integers accepted; booleans, strings, NaN, Inf rejected)."""

NonNegativeFloat = Annotated[float, Field(strict=True, allow_inf_nan=False, ge=0)]
PositiveFloat = Annotated[float, Field(strict=True, allow_inf_nan=False, gt=0)]

StrictInt = Annotated[int, Field(strict=True), BeforeValidator(numpy_scalar)]
"""An integer; JSON ``3.0``, ``"3"`` and ``true`` are rejected."""


StrictBool = Annotated[bool, Field(strict=True), BeforeValidator(numpy_scalar)]
"""JSON true/false only (not 0/1 or "yes")."""

Vec3 = tuple[FiniteFloat, FiniteFloat, FiniteFloat]
"""Three finite numbers ``[x, y, z]``."""

PositiveVec3 = tuple[PositiveFloat, PositiveFloat, PositiveFloat]
"""Three finite numbers, each > 0."""

RGB = tuple[NonNegativeFloat, NonNegativeFloat, NonNegativeFloat]
"""Linear RGB: exactly three finite numbers >= 0 (no single-number grey shorthand)."""

NAME_PATTERN = r"^[A-Za-z0-9_.-]+$"
Name = Annotated[str, StringConstraints(min_length=1, max_length=64, pattern=NAME_PATTERN)]
"""Identifier of a material, object or light: 1..64 characters of ``[A-Za-z0-9_.-]``."""


Loc = tuple[str | int, ...]


def error_at(loc: Loc, error_type: str, message: str, input_value: Any) -> InitErrorDetails:
    """One error located at ``loc`` relative to the model being validated.

    ``message`` is used verbatim: without a context pydantic does not format it.
    """
    return InitErrorDetails(type=PydanticCustomError(error_type, message), loc=loc, input=input_value)


def raise_errors(title: str, errors: Sequence[InitErrorDetails]) -> None:
    """Raise ``errors`` (if any) as one ValidationError.

    Raised inside a validator, pydantic re-roots the locations under the field being
    validated, so a Scene-level check can point at ``objects.3.material``.
    """
    if errors:
        raise ValidationError.from_exception_data(title, list(errors))


def unit_vector(v: Iterable[float]) -> tuple[float, float, float] | None:
    """``v / |v|`` without overflow or underflow, or None for a zero vector."""
    x, y, z = (float(c) for c in v)
    m = max(abs(x), abs(y), abs(z))
    if m == 0.0 or not math.isfinite(m):
        return None
    x, y, z = x / m, y / m, z / m
    n = math.hypot(x, y, z)
    return (x / n, y / n, z / n)
