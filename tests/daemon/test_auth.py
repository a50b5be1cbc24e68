"""First-start admin token file, authentication off only on loopback."""

from __future__ import annotations

import stat

import pytest

from service.api.app import create_app
from service.config import Settings
from service.errors import InputError
from tests.helpers.daemon import make_client
from tests.helpers.waiting import eventually


def test_first_start_writes_the_admin_token_once_with_mode_0600(tmp_path, capsys):
    with make_client(tmp_path) as client:
        path = tmp_path / "admin.token"
        token = path.read_text().strip()
        assert stat.S_IMODE(path.stat().st_mode) == 0o600
        err = capsys.readouterr().err  # not a terminal: the file is named, the token is not shown
        assert token not in err and f"admin token written to {path} (mode 0600)" in err
        assert f"dashboard: http://127.0.0.1:8000/ (token: the admin token in {path})" in err
        assert (
            client.get("/benches", headers={"Authorization": f"Bearer {token}"}).status_code == 200
        )
        r = client.get("/benches")
        assert r.status_code == 401 and r.headers["www-authenticate"].startswith("Bearer")
        assert client.get("/health").status_code == 200  # no token needed
    with make_client(tmp_path):
        # not replaced: the database has tokens
        assert (tmp_path / "admin.token").read_text().strip() == token
        assert "#token=" not in capsys.readouterr().err


def test_auth_none_only_on_loopback(tmp_path):
    with pytest.raises(InputError, match="TILTLAB_AUTH=none is refused on 0.0.0.0"):
        create_app(Settings(data_dir=tmp_path, auth="none", host="0.0.0.0"))
    with make_client(tmp_path, auth="none") as client:
        assert client.get("/tilt").status_code == 200
        assert not (tmp_path / "admin.token").exists()


def test_ready_needs_no_token_and_names_a_lost_instrument(tmp_path):
    with make_client(tmp_path) as client:
        assert client.get("/ready").json() == {"ready": True, "reasons": []}
        bench = client.app.state.bench
        bench.sim.faults("reference_sensor").disconnect(3.0)
        r = eventually(
            lambda: client.get("/ready"),
            until=lambda r: r.status_code != 200,
            timeout_s=10,
            every_s=0.05,
            what="/ready no longer ready",
        )
        assert r.status_code == 503 and any(
            "reference_sensor on " + bench.port_of("reference_sensor") in x
            for x in r.json()["reasons"]
        )
