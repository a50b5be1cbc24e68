"""GET /metrics: Prometheus families a lab's monitoring scrapes, read with prometheus-client's own
parser."""

from __future__ import annotations

from prometheus_client.parser import text_string_to_metric_families

from tests.helpers.waiting import eventually

FAMILIES = {
    "tiltlab_http_requests": "counter",
    "tiltlab_http_request_duration_seconds": "histogram",
    "tiltlab_serial_frames": "counter",
    "tiltlab_serial_bad_checksums": "counter",
    "tiltlab_serial_timeouts": "counter",
    "tiltlab_serial_reconnects": "counter",
    "tiltlab_device_connected": "gauge",
    "tiltlab_jobs": "gauge",
    "tiltlab_websocket_clients": "gauge",
    "tiltlab_websocket_dropped_messages": "counter",
    "tiltlab_sample_writer_queue_depth": "gauge",
}


def scrape(client, headers) -> dict:
    answer = client.get("/metrics", headers=headers)
    assert answer.status_code == 200, answer.text
    assert answer.headers["content-type"].startswith("text/plain")
    return {f.name: f for f in text_string_to_metric_families(answer.text)}


def value(families: dict, family: str, sample: str, **labels: str) -> float:
    for s in families[family].samples:
        if s.name == sample and all(s.labels.get(k) == v for k, v in labels.items()):
            return float(s.value)
    raise AssertionError(f"no sample {sample} {labels} in {families[family].samples}")


def test_metrics_need_a_token(daemon) -> None:
    client, _ = daemon
    assert client.get("/metrics").status_code == 401


def test_the_contracts_families_are_there_and_move_with_the_bench(daemon) -> None:
    client, headers = daemon
    first = scrape(client, headers)
    for name, kind in FAMILIES.items():
        assert name in first, f"{name} missing from /metrics"
        assert first[name].type == kind, (name, first[name].type)
    roles = {s.labels["role"] for s in first["tiltlab_serial_frames"].samples}
    assert {"measurement_sensor", "reference_sensor"} <= roles

    frames_before = value(
        first, "tiltlab_serial_frames", "tiltlab_serial_frames_total", role="measurement_sensor"
    )
    for _ in range(3):
        assert client.get("/tilt", headers=headers).status_code == 200
    with client.websocket_connect(
        f"/ws/readings?token={headers['Authorization'].split()[1]}"
    ) as ws:
        ws.receive_json()  # the snapshot: the client is registered

        def a_new_frame_counted() -> dict | None:
            families = scrape(client, headers)
            frames = value(
                families,
                "tiltlab_serial_frames",
                "tiltlab_serial_frames_total",
                role="measurement_sensor",
            )
            return families if frames > frames_before else None

        # the sensors stream on their own: the frame counter moves with them
        later = eventually(a_new_frame_counted, timeout_s=30, every_s=0, what="a new frame counted")
        assert value(later, "tiltlab_websocket_clients", "tiltlab_websocket_clients") == 1
        # closed here, not by leaving the block while the stream's sender may be mid-send
        ws.close()
    tilt_requests = value(
        later,
        "tiltlab_http_requests",
        "tiltlab_http_requests_total",
        route="/tilt",
        method="GET",
        status="200",
    )
    assert tilt_requests == 3  # by route template and status, one per request
    assert (
        value(
            later,
            "tiltlab_http_request_duration_seconds",
            "tiltlab_http_request_duration_seconds_count",
            route="/tilt",
            method="GET",
        )
        == 3
    )
    scrapes = value(
        later,
        "tiltlab_http_requests",
        "tiltlab_http_requests_total",
        route="/metrics",
        method="GET",
        status="200",
    )
    assert scrapes >= 1
    assert value(later, "tiltlab_jobs", "tiltlab_jobs", state="succeeded") == 0


def test_device_series_keep_their_labels_across_restarts_and_the_port_is_an_info(tmp_path) -> None:
    """Counters by bench and role only: a simulator's new pseudo-terminal at the next start makes no
    new series. Where the instrument is connected and what it said it is are the labels of
    tiltlab_device_info."""
    from tests.helpers.daemon import admin_headers, make_client

    keys = []
    # the same data directory, started twice: each start opens new pseudo-terminals
    for _ in range(2):
        with make_client(tmp_path, sim_transport="pty") as client:
            families = scrape(client, admin_headers(tmp_path))
            keys.append(
                sorted(
                    tuple(sorted(s.labels.items()))
                    for s in families["tiltlab_serial_frames"].samples
                    if s.name == "tiltlab_serial_frames_total"
                )
            )
            info = {s.labels["role"]: s.labels for s in families["tiltlab_device_info"].samples}
            ports = {
                d["role"]: d["port"]
                for d in client.get("/devices", headers=admin_headers(tmp_path)).json()["devices"]
            }
            for role, port in ports.items():
                assert info[role]["port"] == port and info[role]["bench"] == "sim-stage"
            assert info["measurement_sensor"]["model"] == "0x68 binary inclinometer"
    assert keys[0] == keys[1] and all(set(dict(k)) == {"bench", "role"} for k in keys[0]), keys


def test_static_files_are_counted_by_their_folder(daemon) -> None:
    client, headers = daemon
    assert client.get("/web/dashboard.css").status_code == 200
    families = scrape(client, headers)
    assert (
        value(
            families,
            "tiltlab_http_requests",
            "tiltlab_http_requests_total",
            route="/web/{path}",
            method="GET",
            status="200",
        )
        >= 1
    )


def test_an_instrument_without_a_serial_number_is_shown_as_it_reported_itself(daemon) -> None:
    """Family A answers at its bus address and reports no serial: /devices says so, and says the
    port apart."""
    client, headers = daemon
    devices = {d["role"]: d for d in client.get("/devices", headers=headers).json()["devices"]}
    ident = devices["measurement_sensor"]["identity"]
    assert ident["serial"] is None and ident["address"] == "0x00", ident
    assert devices["measurement_sensor"]["port"] and devices["measurement_sensor"][
        "port"
    ] not in str(ident)
    assert devices["stage"]["identity"]["serial"], devices["stage"]
