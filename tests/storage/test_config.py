from __future__ import annotations

from pathlib import Path

import pytest

from service.config import Settings
from service.errors import InputError


def test_defaults_put_sqlite_file_in_data_dir(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.delenv("TILTLAB_DATABASE_URL", raising=False)
    monkeypatch.delenv("TILTLAB_CONFIG", raising=False)
    monkeypatch.setenv("TILTLAB_DATA_DIR", str(tmp_path / "d"))
    s = Settings()
    assert s.data_dir == tmp_path / "d"
    assert s.database_url == f"sqlite:///{(tmp_path / 'd' / 'tiltlab.db').as_posix()}"
    assert (s.host, s.port) == ("127.0.0.1", 8000)


def test_environment_overrides_config_file(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    cfg = tmp_path / "tiltlab.toml"
    cfg.write_text(
        'port = 9001\nmonitoring_retention_days = 7\ndatabase_url = "sqlite:////tmp/x.db"\n'
    )
    monkeypatch.setenv("TILTLAB_CONFIG", str(cfg))
    monkeypatch.setenv("TILTLAB_PORT", "9002")
    monkeypatch.delenv("TILTLAB_DATABASE_URL", raising=False)
    s = Settings()
    assert s.port == 9002
    assert s.monitoring_retention_days == 7
    assert s.database_url == "sqlite:////tmp/x.db"


def test_missing_config_file_is_an_input_error(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.setenv("TILTLAB_CONFIG", str(tmp_path / "nope.toml"))
    with pytest.raises(InputError, match="nope.toml"):
        Settings()


def test_batch_larger_than_queue_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("TILTLAB_CONFIG", raising=False)
    with pytest.raises(ValueError, match="sample_batch_size"):
        Settings(sample_queue_capacity=10, sample_batch_size=100)


def test_unusable_value_is_one_line_naming_the_setting(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("TILTLAB_CONFIG", raising=False)
    monkeypatch.setenv("TILTLAB_PORT", "abc")
    with pytest.raises(InputError, match="TILTLAB_PORT.*'abc'") as err:
        Settings()
    assert "\n" not in str(err.value)


def test_unparsable_config_file_is_named(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    cfg = tmp_path / "tiltlab.toml"
    cfg.write_text("port = \n")
    monkeypatch.setenv("TILTLAB_CONFIG", str(cfg))
    with pytest.raises(InputError, match="tiltlab.toml.*not valid TOML"):
        Settings()


def test_known_keys_of_the_settings_file_are_taken(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    cfg = tmp_path / "tiltlab.toml"
    cfg.write_text("max_body_bytes = 65536\nsim_speed = 4.0\n")
    monkeypatch.setenv("TILTLAB_CONFIG", str(cfg))
    monkeypatch.delenv("TILTLAB_MAX_BODY_BYTES", raising=False)
    monkeypatch.delenv("TILTLAB_SIM_SPEED", raising=False)
    s = Settings()
    assert (s.max_body_bytes, s.sim_speed) == (65536, 4.0)
    cfg.write_text("max_body_bytes = 65536\nmax_body_byte = 1\n")
    with pytest.raises(
        InputError, match=r"max_body_byte: no such setting \(did you mean max_body_bytes\?\)"
    ):
        Settings()
