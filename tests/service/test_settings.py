"""Gateway settings read from the environment, and which addresses count as loopback."""

from __future__ import annotations

import os

from service.settings import Settings, is_loopback


def test_settings_from_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("RANGERET_DATA_ROOTS", f"{tmp_path}{os.pathsep}{tmp_path / 'b'}")
    monkeypatch.setenv("RANGERET_API_TOKEN", "")
    monkeypatch.setenv("RANGERET_RETENTION", "90")
    settings = Settings()
    assert settings.data_roots == [tmp_path.resolve(), (tmp_path / "b").resolve()]
    assert settings.token is None and settings.retention.total_seconds() == 90
    assert settings.address_problem() is None
    assert "RANGERET_API_TOKEN" in Settings(host="0.0.0.0").address_problem()
    assert Settings(host="0.0.0.0", api_token="t").address_problem() is None
    monkeypatch.setenv("RANGERET_DATA_ROOTS", f'["{tmp_path}"]')
    assert Settings().data_roots == [tmp_path.resolve()]
    assert is_loopback("127.0.0.2") and is_loopback("::1") and is_loopback("localhost")
    assert not is_loopback("10.0.0.1") and not is_loopback("example.org")
