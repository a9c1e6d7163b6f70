"""The old home of ``create_app`` (``uvicorn quicknav_service.api.app:create_app``): kept for one release;
the factory is ``quicknav_service.api.main:create_app``."""

from quicknav_service.api.main import create_app

__all__ = ["create_app"]
