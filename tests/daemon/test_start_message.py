"""Every start says where the dashboard is and where its token comes from, never printing the token again."""

from __future__ import annotations

from tests.daemon.conftest import make_client


def test_later_starts_name_the_dashboard_and_the_token_file(tmp_path, capsys):
    with make_client(tmp_path):
        pass
    token = (tmp_path / "admin.token").read_text().strip()
    capsys.readouterr()
    with make_client(tmp_path):
        err = capsys.readouterr().err
    assert "tiltlab: dashboard: http://127.0.0.1:8000/" in err and str(tmp_path / "admin.token") in err
    assert token not in err
    (tmp_path / "admin.token").unlink()
    with make_client(tmp_path):
        assert "tiltlab token create" in capsys.readouterr().err


def test_without_authentication_the_dashboard_is_named(tmp_path, capsys):
    with make_client(tmp_path, auth="none"):
        err = capsys.readouterr().err
    assert "tiltlab: dashboard: http://127.0.0.1:8000/ (authentication off)" in err
    assert not (tmp_path / "admin.token").exists()
