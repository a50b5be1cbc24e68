"""GET /metrics: Prometheus families a lab's monitoring scrapes, read with prometheus-client's own parser."""

from __future__ import annotations

import time

from prometheus_client.parser import text_string_to_metric_families

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

    frames_before = value(first, "tiltlab_serial_frames", "tiltlab_serial_frames_total", role="measurement_sensor")
    for _ in range(3):
        assert client.get("/tilt", headers=headers).status_code == 200
    with client.websocket_connect(f"/ws/readings?token={headers['Authorization'].split()[1]}") as ws:
        ws.receive_json()  # the snapshot: the client is registered
        deadline = time.monotonic() + 30
        while True:  # the sensors stream on their own: the frame counter moves with them
            later = scrape(client, headers)
            frames = value(later, "tiltlab_serial_frames", "tiltlab_serial_frames_total", role="measurement_sensor")
            if frames > frames_before:
                break
            assert time.monotonic() < deadline, "no new frame counted in 30 s"
        assert value(later, "tiltlab_websocket_clients", "tiltlab_websocket_clients") == 1
        ws.close()  # closed here, not by leaving the block while the stream's sender may be mid-send
    tilt_requests = value(later, "tiltlab_http_requests", "tiltlab_http_requests_total", route="/tilt",
                          method="GET", status="200")
    assert tilt_requests == 3  # by route template and status, one per request
    assert value(later, "tiltlab_http_request_duration_seconds", "tiltlab_http_request_duration_seconds_count",
                 route="/tilt", method="GET") == 3
    scrapes = value(later, "tiltlab_http_requests", "tiltlab_http_requests_total", route="/metrics",
                         method="GET", status="200")
    assert scrapes >= 1
    assert value(later, "tiltlab_jobs", "tiltlab_jobs", state="succeeded") == 0
