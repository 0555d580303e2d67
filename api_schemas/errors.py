"""Turn pydantic validation errors into flat ``{"field", "message", "type"}`` records.

Pydantic puts the chosen variant's tag into the location of errors inside a
discriminated union: ``('objects', 2, 'sphere', 'radius')``. A user wrote
``objects[2].radius``, so the tag is dropped: ``"objects.2.radius"``. Tags are
recognised by walking the model's type annotations along the location, so a dict key
that happens to equal a tag (an object named ``sphere`` in ``animation.objects``) is
kept.
"""

from __future__ import annotations

import types
import typing
from collections.abc import Iterable, Mapping, Sequence
from typing import Annotated, Any, Literal, TypedDict, Union

from pydantic import BaseModel, ValidationError
from pydantic.fields import FieldInfo

__all__ = ["FieldError", "field_path", "format_error_details", "format_validation_error"]

_TAG_ERRORS = frozenset({"union_tag_invalid", "union_tag_not_found"})


class FieldError(TypedDict):
    field: str
    """Dot-joined location, list indices included: ``objects.2.radius`` ('' = the document)."""
    message: str
    type: str


def format_validation_error(exc: ValidationError, root: type[BaseModel] | None = None) -> list[FieldError]:
    """One record per error of ``exc``.

    ``root`` is the model that was validated; by default it is looked up by the error's
    title among this package's models (``Scene``, ``Material``, ...).
    """
    if root is None:
        root = _models_by_name().get(exc.title)
    return format_error_details(exc.errors(include_url=False), root)


def format_error_details(errors: Iterable[Mapping[str, Any]], root: Any = None) -> list[FieldError]:
    """Like :func:`format_validation_error` for already-extracted error dicts (for example
    FastAPI's ``RequestValidationError.errors()``; pass the body model as ``root`` and
    strip the leading ``"body"`` from the locations first)."""
    out: list[FieldError] = []
    for err in errors:
        loc = tuple(err.get("loc", ()))
        path = _clean_loc(loc, root)
        if err.get("type") in _TAG_ERRORS:
            # The error sits on the object; the field to fix is its discriminator.
            ctx = err.get("ctx") or {}
            path.append(str(ctx.get("discriminator", "type")).strip("'\""))
        out.append(
            FieldError(
                field=".".join(str(p) for p in path),
                message=str(err.get("msg", "")),
                type=str(err.get("type", "")),
            )
        )
    return out


def field_path(loc: Sequence[str | int], root: Any = None) -> str:
    """Dot-joined location with discriminated-union tags removed."""
    return ".".join(str(p) for p in _clean_loc(tuple(loc), root))


# --------------------------------------------------------------------------- internals


def _models_by_name() -> dict[str, type[BaseModel]]:
    from api_schemas import scene  # late: scene imports common, not errors

    return {
        obj.__name__: obj
        for obj in vars(scene).values()
        if isinstance(obj, type) and issubclass(obj, BaseModel) and obj.__module__ == scene.__name__
    }


def _unwrap(tp: Any, discriminator: str | None) -> tuple[Any, str | None]:
    """Strip Annotated (picking up a Field discriminator) and Optional."""
    while True:
        if typing.get_origin(tp) is Annotated:
            base, *meta = typing.get_args(tp)
            for m in meta:
                if isinstance(m, FieldInfo) and isinstance(m.discriminator, str):
                    discriminator = m.discriminator
            tp = base
            continue
        if _is_union(tp):
            members = [a for a in typing.get_args(tp) if a is not type(None)]
            if len(members) == 1:  # Optional[X]: pydantic adds no location element
                tp = members[0]
                continue
        return tp, discriminator


def _is_union(tp: Any) -> bool:
    return typing.get_origin(tp) in (Union, types.UnionType)


def _variants_by_tag(tp: Any, discriminator: str) -> dict[str, Any]:
    tags: dict[str, Any] = {}
    for member in typing.get_args(tp):
        member, _ = _unwrap(member, None)
        if isinstance(member, type) and issubclass(member, BaseModel):
            field = member.model_fields.get(discriminator)
            if field is not None and typing.get_origin(field.annotation) is Literal:
                for value in typing.get_args(field.annotation):
                    tags[str(value)] = member
    return tags


def _clean_loc(loc: tuple[str | int, ...], root: Any) -> list[str | int]:
    if root is None:
        return _clean_loc_heuristic(loc)
    out: list[str | int] = []
    tp: Any = root
    discriminator: str | None = None
    for i, elem in enumerate(loc):
        if tp is None:
            out.extend(loc[i:])
            break
        tp, discriminator = _unwrap(tp, discriminator)
        if discriminator is not None and _is_union(tp):
            variants = _variants_by_tag(tp, discriminator)
            discriminator = None
            if isinstance(elem, str) and elem in variants:
                tp = variants[elem]
                continue  # the tag: dropped
            tp = None
        out.append(elem)
        tp, discriminator = _child(tp, elem)
    return out


def _child(tp: Any, elem: str | int) -> tuple[Any, str | None]:
    """Type found at ``elem`` inside ``tp`` (None when unknown)."""
    if isinstance(tp, type) and issubclass(tp, BaseModel):
        field = tp.model_fields.get(str(elem))
        if field is None:
            return None, None
        disc = field.discriminator if isinstance(field.discriminator, str) else None
        # field.annotation has the outer Annotated metadata merged into the FieldInfo,
        # hence the discriminator is taken from the field itself.
        return field.annotation, disc
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (list, set, frozenset) and args and isinstance(elem, int):
        return args[0], None
    if origin is tuple and args and isinstance(elem, int):
        if len(args) == 2 and args[1] is Ellipsis:
            return args[0], None
        return (args[elem], None) if 0 <= elem < len(args) else (None, None)
    if origin is dict and len(args) == 2:
        return (None, None) if elem == "[key]" else (args[1], None)
    return None, None


def _known_tags() -> frozenset[str]:
    from api_schemas import scene

    tags: set[str] = set()
    for union in (scene.Camera, scene.SceneObject, scene.Light):
        tp, disc = _unwrap(union, None)
        if disc is not None:
            tags.update(_variants_by_tag(tp, disc))
    return frozenset(tags)


def _clean_loc_heuristic(loc: tuple[str | int, ...]) -> list[str | int]:
    """Without a root model: drop a known tag that starts the location (a bare union was
    validated) or follows a list index or ``camera``."""
    tags = _known_tags()
    out: list[str | int] = []
    for i, elem in enumerate(loc):
        prev = loc[i - 1] if i else None
        if isinstance(elem, str) and elem in tags and (i == 0 or isinstance(prev, int) or prev == "camera"):
            continue
        out.append(elem)
    return out
