"""Service settings from QUICKNAV_* variables: validated, with errors naming the variable."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from quicknav_service.settings import Settings


def test_settings__empty_variable_means_unset(monkeypatch):
    monkeypatch.setenv("QUICKNAV_API_TOKEN", "")
    monkeypatch.setenv("QUICKNAV_GRPC_PORT", "50123")
    s = Settings()
    assert s.api_token is None and s.grpc_port == 50123


def test_settings__bad_values_are_refused(monkeypatch):
    monkeypatch.setenv("QUICKNAV_API_TOKEN", "short")
    with pytest.raises(ValidationError, match="api_token"):
        Settings()
    monkeypatch.delenv("QUICKNAV_API_TOKEN")
    monkeypatch.setenv("QUICKNAV_HEARTBEAT_S", "30")
    monkeypatch.setenv("QUICKNAV_LEASE_S", "10")
    with pytest.raises(ValidationError, match="QUICKNAV_HEARTBEAT_S=30"):
        Settings()
