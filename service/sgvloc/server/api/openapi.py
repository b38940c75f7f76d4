"""OpenAPI documentation of bodies the routes parse themselves (JSON or MessagePack)."""

from __future__ import annotations

from typing import Any

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi
from pydantic import BaseModel

from sgvloc_client import wire

from .schemas import ErrorOut

_REF = "#/components/schemas/{model}"
_BODY_MODELS: dict[str, type[BaseModel]] = {}


def body_doc(model: type[BaseModel]) -> dict[str, Any]:
    """``openapi_extra`` for a route whose body is ``model`` in JSON or MessagePack."""
    _BODY_MODELS[model.__name__] = model
    schema = {"$ref": _REF.format(model=model.__name__)}
    return {
        "requestBody": {
            "required": True,
            "content": {wire.JSON: {"schema": schema}, wire.MSGPACK: {"schema": schema}},
        }
    }


#: errors every protected route can answer: no/unknown key, role or map not allowed, and
#: invalid path parameters, and (routes that use the maps) still loading or no worker free
COMMON_ERRORS = (401, 403, 422, 503)


def error_responses(*statuses: int, common: bool = True) -> dict[int | str, dict[str, Any]]:
    """``responses=`` entries documenting the error body for ``statuses`` (plus
    :data:`COMMON_ERRORS` unless ``common`` is false)."""
    every = sorted({*statuses, *(COMMON_ERRORS if common else ())})
    return {s: {"model": ErrorOut, "description": "error"} for s in every}


def install_openapi(app: FastAPI) -> None:
    """Add the body models' schemas to the generated document's components."""

    def openapi() -> dict[str, Any]:
        if app.openapi_schema:
            return app.openapi_schema
        doc = get_openapi(
            title=app.title, version=app.version, description=app.description, routes=app.routes
        )
        schemas = doc.setdefault("components", {}).setdefault("schemas", {})
        for name, model in _BODY_MODELS.items():
            schema = model.model_json_schema(ref_template=_REF)
            schemas.update(schema.pop("$defs", {}))
            schemas[name] = schema
        app.openapi_schema = doc
        return doc

    app.openapi = openapi  # type: ignore[method-assign]
