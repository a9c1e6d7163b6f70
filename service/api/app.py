"""The old home of ``create_app`` (``uvicorn service.api.app:create_app``): kept for one release;
the factory is ``service.api.main:create_app``."""

from service.api.main import create_app

__all__ = ["create_app"]
