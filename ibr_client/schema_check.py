"""Does this client's copy of the models agree with a server's ``/openapi.json``?

The client validates every answer with the models of ``api_schemas`` and builds its requests from
the same models' fields; a server built from another version may name or type a field otherwise.
:func:`model_drift` compares, field by field, each model the server documents under
``components/schemas`` with the client's model of the same name: the field names, which are
required, and each field's type (its JSON Schema without titles, descriptions, examples and
defaults). It also requires every model the client reads from answers (:data:`CLIENT_MODELS`) and
every request body the server takes to have a client model.

    python -m ibr_client.schema_check http://127.0.0.1:8000    # exit 1 and one line per mismatch
"""

from __future__ import annotations

import importlib
import inspect
import pkgutil
import sys
from collections.abc import Iterable, Mapping
from typing import Any

from pydantic import BaseModel

__all__ = ["CLIENT_MODELS", "client_models", "model_drift"]

MODEL_PACKAGE = "api_schemas"
"""The package whose models the client carries (the wire format): every module of it."""

CLIENT_MODULES = ("ibr_client.client", "ibr_client.cli")
"""The client's own modules: every model they import is one the client uses."""

_NOT_TYPES = frozenset({"title", "description", "examples", "example", "default", "deprecated"})
"""Schema keywords that document a field rather than type it."""


def client_models() -> dict[str, type[BaseModel]]:
    """Every model of :data:`MODEL_PACKAGE`'s modules, by class name (a name two modules define is
    left out: the server would document it under a longer name)."""
    found: dict[str, type[BaseModel]] = {}
    twice: set[str] = set()
    package = importlib.import_module(MODEL_PACKAGE)
    for info in pkgutil.iter_modules(package.__path__):
        module = f"{MODEL_PACKAGE}.{info.name}"
        for name, obj in vars(importlib.import_module(module)).items():
            if inspect.isclass(obj) and issubclass(obj, BaseModel) and obj.__module__ == module:
                if name in found and found[name] is not obj:
                    twice.add(name)
                found[name] = obj
    return {k: v for k, v in found.items() if k not in twice}


def _used_models() -> list[str]:
    names: set[str] = set()
    for module in CLIENT_MODULES:
        for name, obj in vars(importlib.import_module(module)).items():
            if inspect.isclass(obj) and issubclass(obj, BaseModel) and obj.__module__.startswith("api_schemas."):
                names.add(name)
    return sorted(names)


CLIENT_MODELS: list[str] = _used_models()
"""The models the client's code reads answers with or validates local files with."""


def _base(ref_or_name: str) -> str:
    """``#/components/schemas/Scene-Input`` or ``Scene-Output`` -> ``Scene``."""
    name = ref_or_name.rsplit("/", 1)[-1]
    for side in ("-Input", "-Output"):
        if name.endswith(side):
            return name[: -len(side)]
    return name


def _typing(schema: Any) -> Any:
    """The parts of a schema that type a value: documentation dropped, references by model name."""
    if isinstance(schema, dict):
        out: dict[str, Any] = {}
        for k, v in schema.items():
            if k in _NOT_TYPES:
                continue
            if k == "$ref" and isinstance(v, str):
                out[k] = _base(v)
            elif k == "mapping" and isinstance(v, dict):
                out[k] = {tag: _base(ref) for tag, ref in v.items()}
            elif k == "properties" and isinstance(v, dict):
                out[k] = {name: _typing(prop) for name, prop in v.items()}
            else:
                out[k] = _typing(v)
        return out
    if isinstance(schema, list):
        return [_typing(x) for x in schema]
    return schema


def _own_schema(model: type[BaseModel], mode: str) -> dict[str, Any]:
    schema = model.model_json_schema(mode="serialization" if mode == "serialization" else "validation",
                                     ref_template="#/components/schemas/{model}")
    schema.pop("$defs", None)
    return schema


def _compare(component: str, theirs: Mapping[str, Any], mine: Mapping[str, Any]) -> list[str]:
    problems: list[str] = []
    t_props: Mapping[str, Any] = theirs.get("properties", {})
    m_props: Mapping[str, Any] = mine.get("properties", {})
    for name in sorted(set(t_props) - set(m_props)):
        problems.append(f"{component}.{name}: the server has this field, the client's model does not")
    for name in sorted(set(m_props) - set(t_props)):
        problems.append(f"{component}.{name}: the client's model has this field, the server's does not")
    for name in sorted(set(t_props) & set(m_props)):
        t, m = _typing(t_props[name]), _typing(m_props[name])
        if t != m:
            problems.append(f"{component}.{name}: the server types it {t}, the client {m}")
    t_req, m_req = set(theirs.get("required", [])), set(mine.get("required", []))
    if t_req != m_req:
        problems.append(f"{component}: required fields differ: server {sorted(t_req)}, client {sorted(m_req)}")
    rest_t = _typing({k: v for k, v in theirs.items() if k not in ("properties", "required")})
    rest_m = _typing({k: v for k, v in mine.items() if k not in ("properties", "required")})
    if rest_t != rest_m:
        problems.append(f"{component}: the server's schema is {rest_t}, the client's {rest_m}")
    return problems


def _request_bodies(openapi: Mapping[str, Any]) -> Iterable[tuple[str, str]]:
    """(operation, component name) of every request body given by reference."""
    for path, ops in openapi.get("paths", {}).items():
        for method, op in ops.items():
            content = (op.get("requestBody") or {}).get("content", {}) if isinstance(op, dict) else {}
            for media in content.values():
                ref = (media.get("schema") or {}).get("$ref")
                if isinstance(ref, str):
                    yield f"{method.upper()} {path}", ref.rsplit("/", 1)[-1]


def model_drift(openapi: Mapping[str, Any], models: Mapping[str, type[BaseModel]] | None = None) -> list[str]:
    """One line per disagreement between ``openapi`` (a server's document) and the client's
    ``models`` (default: :func:`client_models`); empty when they agree."""
    models = client_models() if models is None else models
    components: Mapping[str, Any] = openapi.get("components", {}).get("schemas", {})
    problems: list[str] = []
    documented: set[str] = set()
    for name, schema in sorted(components.items()):
        model = models.get(_base(name))
        if model is None:
            continue
        documented.add(_base(name))
        mode = "serialization" if name.endswith("-Output") else "validation"
        problems += _compare(name, schema, _own_schema(model, mode))
    for name in CLIENT_MODELS:
        if name in models and name not in documented:
            problems.append(f"{name}: the client reads this model, the server documents no such model")
    for op, name in _request_bodies(openapi):
        if _base(name) not in models:
            problems.append(f"{op}: the request body {name} has no client model")
    return problems


def main(argv: list[str] | None = None) -> int:
    import httpx

    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print("usage: python -m ibr_client.schema_check API_URL", file=sys.stderr)
        return 2
    doc = httpx.get(args[0].rstrip("/") + "/openapi.json", timeout=30).raise_for_status().json()
    problems = model_drift(doc)
    for line in problems:
        print(line)
    n = len({_base(k) for k in doc.get("components", {}).get("schemas", {})} & set(client_models()))
    print(f"{n} models compared, {len(problems)} mismatches", file=sys.stderr)
    return 1 if problems else 0


if __name__ == "__main__":
    raise SystemExit(main())
